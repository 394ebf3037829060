"""Naive float64 re-implementations of the sparse layers of the authors' encoders (``EricLiuhhh/MSSF``).

Written from the definitions, independent of spconv: a voxel set is a dict ``(b, z, y, x) -> feature``;
every output site is computed by a loop over the kernel taps, as a 3D cross-correlation
(``out[q] = sum_k W[:, k, :] @ in[s * q - pad + k]``; spconv's weight layout ``(C_out, kz, ky, kx, C_in)``).
The layers, as their source builds them:

* ``make_sparse_convmodule``: conv (no bias), ``BN1d(eps=1e-3)``, ReLU; keys ``<p>.0.weight``, ``<p>.1.*``;
* mmdet3d's ``SparseBasicBlock``: ``relu(bn2(conv2(relu(bn1(conv1(x))))) + x)``, submanifold 3x3x3 convs
  without bias; keys ``conv1.weight``, ``bn1.*``, ``conv2.weight``, ``bn2.*``.
"""

from __future__ import annotations

import itertools
from typing import Dict, Tuple

import torch

Site = Tuple[int, int, int, int]


def as_sites(features, coords) -> Dict[Site, torch.Tensor]:
    return {tuple(int(v) for v in c): features[i] for i, c in enumerate(coords)}


def bn_eval(x, sd, prefix, eps=1e-3):
    return (x - sd[f"{prefix}.running_mean"]) / torch.sqrt(sd[f"{prefix}.running_var"] + eps) * sd[
        f"{prefix}.weight"] + sd[f"{prefix}.bias"]


def subm_conv(sites: Dict[Site, torch.Tensor], weight) -> Dict[Site, torch.Tensor]:
    """Submanifold conv (kernel 3, padding 1): the output sites are the input sites."""
    k = weight.shape[1]
    out = {}
    for (b, z, y, x) in sites:
        acc = weight.new_zeros(weight.shape[0])
        for dz, dy, dx in itertools.product(range(k), repeat=3):
            nb = sites.get((b, z + dz - k // 2, y + dy - k // 2, x + dx - k // 2))
            if nb is not None:
                acc = acc + weight[:, dz, dy, dx, :] @ nb
        out[(b, z, y, x)] = acc
    return out


def strided_conv(sites: Dict[Site, torch.Tensor], weight, stride, padding, out_shape) -> Dict[Site, torch.Tensor]:
    """Regular sparse conv: an output site exists where at least one input site falls in its window."""
    k = weight.shape[1:4]
    out: Dict[Site, torch.Tensor] = {}
    for (b, z, y, x), f in sites.items():
        for dz, dy, dx in itertools.product(range(k[0]), range(k[1]), range(k[2])):
            q = []
            for p, d, s, pad, n in zip((z, y, x), (dz, dy, dx), stride, padding, out_shape):
                t = p + pad - d
                if t % s or not 0 <= t // s < n:
                    break
                q.append(t // s)
            else:
                key = (b, *q)
                out[key] = out.get(key, weight.new_zeros(weight.shape[0])) + weight[:, dz, dy, dx, :] @ f
    return out


def conv_module(sites, sd, prefix, stride=None, padding=None, out_shape=None, eps=1e-3):
    """Their ``make_sparse_convmodule``: conv, BN, ReLU (``stride=None``: submanifold)."""
    w = sd[f"{prefix}.0.weight"]
    y = subm_conv(sites, w) if stride is None else strided_conv(sites, w, stride, padding, out_shape)
    return {s: torch.relu(bn_eval(v, sd, f"{prefix}.1", eps)) for s, v in y.items()}


def basic_block(sites, sd, prefix, eps=1e-3):
    """mmdet3d's ``SparseBasicBlock`` (identity shortcut)."""
    h = {s: torch.relu(bn_eval(v, sd, f"{prefix}.bn1", eps)) for s, v in subm_conv(sites, sd[f"{prefix}.conv1.weight"]).items()}
    h = subm_conv(h, sd[f"{prefix}.conv2.weight"])
    return {s: torch.relu(bn_eval(v, sd, f"{prefix}.bn2", eps) + sites[s]) for s, v in h.items()}
