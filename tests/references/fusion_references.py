"""References and random inputs of the fusion tests (``tests/samplers/test_sff.py``, ``test_msdff.py``), written
independently of the code under test: per-level ``F.grid_sample`` on images projected pixel by pixel,
naive loops over voxels / cameras / heads, eval-mode BatchNorm as its affine formula.
"""

import pytest
import torch
import torch.nn.functional as F
from torch import nn

from mssf_blocks.samplers import MSDFF
from mssf_blocks.geometry import CentroidProjection


D64 = torch.float64
# MSDFF value widths: the paper's / authors' (value_dim = value_channels, the default) and the narrow
# layout (value_dim = embed_dim: the image projected down to the voxel width before the attention).
WIDTHS = [pytest.param("paper", id="paper_width"), pytest.param("narrow", id="narrow_width")]


def width_kw(width, embed_dim):
    """MSDFF keyword arguments of a value width of WIDTHS."""
    return {} if width == "paper" else {"value_dim": embed_dim}


def make_projection(uv, valid, batch_index, device=None):
    n, v = valid.shape
    uv, valid, batch_index = (t.to(device) for t in (uv, valid, batch_index))
    return CentroidProjection(
        uv=uv, depth=torch.ones(n, v, dtype=uv.dtype, device=uv.device), valid=valid,
        centroid=torch.zeros(n, 3, dtype=uv.dtype, device=uv.device),
        has_points=torch.ones(n, dtype=torch.bool, device=uv.device), batch_index=batch_index,
    )


def randomize_norm(norm: nn.BatchNorm1d, gen):
    with torch.no_grad():
        c = norm.num_features
        norm.running_mean.copy_(torch.randn(c, generator=gen, dtype=D64))
        norm.running_var.copy_(torch.rand(c, generator=gen, dtype=D64) + 0.5)
        norm.weight.copy_(torch.randn(c, generator=gen, dtype=D64))
        norm.bias.copy_(torch.randn(c, generator=gen, dtype=D64))


def ref_bn_eval(x, norm):
    return (x - norm.running_mean) / torch.sqrt(norm.running_var + norm.eps) * norm.weight + norm.bias


def grid_sample_at(img, uv):
    """Independent bilinear reference: img (C, H, W), uv (K, 2) normalised -> (K, C)."""
    grid = (2.0 * uv - 1.0).view(1, 1, -1, 2)
    return F.grid_sample(img[None], grid, mode="bilinear", padding_mode="zeros", align_corners=False)[0, :, 0].T


def scene(gen, b=2, v=2, n=7, chans=(3, 2), sizes=((5, 6), (3, 4))):
    """Random float64 levels (B, V, C, H, W), uv, valid mask (mixed), batch index."""
    levels = [torch.randn(b, v, c, h, w, generator=gen, dtype=D64) for c, (h, w) in zip(chans, sizes)]
    uv = torch.rand(n, v, 2, generator=gen, dtype=D64) * 0.9 + 0.05
    valid = torch.rand(n, v, generator=gen) > 0.3
    valid[0] = False  # seen by no camera
    valid[1] = True  # seen by all cameras
    if v > 1:
        valid[2] = torch.tensor([True] + [False] * (v - 1))
    batch_index = torch.randint(0, b, (n,), generator=gen)
    return levels, uv, valid, batch_index


# ---------------------------------------------------------------------------------------------------
# references
# ---------------------------------------------------------------------------------------------------
def reference_sff_sample(levels, uv, valid, batch_index):
    n, v = valid.shape
    out = torch.zeros(n, sum(l.shape[2] for l in levels), dtype=D64)
    for i in range(n):
        cams = [c for c in range(v) if valid[i, c]]
        for c in cams:
            row = [grid_sample_at(l[batch_index[i], c], uv[i, c][None])[0] for l in levels]
            out[i] += torch.cat(row) / len(cams)
    return out


def reference_msdff(mod: MSDFF, query, levels, uv, valid, batch_index):
    """Project every pixel with value_proj first, then per-level grid_sample (Deformable DETR's order)."""
    n, v = valid.shape
    e, m, lv, p = mod.value_dim, mod.num_heads, mod.num_levels, mod.num_points
    d = e // m
    off = (query @ mod.sampling_offsets.weight.T + mod.sampling_offsets.bias).view(n, m, lv, p, 2)
    att = (query @ mod.attention_weights.weight.T + mod.attention_weights.bias).view(n, m, lv * p)
    att = att.softmax(-1).view(n, m, lv, p)
    wv, bv = mod.value_proj.weight, mod.value_proj.bias
    projected = [torch.einsum("bvchw,ec->bvehw", l, wv) + bv[:, None, None] for l in levels]
    out = torch.zeros(n, e, dtype=D64)
    visible = valid.any(1)
    for i in range(n):
        cams = [c for c in range(v) if valid[i, c]]
        for c in cams:
            for h in range(m):
                for l in range(lv):
                    hl, wl = levels[l].shape[-2:]
                    loc = uv[i, c] + off[i, h, l] / torch.tensor([wl, hl], dtype=D64)
                    img = projected[l][batch_index[i], c, h * d:(h + 1) * d]
                    s = grid_sample_at(img, loc)  # (P, d)
                    out[i, h * d:(h + 1) * d] += (s * att[i, h, l][:, None]).sum(0) / len(cams)
    y = ref_bn_eval(out @ mod.output_proj.weight.T + mod.output_proj.bias, mod.norm)
    return torch.where(visible[:, None], y, torch.zeros_like(y)), off, att


def randomize_msdff(mod: MSDFF, gen, scale=0.5):
    with torch.no_grad():
        for lin in (mod.sampling_offsets, mod.attention_weights, mod.value_proj, mod.output_proj):
            lin.weight.copy_(torch.randn(lin.weight.shape, generator=gen, dtype=D64) * scale)
            lin.bias.copy_(torch.randn(lin.bias.shape, generator=gen, dtype=D64) * scale)
        mod.sampling_offsets.bias.mul_(4.0)  # offsets of a few pixels: some samples leave the image
    randomize_norm(mod.norm, gen)
