"""mmcv's CUDA multi-scale deformable attention op, built alone from an mmcv source archive, for
``benchmarks/gpu_check.py``'s comparison (stage 2b) on GPU machines where mmcv's compiled ops do not
install: no prebuilt mmcv wheel for that torch / CUDA, or no network to fetch one.

``gpu_check.py --mmcv-src mmcv-2.1.0.tar.gz`` (or ``$MSSF_MMCV_SRC``; the source archive from the package
registry, or an unpacked source tree) compiles the one CUDA file of mmcv's op
(``mmcv/ops/csrc/pytorch/cuda/ms_deform_attn_cuda.cu`` with the headers it includes, read from the archive
as they are) with ``torch.utils.cpp_extension.load`` (nvcc, for the visible GPU's architecture: about half a
minute on 16 cores), together with two files written here: a Python binding of its forward and backward
functions, and ``THC/THCAtomics.cuh``, a header that mmcv 2.1.0 still includes and torch >= 1.11 no longer
ships (its atomics are ``ATen/cuda/Atomic.cuh`` now). :class:`MmcvMSDAFunction` then has the calling
convention and the autograd formula of mmcv's ``MultiScaleDeformableAttnFunction``: ``apply(value (B, S, M,
d), spatial_shapes (L, 2) int64, level_start_index (L,) int64, sampling_locations (B, Q, M, L, P, 2),
attention_weights (B, Q, M, L, P), im2col_step) -> (B, Q, M * d)``; the locations and weights are cast to
the value's dtype as mmcv does.

Checked on a machine without a GPU (2026-12-03): mmcv 2.1.0's file compiles for sm_90 with nvcc 13.0
against torch 2.13.0's headers (``tests/project/test_gpu_check.py`` compiles the binding written here).
"""

from __future__ import annotations

import tarfile
from pathlib import Path
from typing import Dict, Optional, Tuple

__all__ = ["MMCV_CU", "BINDING", "prepare_sources", "build", "start_build", "function"]

#: mmcv's CUDA file of the op, relative to its ``mmcv/ops/csrc`` folder (it includes ``common/``'s headers).
MMCV_CU = "pytorch/cuda/ms_deform_attn_cuda.cu"

#: The binding (ours): mmcv's two host functions of that file, declared and exposed to Python.
BINDING = r"""
#include <torch/extension.h>

at::Tensor ms_deform_attn_cuda_forward(const at::Tensor &value, const at::Tensor &spatial_shapes,
                                       const at::Tensor &level_start_index, const at::Tensor &sampling_loc,
                                       const at::Tensor &attn_weight, const int im2col_step);

void ms_deform_attn_cuda_backward(const at::Tensor &value, const at::Tensor &spatial_shapes,
                                  const at::Tensor &level_start_index, const at::Tensor &sampling_loc,
                                  const at::Tensor &attn_weight, const at::Tensor &grad_output,
                                  at::Tensor &grad_value, at::Tensor &grad_sampling_loc,
                                  at::Tensor &grad_attn_weight, const int im2col_step);

static void backward(at::Tensor value, at::Tensor spatial_shapes, at::Tensor level_start_index,
                     at::Tensor sampling_loc, at::Tensor attn_weight, at::Tensor grad_output,
                     at::Tensor grad_value, at::Tensor grad_sampling_loc, at::Tensor grad_attn_weight,
                     int64_t im2col_step) {
  // (the gradients are written into the three tensors given, which the caller zero-fills)
  ms_deform_attn_cuda_backward(value, spatial_shapes, level_start_index, sampling_loc, attn_weight,
                               grad_output, grad_value, grad_sampling_loc, grad_attn_weight,
                               static_cast<int>(im2col_step));
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", [](at::Tensor value, at::Tensor spatial_shapes, at::Tensor level_start_index,
                      at::Tensor sampling_loc, at::Tensor attn_weight, int64_t im2col_step) {
    return ms_deform_attn_cuda_forward(value, spatial_shapes, level_start_index, sampling_loc, attn_weight,
                                       static_cast<int>(im2col_step));
  });
  m.def("backward", &backward);
}
"""

_THC_ATOMICS = "#pragma once\n#include <ATen/cuda/Atomic.cuh>\n"


def _csrc_files(source: Path) -> Dict[str, bytes]:
    """The files the op needs, by their path under mmcv's ``mmcv/ops/csrc`` (:data:`MMCV_CU` and
    ``common/``), read from ``source``: an mmcv ``.tar.gz`` source archive or an unpacked source tree."""
    if source.is_dir():
        found = sorted(source.glob(f"**/mmcv/ops/csrc/{MMCV_CU}"))
        if not found:
            raise FileNotFoundError(f"mmcv source: no mmcv/ops/csrc/{MMCV_CU} under {source}")
        root = found[0].parents[2]  # .../mmcv/ops/csrc
        return {str(path.relative_to(root)): path.read_bytes()
                for path in [found[0], *sorted((root / "common").rglob("*"))] if path.is_file()}
    if not source.is_file():
        raise FileNotFoundError(f"mmcv source: {source} does not exist (an mmcv source archive or folder)")
    files = {}
    with tarfile.open(source) as tar:
        for member in tar.getmembers():
            _, _, rel = member.name.partition("/mmcv/ops/csrc/")
            if ".." in Path(rel).parts:  # (never written outside the build folder)
                continue
            if member.isfile() and (rel == MMCV_CU or rel.startswith("common/")):
                files[rel] = tar.extractfile(member).read()
    if MMCV_CU not in files:
        raise FileNotFoundError(f"mmcv source: no mmcv/ops/csrc/{MMCV_CU} in the archive {source}")
    return files


def prepare_sources(source: Path, build_dir: Path) -> Tuple[list, list]:
    """``(sources, include_dirs)`` for ``torch.utils.cpp_extension.load``: mmcv's ``csrc`` files the op
    needs, copied from ``source`` (an mmcv ``.tar.gz`` source archive or an unpacked source tree) into
    ``build_dir``, and the two files written here.

    Raises:
        FileNotFoundError: ``source`` is missing, or holds no ``mmcv/ops/csrc/`` + :data:`MMCV_CU`.
    """
    build_dir = Path(build_dir)
    csrc, shim, binding = build_dir / "csrc", build_dir / "shim", build_dir / "msda_binding.cpp"
    written = {csrc / rel: data for rel, data in _csrc_files(Path(source)).items()}
    written.update({shim / "THC" / "THCAtomics.cuh": _THC_ATOMICS.encode(), binding: BINDING.encode()})
    for path, data in written.items():
        if path.is_file() and path.read_bytes() == data:
            continue  # (left as it is: a new time stamp would make ninja compile the built op again)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
    includes = [shim, csrc / "common", csrc / "common" / "cuda"]
    return [str(binding), str(csrc / MMCV_CU)], [str(p) for p in includes]


def build(source: Path, build_dir: Path, verbose: bool = False):
    """The compiled extension (functions ``forward`` and ``backward``), built into ``build_dir``."""
    from torch.utils.cpp_extension import load

    sources, includes = prepare_sources(source, build_dir)
    return load(name="mssf_mmcv_msda", sources=sources, extra_include_paths=includes,
                extra_cuda_cflags=["-O3", "--expt-relaxed-constexpr"], build_directory=str(build_dir),
                verbose=verbose)


def start_build(source: Path, build_dir: Path, log: Path):
    """:func:`build` in a background process (``subprocess.Popen``, output to ``log``), so nvcc compiles
    while the GPU runs the tests; a later :func:`function` with the same folder finds it built (ninja has
    nothing left to do) and only loads it. Wait for the process before calling :func:`function`."""
    import subprocess
    import sys

    Path(build_dir).mkdir(parents=True, exist_ok=True)
    code = ("import sys; sys.path.insert(0, sys.argv[1]); import _mmcv_build; "
            "_mmcv_build.build(__import__('pathlib').Path(sys.argv[2]), __import__('pathlib').Path(sys.argv[3]))")
    with open(log, "w") as f:
        return subprocess.Popen([sys.executable, "-c", code, str(Path(__file__).resolve().parent), str(source),
                                 str(build_dir)], stdout=f, stderr=subprocess.STDOUT)


def function(source: Path, build_dir: Path) -> Tuple[Optional[type], Optional[str]]:
    """``(MmcvMSDAFunction, None)``, or ``(None, why)`` when the build fails."""
    try:
        ext = build(source, build_dir)
    except Exception as exc:  # noqa: BLE001 - no nvcc, a compile error, no archive: reported in the row
        return None, f"n/a (building mmcv's op from {source} failed: {type(exc).__name__}: {str(exc)[-200:]})"
    import torch

    class MmcvMSDAFunction(torch.autograd.Function):
        """mmcv's ``MultiScaleDeformableAttnFunction``, over the op built from its source."""

        @staticmethod
        def forward(ctx, value, spatial_shapes, level_start_index, sampling_locations, attention_weights,
                    im2col_step):
            loc, wt = sampling_locations.type_as(value), attention_weights.type_as(value)
            ctx.im2col_step = int(im2col_step)
            ctx.save_for_backward(value, spatial_shapes, level_start_index, loc, wt)
            return ext.forward(value, spatial_shapes, level_start_index, loc, wt, ctx.im2col_step)

        @staticmethod
        def backward(ctx, grad_output):
            value, shapes, starts, loc, wt = ctx.saved_tensors
            gv, gl, gw = torch.zeros_like(value), torch.zeros_like(loc), torch.zeros_like(wt)
            ext.backward(value, shapes, starts, loc, wt, grad_output.contiguous(), gv, gl, gw, ctx.im2col_step)
            return gv, None, None, gl, gw, None

    return MmcvMSDAFunction, None
