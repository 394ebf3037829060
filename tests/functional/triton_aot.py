"""Ahead-of-time compile of every Triton kernel variant of the sampling op, for a GPU target, without a GPU.

Run as a script in a process *without* ``TRITON_INTERPRET`` (``tests/functional/test_triton_kernels.py``
starts it)::

    python tests/functional/triton_aot.py 80 90

For every CUDA compute capability given, every kernel (forward; backward with and without the value
gradient), value dtype (float32, bfloat16, float16) and head width ``d`` in ``HEAD_DIMS`` at
the launch configuration of :func:`mssf_blocks.functional.deform.triton.kernels.launch_config`, it compiles
the kernel to PTX and cubin with ``triton.compile(..., target=GPUTarget("cuda", cc, 32))`` (the wheel
brings ``ptxas``) and reads the registers and spill stores of the cubin with the wheel's
``cuobjdump -res-usage`` (registers, stack frame) and its spills with ``ptxas -v`` on the same PTX.
Prints one JSON object per line: ``{"kernel", "cc", "dtype", "d", "block_q", "num_warps", "registers",
"stack_bytes", "local_bytes", "spill_stores", "spill_loads"}``.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

if os.environ.get("TRITON_INTERPRET"):
    raise SystemExit("triton_aot.py: run without TRITON_INTERPRET (the interpreter compiles nothing)")

import triton  # noqa: E402
from triton.backends.compiler import GPUTarget  # noqa: E402
from triton.compiler import ASTSource  # noqa: E402

from mssf_blocks.functional.deform.triton import kernels as tk  # noqa: E402

DTYPES = {"float32": "fp32", "bfloat16": "bf16", "float16": "fp16"}
HEAD_DIMS = (32, 64, 256)  # the paper's d = 256 / 8 heads, the tests' 64, MAX_HEAD_DIM
M = 8  # heads (a grid axis and a stride: the register use does not depend on it)


def _signature(kernel, value_ty: str, constexprs: dict) -> dict:
    types = {
        "value_ptr": f"*{value_ty}", "shapes_ptr": "*i32", "starts_ptr": "*i32", "index_ptr": "*i64",
        "loc_ptr": "*fp32", "wt_ptr": "*fp32", "out_ptr": f"*{value_ty}", "grad_out_ptr": f"*{value_ty}",
        "grad_value_ptr": "*fp32", "grad_loc_ptr": "*fp32", "grad_wt_ptr": "*fp32", "Q": "i32", "S": "i32",
        "L": "i32", "P": "i32",
    }
    sig = {}
    for name in kernel.arg_names:
        sig[name] = "constexpr" if name in constexprs else types.get(name, "i64")
    return sig


def _res_usage(cubin: bytes, bin_dir: Path) -> dict:
    """Registers and stack frame (local memory: spills) of the cubin, by ``cuobjdump -res-usage``."""
    with tempfile.NamedTemporaryFile(suffix=".cubin") as f:
        f.write(cubin)
        f.flush()
        text = subprocess.run([str(bin_dir / "cuobjdump"), "-res-usage", f.name], check=True,
                              capture_output=True, text=True).stdout
    regs, stack, local = (re.search(rf"\b{key}:(\d+)", text) for key in ("REG", "STACK", "LOCAL"))
    if not (regs and stack and local):
        raise RuntimeError(f"cuobjdump -res-usage: unexpected output {text!r}")
    return {"registers": int(regs.group(1)), "stack_bytes": int(stack.group(1)), "local_bytes": int(local.group(1))}


def _ptxas(cc: int, bin_dir: Path) -> str:
    """The ``ptxas`` Triton itself uses for ``cc`` (newer Triton ships a second one for sm_90 and up)."""
    try:
        from triton.backends.nvidia.compiler import get_ptxas
    except ImportError:
        return str(bin_dir / "ptxas")
    return get_ptxas(cc).path


def _ptxas_spills(ptx: str, cc: int, bin_dir: Path) -> dict:
    """Spill stores and loads in bytes, from ``ptxas -v`` on the kernel's PTX (the same compile)."""
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "k.ptx"
        src.write_text(ptx)
        arch = f"sm_{cc}a" if cc == 90 else f"sm_{cc}"
        res = subprocess.run([_ptxas(cc, bin_dir), "-v", f"--gpu-name={arch}", str(src), "-o", str(Path(tmp) / "k.o")],
                             check=True, capture_output=True, text=True)
    text = res.stdout + res.stderr
    m = re.search(r"(\d+) bytes spill stores, (\d+) bytes spill loads", text)
    if not m:
        raise RuntimeError(f"ptxas -v: unexpected output {text!r}")
    return {"spill_stores": int(m.group(1)), "spill_loads": int(m.group(2))}


def main(ccs) -> None:
    bin_dir = Path(triton.__file__).parent / "backends" / "nvidia" / "bin"
    variants = [("forward", tk.forward_kernel, None), ("backward", tk.backward_kernel, True),
                ("backward_no_value_grad", tk.backward_kernel, False)]
    for cc in ccs:
        for name, kernel, value_grad in variants:
            for dtype, ty in DTYPES.items():
                for d in HEAD_DIMS:
                    block_q, block_d, warps = tk.launch_config(d, backward=value_grad is not None)
                    constexprs = {"M": M, "D": d, "BLOCK_Q": block_q, "BLOCK_D": block_d}
                    if value_grad is not None:
                        constexprs["VALUE_GRAD"] = value_grad
                    src = ASTSource(kernel, _signature(kernel, ty, constexprs), constexprs=constexprs)
                    compiled = triton.compile(src, target=GPUTarget("cuda", cc, 32),
                                              options={"num_warps": warps, "enable_fp_fusion": tk.FP_FUSION})
                    row = {"kernel": name, "cc": cc, "dtype": dtype, "d": d, "block_q": block_q, "num_warps": warps}
                    row.update(_res_usage(compiled.asm["cubin"], bin_dir))
                    row.update(_ptxas_spills(compiled.asm["ptx"], cc, bin_dir))
                    print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or [80, 90])
