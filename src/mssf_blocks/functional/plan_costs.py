"""Cost constants of the MSDFF sampling planner (the ``"touched"`` plans), per device.

Every machine-dependent choice of the planner lives here. The CPU values below were measured with
``benchmarks/msdff.py`` (its ``plan_costs`` / ``primitive_floor`` tables) on the development machine.
"""

# Cost model of the "touched" method, per level, in multiply-adds of a dense GEMM (D input channels,
# E = M * d output channels, U touched pixels of the level's I * H * W, Q * M * P * 4 corners):
#   "dense"   project every pixel, then sample d per head:          pixels * D * E
#   "project" gather the U touched raw rows, project them:          U * D * (E + _GATHER_COST)
#   "sample"  gather the U touched raw rows into a compact table,
#             sample its D channels per corner, project per head:   U * D * (_GATHER_COST + _COPY_COST)
#                                                                   + corners * D * _BAG_COST + Q * D * E
# Measured on one core (Xeon, torch 2.13, D = 256, 10^4-10^5-pixel maps, NCHW and channels-last): a
# GEMM multiply-add costs 0.03-0.04 ns, a gathered element 1.4-3 ns (about 48 multiply-adds), an
# element of embedding_bag over a compact (U, D) table 0.15 ns (about 5). The smallest wins: "dense"
# when most pixels are touched and E is small, "sample" when E is large against the corners per
# touched pixel (e.g. few queries and E = 128), "project" in between.
_GATHER_COST = 48.0
_BAG_COST = 5.0
# "direct" (channels-last maps only): embedding_bag straight over the level's free (pixels, D) row
# view, no gather: corners * D * _DIRECT_BAG_COST + Q * D * E. With the queries in image order
# (_SORT_CELL below) its rows are read about as fast as a compact table's (it was 6, random 1 KiB
# rows of a 10^5-row table missing the cache, before the queries were sorted). Measured per level with
# benchmarks/msdff.py's setting, paper width, 2,500-8,000 radar-band voxels: "direct" 10-55 ms forward
# against 10-91 ms for "sample" on every level P2-P6, and 149-220 ms against 165-245 ms with
# gradients. So "sample" (and its (U, D) table: 57 MiB on P2 at 8,000 voxels) is left to NCHW maps.
_DIRECT_BAG_COST = _BAG_COST
# The static-shape path (functional/deform/bag.py, sample_project_static) bags every corner's row straight
# from the level's table in fixed-size bags, without the touched plans' query blocks: an element costs
# about 10 multiply-adds there (0.30-0.38 ns against 0.035 ns per GEMM multiply-add; MSDFF at the paper's
# width on a VoD image, 2,500 / 8,000 radar-band voxels, channels-last levels, one core of a Xeon, torch
# 2.13, 2026-12-04). Per level it projects every pixel when that costs less.
_STATIC_BAG_COST = 10.0
# It bags its queries in blocks of this many bytes of (queries * M, C) raw samples (bag.static_blocks: 1,024
# queries at M = 8, C = 256 float32), in row order, so that a block's samples and corner arrays stay in cache
# and its temporaries are reused from the heap: one block of every query (65 MiB of samples at 8,000 voxels)
# came back as fresh pages on each call (the bags of P2 117 -> 63 ms at 8,000 voxels with glibc's mmap
# threshold raised, 75 ms in blocks either way). Measured with `python benchmarks/static_path.py --block-mib
# 2 4 8 16 0 --repeats 9` (the static MSDFF / eager at 2,500 and 8,000 voxels, paper width, channels-last,
# 2 / 4 / 8 / 16 MiB / one block: 1.36 / 1.20 / 1.27 / 1.23 / 1.44 and 1.43 / 1.42 / 1.33 / 1.46 / 1.79; the AMD
# EPYC host, one thread, 2026-12-05).
_STATIC_BLOCK_BYTES = 8 << 20
# "sample" gathers the touched rows in pieces and concatenates them into one table (a second copy).
_COPY_COST = 8.0
_PROJECT_CHUNK = 4096  # touched rows gathered at a time (4 MiB of 256 float32 channels)
# The raw-row plans bag their queries in blocks of this many bytes of (queries * M, D) samples
# (benchmarks/msdff.py; 4 MiB = 512 queries at M = 8, D = 256 float32).
_RAW_CHUNK_BYTES = 4 << 20
# The touched plans take the queries in image order (by image, then along a Hilbert curve of square
# cells of _SORT_CELL pixels of the finest level): neighbouring queries read neighbouring rows, still
# in cache, and a block of queries reads one compact patch of the image. Measured with
# benchmarks/order.py (msdff.py's setting, paper width, one core of an AMD EPYC with 1 MiB of L2,
# 9 interleaved rounds) against the earlier order by 64 bands of rows then u: forward 0.85-0.93 of
# the time, forward+backward 0.78-0.93 (2,500-8,000 queries, uniform and radar band); Z order
# 0.87-1.0; cells of 1 and 4 pixels within the noise of 2. Against no sort the bands were 1.3-1.5x
# faster (forward).
_SORT_CELL = 2.0
# With gradients: the backward of embedding_bag over raw rows (per-corner weight gradients: one D-long
# dot product per corner) costs about _BAG_BACKWARD forward passes (measured on one core: 4-5x the
# forward for fwd+bwd); "project" also zero-fills a dense (pixels, E) map and its gradient for
# grid_sample, _FILL_COST per element.
_BAG_BACKWARD = 3.0
_FILL_COST = 0.1

# ---------------------------------------------------------------------------------------------------
# Plan of method="auto" per device (the cost model above was measured on a CPU only)
# ---------------------------------------------------------------------------------------------------
# On a GPU (and on any device other than the CPU) the "touched" plans do not pay: the dense GEMM that
# projects every pixel is nearly free there, while the planner's mark array, int(inner.sum()) and
# nonzero() synchronise the host with the device on every level and call; and the gathered-pixel
# bilinear sample ("gather") is built from the same operations. So off the CPU, and on every device
# while a graph is captured (torch.compile / export / ONNX: sizes must not depend on data), MSDFF
# projects first and samples with grid_sample ("grid") and bilinear_sample uses grid_sample ("grid").
# The CPU keeps the measured planner ("touched") and the gather ("gather", 2-6x faster than grid_sample
# on one core, benchmarks/msdff.py). Under torch.compile (not export) on the CPU, both stay as opaque ops:
# MSDFF's sampling op (samplers/msdff.py) and the gather (functional/deform/gather_op.py).
_MSDFF_AUTO = {"cpu": "touched"}
_BILINEAR_AUTO = {"cpu": "gather"}
_STATIC = "grid"  # the plan of every other device and of graph capture


# ---------------------------------------------------------------------------------------------------
# Backend of the sampling op (functional/deform/op.py) per device
# ---------------------------------------------------------------------------------------------------
# "touched": the CPU plans above (measured: benchmarks/msdff.py). "triton": the Triton kernels
# (functional/deform/triton/), where triton imports and the inputs suit them (float32 / bfloat16 /
# float16, heads of at most 256 channels), else the fallback; checked numerically and compiled for
# sm_80 / sm_90 on a CPU (tests/functional/test_triton_kernels.py), NOT YET TIMED on a GPU: the choice
# waits for benchmarks/gpu_check.py (`make gpu-check`: Triton op vs grid path vs mmcv's op). "grid":
# project every pixel, F.grid_sample per level (every other device, and the fallback).
SAMPLING_BACKENDS = {"cpu": "touched", "cuda": "triton"}
SAMPLING_FALLBACK = "grid"
# The oldest Triton the kernels compile with: they call tl.floor, which triton.language exports from 3.0
# (2.2 and 2.3, torch 2.2-2.3's, have it only as tl.math.floor; 2.1, torch 2.1's, also lacks the
# enable_fp_fusion launch option). Compiled for sm_80 / sm_90 on a CPU with Triton 3.0.0 and 3.1.0 (every
# kernel, dtype and head width of tests/functional/triton_aot.py), 3.6 and 3.9 (that test). With an older
# triton installed, "auto" takes the fallback up front (no failed first launch, no warning); forcing
# "triton" is an error naming both versions.
TRITON_MIN_VERSION = (3, 0)
# Under torch.compile, MSDFF's sampling with gradients per device: "op" (the sampling op, one opaque node;
# its forward runs the backend under autograd and keeps the graph for the backward, functional/deform/kept.py)
# or "grid" (the static grid plan of standard operators, which inductor compiles).
# CPU: "op", measured on one core (FusionBlock(MSDFF) of benchmarks/compile.py at 4,100 voxels, a quarter
# of them outside the image, inductor, 11 interleaved rounds in one process, load average about 1,
# 2026-12-03): a training step 126 ms with the op, 251 ms with the grid plan, 116 ms eager (first call
# 12 s against 9 s). The script: python benchmarks/compile_training.py (the same measurement).
COMPILED_TRAINING = {"cpu": "op"}


# ---------------------------------------------------------------------------------------------------
# MSDFF's sampling in an ONNX graph, per device of the exported tensors
# ---------------------------------------------------------------------------------------------------
# "per_level" (functional/deform/grid.py, sample_project_onnx): per level the cheaper of projecting every
# pixel (a 1 x 1 Conv, then GridSample of d channels per head) and one GridSample of the raw C channels at
# every point of every head, projected per head after (MatMul). In onnxruntime on one core the raw form
# costs about _ONNX_GRID_RAW_COST Conv multiply-adds per sampled channel: GridSample's 2.4-3.7 ns per
# channel against 0.034 ns per Conv multiply-add (the floors table of `python benchmarks/static_path.py`:
# MSDFF at the paper's width on a VoD image, N = 2,500 / 8,000, an AMD EPYC 2-vCPU guest, onnxruntime
# 1.32 CPU provider, 2026-12-05), plus its transposes and the per-head MatMul: with 150 the two forms of
# P2 (304 x 484) break even at about 7,800 voxels, of P3 (152 x 242) at about 2,000. Measured in the whole
# MSDFF (the same host and benchmark): raw P2 and P3 (the constant at 100) 262 / 840 ms at 2,500 / 8,000
# voxels, raw P2 only (150) 279 / 663 ms, every level project-first 534 / 644 ms (with a copy of every level,
# since removed: about 137 ms on P2). A graph serves every voxel count: it is planned for
# bag.STATIC_PLAN_QUERIES. "project" (every other device: on a GPU the projection is one cheap GEMM): project
# every pixel of every level first.
ONNX_SAMPLING = {"cpu": "per_level"}
_ONNX_GRID_RAW_COST = 150.0


def onnx_sampling_per_level(device_type: str) -> bool:
    """Whether MSDFF's ONNX form on ``device_type`` chooses per level (``ONNX_SAMPLING``; else project-first)."""
    return ONNX_SAMPLING.get(device_type, "project") == "per_level"


def msdff_auto_method(device_type: str, static: bool) -> str:
    """MSDFF's plan for ``method="auto"`` on ``device_type`` (``"touched"`` or ``"grid"``)."""
    return _STATIC if static else _MSDFF_AUTO.get(device_type, _STATIC)


def compiled_training_uses_op(device_type: str) -> bool:
    """Whether MSDFF's sampling with gradients under ``torch.compile`` on ``device_type`` is the sampling op
    (``COMPILED_TRAINING``; devices without an entry: the op)."""
    return COMPILED_TRAINING.get(device_type, "op") == "op"


def bilinear_auto_method(device_type: str, static: bool) -> str:
    """``bilinear_sample``'s method for ``method="auto"`` on ``device_type`` (``"gather"`` or ``"grid"``)."""
    return _STATIC if static else _BILINEAR_AUTO.get(device_type, _STATIC)
# The projected plans ("dense", "project") then read d = E / M channels per head and corner: forward
# from an embedding bag over the projected table (_BAG_COST per element), with gradients through
# F.grid_sample on the (M, d, H, W) per-head views of the projected map, whose forward + backward
# costs about 400 multiply-adds per element (measured on one core with benchmarks/msdff.py at the
# paper's width, d = 32: 12-16 ns per element against 0.035 ns per GEMM multiply-add). Negligible at
# d = 2-4 (the narrow layout), it decides the plan at d = 32.
_GRID_SAMPLE_COST = 400.0
