"""Checks of what reaches spconv: a sparse tensor's features, indices, shape and batch size, and the first
convolution of a module (channels, dtype, a CPU bias in eval mode), so that a mistake gets our error
instead of an assertion deep inside spconv's kernels. spconv itself is imported lazily."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

__all__ = ["check_spconv_input", "check_module_input", "check_sparse_tensor", "first_conv"]

#: feature dtypes spconv's kernels handle (no integer path; float64 runs on the CPU with one torch thread,
#: checked against a dense conv3d in tests/integrations/test_spconv_dense_reference.py and the float64 parity tests of the
#: authors' stages; with two threads its CPU float64 results are wrong, so check_spconv_input refuses that)
_SPCONV_FEATURE_DTYPES = (torch.float32, torch.float64, torch.float16, torch.bfloat16)


def check_spconv_input(features: Tensor, coords: Tensor, spatial_shape, batch_size: int,
                       name: str = "voxels", expected_shape=None, coords_name: str = "coords",
                       module: Any = None, module_name: str = "module") -> None:
    """Our error, before spconv runs, for what spconv would fail on with its own internal error.

    The one check of what enters spconv: :meth:`SparseVoxels.to_spconv`, a ``FusionBlock`` (an spconv
    tensor it is given, and what it hands its ``downsample`` / ``blocks``), the example backbones.

    Checks (shapes and dtypes only, no data read): ``features`` a floating ``(N, C)`` tensor (float32,
    float64, float16 or bfloat16; float64 on the CPU only with one torch thread, where spconv 2.3.8 is right); ``coords`` an int32 ``(N, 4)`` tensor; ``N > 0`` (spconv cannot
    run on zero voxels); and, with ``expected_shape`` (the network's ``(D, H, W)``), ``spatial_shape``
    equal to it, naming the axis order when it is a permutation of it. With ``module`` (what the tensor is
    handed to), also the channels and dtype its first spconv convolution takes (:func:`check_module_input`).
    ``coords_name``: the field's name in messages (``"indices"`` for an spconv tensor).

    Raises:
        MSSFError: naming ``name``'s field, what was expected and what was received.
    """
    from mssf_blocks.errors import MSSFError

    if not isinstance(features, Tensor) or features.dim() != 2:
        got = tuple(features.shape) if isinstance(features, Tensor) else type(features).__name__
        raise MSSFError(f"{name}.features: expected an (N, C) tensor for spconv, got {got}")
    if features.dtype not in _SPCONV_FEATURE_DTYPES:
        raise MSSFError(
            f"{name}.features: expected a floating dtype (float32, float64, float16 or bfloat16) for spconv, "
            f"got {features.dtype}; convert with .float()"
        )
    if not isinstance(coords, Tensor) or coords.dim() != 2 or coords.shape[1] != 4:
        got = tuple(coords.shape) if isinstance(coords, Tensor) else type(coords).__name__
        raise MSSFError(f"{name}.{coords_name}: expected an (N, 4) (batch, z, y, x) tensor for spconv, got {got}")
    if coords.dtype != torch.int32:
        raise MSSFError(f"{name}.{coords_name}: expected dtype torch.int32 for spconv (its indices), got "
                        f"{coords.dtype}; convert with .int()")
    if module is not None:  # (before the thread rule below: a float64 tensor into a float32 module is named as such)
        check_module_input(features, module, name, module_name)
    if features.dtype == torch.float64 and features.device.type == "cpu" and torch.get_num_threads() > 1:
        raise MSSFError(
            f"{name}.features: float64 on the CPU needs one torch thread for spconv, got "
            f"{torch.get_num_threads()} threads: spconv 2.3.8's CPU float64 kernels give wrong values with more "
            "than one (off by up to about 1 in 9 of 10 random draws, measured 2026-12-03; float32 is right); "
            "call torch.set_num_threads(1) or use float32"
        )
    if features.shape[0] != coords.shape[0]:
        raise MSSFError(f"{name}: expected as many feature rows as {coords_name} rows, got {features.shape[0]} and "
                        f"{coords.shape[0]}")
    if features.shape[0] == 0:
        raise MSSFError(f"{name}: expected at least one voxel for spconv, got 0 (an empty point cloud? skip "
                        "the frame, or give it one voxel)")
    shape = tuple(int(s) for s in spatial_shape)
    if expected_shape is not None:
        want = tuple(int(s) for s in expected_shape)
        if shape != want:
            order = ""
            if sorted(shape) == sorted(want):
                order = (f"; (D, H, W) = (z, y, x) order is expected: {shape} is {want} with its axes "
                         f"permuted (e.g. (x, y, z) = (W, H, D) order)")
            raise MSSFError(f"{name}.spatial_shape: expected the network's {want}, got {shape}{order}")
    # (a 0-d tensor is what mmdet3d's SparseEncoder hands spconv: reading it would stall a GPU, spconv reads it)
    if not (isinstance(batch_size, Tensor) and batch_size.dim() == 0 and not batch_size.is_floating_point()) and (
            isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1):
        raise MSSFError(f"{name}.batch_size: expected a positive int, got {batch_size!r}")


def first_conv(module: Any) -> Any:
    """The spconv convolution that first reads what ``module`` is given: ``module`` itself, else, down the
    first registered child at each level (a ``SparseSequential`` / ``Sequential``, a residual block's
    ``conv1``), the first spconv convolution met; ``None`` when that path holds none (then nothing is checked)."""
    while module is not None:
        if hasattr(module, "subm") and hasattr(module, "in_channels") and isinstance(getattr(module, "weight", None),
                                                                                     Tensor):
            return module
        module = next(iter(module.children()), None) if hasattr(module, "children") else None
    return None


def _cpu_eval_bias(module: Any) -> Any:
    """``(qualified name, module)`` (name ``""``: ``module`` itself) of the first spconv convolution in
    ``module`` that would pass its bias to spconv's inference kernel (eval mode, spconv's own ``forward``),
    or ``None``."""
    try:
        from spconv.pytorch.conv import SparseConvolution
    except ImportError:  # pragma: no cover - depends on the environment
        return None
    for qual, m in module.named_modules():
        if (type(m).forward is SparseConvolution.forward and not m.training
                and getattr(m, "bias", None) is not None):
            return qual, m
    return None


def check_module_input(features: Tensor, module: Any, name: str = "voxels", module_name: str = "module") -> None:
    """``features (N, C)`` fit ``module``'s first spconv convolution (:func:`first_conv`): ``C`` its
    ``in_channels`` (else spconv's "channel size mismatch" assertion), and its parameters' dtype (else a
    matrix-product dtype error deep in spconv). Not checked: the dtype under ``torch.autocast`` (spconv casts
    there), and float16 features into float32 parameters (spconv runs those in float16). On the CPU, also that
    no spconv convolution in ``module`` has a bias in eval mode (spconv's CPU kernels assert on it)."""
    from mssf_blocks.checks.tensors import autocast_on
    from mssf_blocks.errors import MSSFError

    conv = first_conv(module)
    if conv is None:
        return
    owner = module_name + ("'" if module_name.endswith("s") else "'s")
    what = f"{owner} first convolution ({type(conv).__name__})"
    c = features.shape[1]
    if c != conv.in_channels:
        raise MSSFError(
            f"{name}.features: expected {conv.in_channels} channels (in_channels={conv.in_channels} of {what}), "
            f"got {c}; build that convolution with in_channels={c}, or give it {conv.in_channels}-channel voxels"
        )
    w = conv.weight.dtype
    if (features.dtype != w and not (features.dtype == torch.float16 and w == torch.float32)
            and not autocast_on(features.device.type)):
        raise MSSFError(
            f"{name}.features: expected dtype {w} (the parameters of {what}), got {features.dtype}; convert the "
            f"features (.to({w})) or the module (.to({features.dtype}))"
        )
    if features.device.type == "cpu":
        biased = _cpu_eval_bias(module)
        if biased is not None:
            qual, m = biased
            raise MSSFError(
                f"{module_name}{'.' + qual if qual else ''}: expected no bias in eval mode on the CPU, got a "
                f"{type(m).__name__} with a bias (spconv 2.x adds it inside its "
                "inference kernel, which asserts \"cpu don't support act and bias\"); build it with bias=False (a "
                "BatchNorm after it makes the bias redundant), or run on CUDA"
            )


def check_sparse_tensor(t: Any, name: str, module: Any, module_name: str) -> None:
    """:func:`check_spconv_input` on ``t`` (a ``SparseVoxels``, with ``coords``, or an spconv tensor, with
    ``indices``) and what ``module``'s first convolution takes (shapes and dtypes only)."""
    if hasattr(t, "coords"):
        check_spconv_input(t.features, t.coords, t.spatial_shape, t.batch_size, name, module=module,
                           module_name=module_name)
    else:
        check_spconv_input(t.features, t.indices, t.spatial_shape, t.batch_size, name, coords_name="indices",
                           module=module, module_name=module_name)
