"""MSDFF: multi-scale deformable feature fusion (paper eq. 9-10), Deformable-DETR cross-attention.

Paper: *MSSF*, Sec. III-C. See :mod:`mssf_blocks.samplers` for the conventions shared by the samplers.
"""

from __future__ import annotations

import math
from typing import Optional, Sequence, Tuple, Type, Union

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mssf_blocks import torch_versions
from mssf_blocks.checks.tensors import check_floating, check_shape
from mssf_blocks.checks.arguments import check_positive_int
from mssf_blocks.checks.agreement import check_channels
from mssf_blocks.samplers._layers import (
    _autocast_off,
    _factory,
    _linear_bn_rows,
    _linear_bn_visible,
    _norm,
    _sampling_dtype,
    _to_sampling_dtype,
)
from mssf_blocks.checks.image_features import _check_projection, check_image_features
from mssf_blocks.samplers._msdff_pairs import Pairs, reduce_cameras, select_pairs
from mssf_blocks.static_path import use_static_path
from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.plan_costs import compiled_training_uses_op, msdff_auto_method
from mssf_blocks.functional.deform import bag, grid, ms_deform_sample
from mssf_blocks.functional.deform.op import sample_project_unchecked
from mssf_blocks.geometry.voxel_centroid_projector import CentroidProjection

__all__ = ["MSDFF"]

_METHODS = ("auto", "reference", "fast", "grid", "touched", "triton")
_VALUE_PROJECTIONS = ("after_sampling", "before_sampling")


def _exporting_onnx() -> bool:
    """An ONNX exporter (``torch.onnx.export``, dynamo or TorchScript) is capturing."""
    return getattr(torch, "onnx", None) is not None and torch.onnx.is_in_onnx_export()


def _compiling_only() -> bool:
    """``torch.compile`` (dynamo) is capturing, not an exporter: the sampling op is one opaque node there
    (the device's backend, e.g. the CPU plans, instead of the static grid plan), while exports (torch.export,
    ONNX, tracing) keep the static plans of standard operators."""
    if not torch_versions.is_compiling() or torch_versions.is_exporting():
        return False
    return not _exporting_onnx()


class MSDFF(nn.Module):
    """Multi-scale deformable feature fusion (paper eq. 9-10), Deformable-DETR cross-attention.

    For every voxel query ``q`` and every camera where the voxel projects validly to ``c_img``:

    * ``o = sampling_offsets(q)`` viewed ``(M, L, P, 2)``, sampling location
      ``c_img + o / (W_l, H_l)`` (eq. 9);
    * ``w = softmax over the L*P slots of attention_weights(q)`` per head;
    * head ``m`` reads ``sum_{l,p} w * Sample(value_proj_m(F_l), location)``;

    heads are concatenated, averaged over the valid cameras, and ``Linear_BN`` = ``output_proj`` + norm
    gives ``f_img`` (eq. 10). Widths: ``value_proj: value_channels -> value_dim`` (the heads split
    ``value_dim``, ``value_dim / M`` channels each) and ``output_proj: value_dim -> embed_dim``; the
    default ``value_dim = value_channels`` is the paper's and the authors' layout (256 -> 256 for an
    FPN, then 256 -> ``C_vox``); ``value_dim = embed_dim`` projects the image down to the voxel width
    before the attention (the narrow layout of this library's earlier releases).

    Sampling is linear in the values, so the value projection may be applied to the pixels (all of
    them, or only those a bilinear corner reads) or after sampling (raw channels sampled per head,
    projected with that head's rows of ``value_proj.weight``, plus ``value_proj.bias`` times the
    in-image bilinear weight mass): all are exactly equal, and the
    default ``method="auto"`` picks the cheapest per level, at a cost that scales with the pixels the
    voxels read, not with the image.

    Args:
        in_channels: channels ``C`` of the image levels (as :class:`SFF`'s first argument); all levels must
            have the same (FPN) channels, an int or a sequence of equal ints. Also accepted as
            ``value_channels=`` (Deformable DETR's name; the attribute keeps it).
        out_channels: query and output channels ``E`` (the voxel channels); any positive int. Also accepted
            as ``embed_dim=`` (the attribute keeps it).
        value_dim: ``D_v``, channels the heads attend over (``value_proj``'s output, ``output_proj``'s
            input); divisible by ``num_heads``. ``None`` (default): ``value_channels``.
        num_heads: ``M``.
        num_levels: ``L``, number of image levels read.
        num_points: ``P``, sampling points per head and level.
        norm_layer: normalisation after ``output_proj``; ``None`` for none (the authors' module has
            none, see :mod:`mssf_blocks.weights.authors_checkpoint`).
        method: ``"auto"`` (default): whatever ``value_projection``, per level the cheapest exact plan
            of :func:`~mssf_blocks.functional.ms_deform_sample_project` ``method="touched"`` (project
            every pixel, project only the ``U_l`` pixels some bilinear corner reads, or sample those
            pixels' raw channels and project per head; cost
            ``O(min(pixels_l * D_v, U_l * (D_v + G), U_l * G + N * M * P * 4 * B) * C)``, see
            ``docs/fusion.md``) on the CPU, the sampling op's backend on CUDA; under ``torch.compile``
            the sampling op (one opaque node; with gradients per ``plan_costs.COMPILED_TRAINING``);
            on the static-shape path (``torch.export``, tracing, ``static_path()``) on the CPU per level the raw
            channels of every corner in fixed-size bags, projected per head after (no cost in the pixels),
            and under an ONNX export ``"grid"`` with a 1 x 1 convolution (``Conv`` + ``GridSample``).
            ``"grid"``: project every pixel, then ``F.grid_sample`` per head with static shapes (no
            host synchronisation, exportable; every query is sampled in each of the ``B * V`` images
            and keeps its own). ``"fast"`` / ``"reference"``: the literal order of
            ``value_projection`` with ``ms_deform_sample``'s embedding-bag / ``grid_sample`` path
            (``"reference"`` becomes ``"grid"`` while a graph is captured: it sizes per-image lists by the
            data).
            ``"touched"`` / ``"triton"``: force that backend of the sampling op
            (:func:`~mssf_blocks.functional.deform.op.deform_sample_project`; ``"auto"`` lets the op
            pick the device's, ``plan_costs.SAMPLING_BACKENDS``; ``$MSSF_SAMPLING_BACKEND`` forces one
            for ``"auto"``); ``"triton"`` needs CUDA tensors (or the interpreter) and becomes
            ``"grid"`` while a graph is captured.
        value_projection: the order used by ``method`` ``"fast"`` / ``"reference"``:
            ``"after_sampling"`` (default; sample the raw channels per head, then project; cost
            ``O(N * M * L * P * C)``, independent of the image size) or ``"before_sampling"``
            (Deformable DETR's order: ``value_proj`` on every pixel, then sample ``D_v / M`` channels
            per head; ``O(pixels * C * D_v + N * M * L * P * D_v / M)``). All give the same result
            (tested).
        device, dtype: factory arguments of the parameters.
        add_query: ``False`` (default; paper eq. 10, ``f_img = Linear_BN(...)``): the output is the
            image feature. ``True``: the output is ``query + f_img`` (the authors' attention adds its
            input back, so their fusion block computes ``f_vox + query + f_img``, i.e.
            ``2 f_vox + f_img`` when the query is the voxel feature).
        output_dropout: dropout probability on ``f_img`` in training mode (default 0; the authors use
            0.1, applied before the query is added back).

    Shapes:
        - query: ``(N, E)``; image_features: ``L`` levels ``(B, [V,] C, H_l, W_l)``;
          projection: ``uv (N, V, 2)``, ``valid (N, V)``, ``batch_index (N,)``.
        - output: ``(N, E)``; exact zeros for voxels seen by no camera.

    Precision: the locations, attention weights and sampling run in float32 (float64 for a float64
    module), also under ``torch.autocast``; float16 / bfloat16 levels are read as float32
    (``docs/fusion.md``, "Precision and mixed-precision training").

    Host synchronisation (what stalls a GPU), all data-dependent and so inherent: the projection's
    batch-index range check; ``valid.all()`` (one camera seeing every voxel takes a path without
    gathers); with several cameras the ``(voxel, camera)`` pairs (``nonzero``); the visible rows of the
    output BatchNorm (``nonzero``); ``method="auto"`` and ``"fast"`` also size their per-level gathers
    by the pixels the voxels touch. None grows with the number of voxels (``tests/test_devices.py``
    counts them on CUDA).

    Weights: ``sampling_offsets (M*L*P*2, E)``, ``attention_weights (M*L*P, E)``, ``value_proj
    (D_v, C)``, ``output_proj (E, D_v)`` (plus biases) have the names and layout of Deformable DETR's
    ``MSDeformAttn`` and of mmcv's / the MSSF authors' ``MSDeformableAttention`` (their
    ``query_embed_dims`` = ``E``, ``value_embed_dims`` = ``C`` = ``D_v``, ``output_embed_dims`` = ``E``):
    the tensors copy across unchanged, offsets ordered ``(M, L, P, xy)`` and head ``m`` reading
    ``value_proj`` rows ``[m * D_v / M, (m + 1) * D_v / M)`` in both. Deformable DETR itself has
    ``E = C = D_v``. The norm (``norm``) is ours; the authors' module has none and adds the query back
    (:mod:`mssf_blocks.weights.authors_checkpoint` maps their checkpoints and lists the switches).
    """

    def __init__(
        self,
        in_channels: Union[int, Sequence[int], None] = None,
        out_channels: Optional[int] = None,
        value_dim: Optional[int] = None,
        num_heads: int = 8,
        num_levels: int = 4,
        num_points: int = 4,
        norm_layer: Optional[Type[nn.Module]] = nn.BatchNorm1d,
        method: str = "auto",
        value_projection: str = "after_sampling",
        device=None,
        dtype=None,
        add_query: bool = False,
        output_dropout: float = 0.0,
        *,
        embed_dim: Optional[int] = None,
        value_channels: Union[int, Sequence[int], None] = None,
    ) -> None:
        super().__init__()
        # (embed_dim= / value_channels=: Deformable DETR's names for out_channels / in_channels, kept as keywords)
        for new_name, new_value, old_name, old_value in (("in_channels", in_channels, "value_channels", value_channels),
                                                         ("out_channels", out_channels, "embed_dim", embed_dim)):
            if new_value is not None and old_value is not None:
                raise MSSFError(f"{old_name}: expected either {new_name}= or {old_name}= (the same argument), got both")
            if new_value is None and old_value is None:
                raise MSSFError(f"{new_name}: expected a positive int ("
                                + ("image channels C of every level" if new_name == "in_channels"
                                   else "voxel channels E, the fusion block's") + "), got None")
        value_channels = value_channels if in_channels is None else in_channels
        embed_dim = embed_dim if out_channels is None else out_channels
        if not isinstance(add_query, bool):
            raise MSSFError(f"add_query: expected a bool, got {add_query!r}")
        if (isinstance(output_dropout, bool) or not isinstance(output_dropout, (int, float))
                or not 0 <= output_dropout < 1):
            raise MSSFError(f"output_dropout: expected a probability in [0, 1), got {output_dropout!r}")
        self.add_query, self.output_dropout = add_query, float(output_dropout)
        self.embed_dim = check_positive_int(embed_dim, "embed_dim")
        self.num_heads = check_positive_int(num_heads, "num_heads")
        self.num_levels = check_positive_int(num_levels, "num_levels")
        self.num_points = check_positive_int(num_points, "num_points")
        if isinstance(value_channels, int):
            self.value_channels = check_positive_int(value_channels, "value_channels")
        else:
            chans = tuple(check_positive_int(c, f"value_channels[{i}]") for i, c in enumerate(value_channels))
            if len(chans) != self.num_levels or len(set(chans)) != 1:
                raise MSSFError(
                    f"value_channels: expected one channel count shared by all {self.num_levels} levels "
                    f"(FPN outputs; value_proj is shared across levels), got {chans}"
                )
            self.value_channels = chans[0]
        self.value_dim = self.value_channels if value_dim is None else check_positive_int(value_dim, "value_dim")
        if self.value_dim % self.num_heads:
            hint = "; value_dim defaults to value_channels" if value_dim is None else ""
            raise MSSFError(
                f"value_dim: expected a multiple of num_heads={self.num_heads} (the heads split it{hint}), "
                f"got {self.value_dim}"
            )
        if method not in _METHODS:
            raise MSSFError(f"method: expected one of {_METHODS}, got {method!r}")
        self.method = method
        if value_projection not in _VALUE_PROJECTIONS:
            raise MSSFError(f"value_projection: expected one of {_VALUE_PROJECTIONS}, got {value_projection!r}")
        self.value_projection = value_projection
        factory = _factory(device, dtype)
        m, l, p = self.num_heads, self.num_levels, self.num_points
        self.sampling_offsets = nn.Linear(self.embed_dim, m * l * p * 2, **factory)
        self.attention_weights = nn.Linear(self.embed_dim, m * l * p, **factory)
        self.value_proj = nn.Linear(self.value_channels, self.value_dim, **factory)
        self.output_proj = nn.Linear(self.value_dim, self.embed_dim, **factory)
        self.norm = _norm(norm_layer, self.embed_dim, factory)
        self.reset_parameters()

    @property
    def in_channels(self) -> int:
        """Image channels ``C`` of every level (``value_channels``), as :class:`SFF`'s ``in_channels``."""
        return self.value_channels

    @property
    def out_channels(self) -> int:
        """Voxel channels ``E`` of the query and the output (``embed_dim``), as :class:`SFF`'s."""
        return self.embed_dim

    @property
    def head_dim(self) -> int:
        return self.value_dim // self.num_heads

    def reset_parameters(self) -> None:
        """Deformable-DETR initialisation.

        Offsets start on a grid: head ``m`` points in direction ``2 pi m / M`` (scaled so the larger of
        ``|cos|, |sin|`` is 1), point ``p`` at distance ``p + 1`` pixels of every level; attention
        weights start uniform (zero weight and bias); projections are xavier-uniform with zero bias.
        """
        m, l, p = self.num_heads, self.num_levels, self.num_points
        nn.init.zeros_(self.sampling_offsets.weight)
        w = self.sampling_offsets.weight
        thetas = torch.arange(m, dtype=torch.float64) * (2.0 * math.pi / m)
        grid = torch.stack([thetas.cos(), thetas.sin()], dim=-1)
        grid = grid / grid.abs().max(dim=-1, keepdim=True).values
        grid = grid.view(m, 1, 1, 2).repeat(1, l, p, 1)
        grid = grid * torch.arange(1, p + 1, dtype=torch.float64).view(1, 1, p, 1)
        with torch.no_grad():
            self.sampling_offsets.bias.copy_(grid.reshape(-1).to(device=w.device, dtype=w.dtype))
        nn.init.zeros_(self.attention_weights.weight)
        nn.init.zeros_(self.attention_weights.bias)
        for lin in (self.value_proj, self.output_proj):
            nn.init.xavier_uniform_(lin.weight)
            nn.init.zeros_(lin.bias)

    def sampling_locations_and_weights(
        self, query: Tensor, uv: Tensor, level_sizes: Sequence[Tuple[int, int]]
    ) -> Tuple[Tensor, Tensor]:
        """Eq. 9 and the softmax: ``(Q, M, L, P, 2)`` locations (a view of ``(Q, L, 2, M, P)`` memory)
        and ``(Q, M, L, P)`` weights.

        Args:
            query: ``(Q, E)`` queries (one row per voxel-camera pair).
            uv: ``(Q, 2)`` normalised reference points.
            level_sizes: ``(H_l, W_l)`` of every level.
        """
        q = query.shape[0]
        m, l, p = self.num_heads, self.num_levels, self.num_points
        dtype = _sampling_dtype(self.value_proj.weight)
        with _autocast_off(query.device.type):  # locations in float32 at least (see the module doc)
            query = _to_sampling_dtype(query, dtype, "query", "MSDFF")
            uv = uv.to(dtype)
            aw, so = self.attention_weights, self.sampling_offsets
            weights = F.linear(query, aw.weight.to(dtype), aw.bias.to(dtype))
            weights = weights.view(q, m, l * p).softmax(dim=-1).view(q, m, l, p)
            # Offsets are in pixels of each level, location = uv + offset / (W_l, H_l). Both steps are
            # folded into one affine map of [query, uv]: the rows of sampling_offsets scaled by
            # (1 / W_l, 1 / H_l) plus a 0/1 selector that adds u (v) to every x (y) output. One GEMM
            # instead of a broadcast division and addition over the (Q, M, L, P, 2) output (measured
            # 4-6x faster on the CPU); equal up to float rounding.
            inv = torch.tensor([[1.0 / w, 1.0 / h] for h, w in level_sizes], dtype=dtype, device=query.device)
            scale = inv.view(1, l, 1, 2).expand(m, l, p, 2).reshape(-1, 1)  # (M * L * P * 2, 1)
            select = torch.eye(2, dtype=dtype, device=query.device).repeat(m * l * p, 1)  # (M * L * P * 2, 2)
            weight = torch.cat([so.weight.to(dtype) * scale, select], 1)
            bias = so.bias.to(dtype) * scale[:, 0]
            # Output columns in (L, 2, M, P) order, returned as a (Q, M, L, P, 2) view: one level's x (or
            # y) of all heads and points is then a contiguous run per query, which the samplers copy
            # as whole rows (functional/deform/touched/points.py, _sorted_points).
            perm = torch.arange(m * l * p * 2, device=query.device).view(m, l, p, 2).permute(1, 3, 0, 2).reshape(-1)
            locations = torch.addmm(bias[perm], torch.cat([query, uv], 1), weight[perm].t())
        return locations.view(q, l, 2, m, p).permute(0, 3, 1, 4, 2), weights

    def forward(
        self, query: Tensor, image_features: Sequence[Tensor], projection: CentroidProjection
    ) -> Tensor:
        levels = check_image_features(
            image_features, num_levels=self.num_levels, channels=[self.value_channels] * self.num_levels,
            channels_name="MSDFF value_channels",
        )
        b, v = levels[0].shape[:2]
        uv, valid, batch_index = _check_projection(projection, b, v)
        n = uv.shape[0]
        check_channels(query, "query", self.embed_dim, "MSDFF embed_dim")
        check_shape(query, "query", (n, self.embed_dim))
        check_floating(query, "query")

        # The sampling runs in float32 (float64 for a float64 module), autocast or not: lower-precision
        # levels are read as float32 and the locations are never rounded to half precision.
        dtype = _sampling_dtype(self.value_proj.weight)
        levels = [_to_sampling_dtype(lvl, dtype, f"image_features[{i}]", "MSDFF") for i, lvl in enumerate(levels)]
        uv = uv.to(dtype)
        method, static = self._plan(uv.device.type)
        with _autocast_off(uv.device.type):
            sizes = [tuple(lvl.shape[-2:]) for lvl in levels]
            pairs = select_pairs(self.sampling_locations_and_weights, query, uv, valid, batch_index, sizes, static)
            heads = self._sample(method, static, levels, pairs, dtype)  # (Q, M, d)
            attended = reduce_cameras(heads, pairs, valid)
        attended = attended.to(self.output_proj.weight.dtype)
        if pairs.seen is not None:  # (the seen voxels' rows only)
            f_img = _linear_bn_rows(self.output_proj, self.norm, attended, pairs.seen, n)
        else:
            # (a sum: ONNX exports any() as ReduceMax, which its opset 18 -> 17 conversion cannot adapt)
            f_img = _linear_bn_visible(self.output_proj, self.norm, attended, valid.sum(dim=1) > 0, static)
        if self.output_dropout:
            f_img = F.dropout(f_img, self.output_dropout, self.training)
        return query.to(f_img.dtype) + f_img if self.add_query else f_img

    def _plan(self, device_type: str) -> Tuple[str, bool]:
        """``(method, static)``: the sampling method (``"auto"`` resolved) and whether the queries take the
        static layout (every (voxel, camera) pair, no host synchronisation)."""
        static = use_static_path()
        method = self.method
        if method == "auto" or (static and method in ("reference", "triton")):
            method = msdff_auto_method(device_type, static)
            method = "sample_op" if method == "touched" else method  # (the op picks the device's backend)
            # Under torch.compile the op is one opaque node; with gradients, per device, the op or the grid plan
            # by measurement (plan_costs.COMPILED_TRAINING).
            opaque = _compiling_only() and (not torch.is_grad_enabled() or compiled_training_uses_op(device_type))
            method = "sample_op" if method == "grid" and (not static or opaque) else method
            if method == "grid" and static and not _compiling_only():  # (compile: COMPILED_TRAINING's grid)
                # Static shapes: raw channels in fixed-size bags, projected per head (CPU; off it the grid plan's GEMM
                # is cheap: plan_costs); ONNX writes embedding_bag as a Loop: GridSample forms (docs/deployment.md).
                method = "grid_conv" if _exporting_onnx() else "static_bag" if device_type == "cpu" else "grid"
        # (the grid and Triton paths never synchronise with the device: on a GPU the op takes every
        # (voxel, camera) pair, the invalid ones reading zeros, rather than gathering the valid ones)
        static = static or method in ("grid", "grid_conv", "static_bag", "triton") or (
            method == "sample_op" and device_type != "cpu")
        return method, static

    def _sample(self, method: str, static: bool, levels: Sequence[Tensor], pairs: Pairs, dtype: torch.dtype) -> Tensor:
        """``(Q, M, d)`` heads of the queries ``pairs``, by ``method`` (resolved: not ``"auto"``)."""
        b, v, c = levels[0].shape[:3]
        m, e = self.num_heads, self.value_dim
        image_index, locations, weights = pairs.image_index, pairs.locations, pairs.weights
        w_heads = self.value_proj.weight.to(dtype).view(m, self.head_dim, c)
        b_heads = self.value_proj.bias.to(dtype).view(m, self.head_dim)
        raw = [lvl.reshape(b * v, 1, c, lvl.shape[-2], lvl.shape[-1]) for lvl in levels]  # Mv = 1 views
        if method == "static_bag":  # the static-shape path (bag.sample_project_static)
            return bag.sample_project_static(raw, image_index, locations, weights, w_heads, b_heads)
        if method in ("grid", "grid_conv") and static:  # the op's grid path / the ONNX form: standard operators
            fn = grid.sample_project_onnx if method == "grid_conv" else grid.sample_project
            return fn(raw, image_index, locations, weights, w_heads, b_heads)
        if method in ("sample_op", "touched", "triton"):
            # The sampling op: the device's backend (functional/deform/op.py; CPU: per level the
            # cheapest exact "touched" plan, CUDA: the Triton kernels or the grid path) or the forced one.
            return sample_project_unchecked(raw, image_index, locations, weights, w_heads, b_heads,
                                            "auto" if method == "sample_op" else method)
        if self.value_projection == "after_sampling":
            sampled, mass = ms_deform_sample(
                raw, image_index, locations, weights, method=method, return_mass=True
            )  # (Q, M, C), (Q, M)
            # value_proj after sampling: head m uses rows [m*d, (m+1)*d) of the projection; its bias
            # contributes only where the bilinear corners were inside the image (zero padding).
            return torch.einsum("qmc,mdc->qmd", sampled, w_heads) + mass[..., None] * b_heads
        values = []
        for lvl in levels:
            h, w = lvl.shape[-2:]
            projected = F.linear(lvl.reshape(b * v, c, h, w).permute(0, 2, 3, 1), w_heads.reshape(e, c),
                                 b_heads.reshape(e))  # (I, H, W, E)
            values.append(projected.view(b * v, h, w, m, self.head_dim).permute(0, 3, 4, 1, 2))
        return ms_deform_sample(values, image_index, locations, weights, method=method)

    def extra_repr(self) -> str:
        return (
            f"embed_dim={self.embed_dim}, value_channels={self.value_channels}, value_dim={self.value_dim}, "
            f"num_heads={self.num_heads}, "
            f"num_levels={self.num_levels}, num_points={self.num_points}, method={self.method!r}, "
            f"value_projection={self.value_projection!r}"
            + (f", add_query={self.add_query}, output_dropout={self.output_dropout}"
               if self.add_query or self.output_dropout else "")
        )
