"""``benchmarks/_mmcv_build.py``: mmcv's deformable-attention CUDA op built alone from an mmcv source
archive (gpu_check's comparison where mmcv's compiled ops do not install). Without a GPU: the files it
takes from an archive or a tree, and its binding, compiled against torch's headers, asks the linker for
exactly mmcv 2.1.0's two host functions (their signatures as written in mmcv's
``ms_deform_attn_cuda.cu``)."""

import io
import os
import shutil
import subprocess
import sys
import sysconfig
import tarfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO / "benchmarks"))
import _mmcv_build as mb  # noqa: E402

CU = "mmcv-2.1.0/mmcv/ops/csrc/pytorch/cuda/ms_deform_attn_cuda.cu"
FILES = {  # a stand-in for the archive's layout: what the op needs, and files it must leave
    CU: "// the op's CUDA file\n",
    "mmcv-2.1.0/mmcv/ops/csrc/common/pytorch_cuda_helper.hpp": "// helper\n",
    "mmcv-2.1.0/mmcv/ops/csrc/common/cuda/ms_deform_attn_cuda_kernel.cuh": "// kernel\n",
    "mmcv-2.1.0/mmcv/ops/csrc/pytorch/cuda/nms_cuda.cu": "// another op\n",
    "mmcv-2.1.0/mmcv/ops/csrc/pytorch/ms_deform_attn.cpp": "// the CPU dispatch\n",
    "mmcv-2.1.0/setup.py": "# setup\n",
}


def _check_prepared(sources, includes, build):
    binding, cu = map(Path, sources)
    assert cu.read_text() == FILES[CU] and binding.read_text() == mb.BINDING
    shim = Path(includes[0])
    assert (shim / "THC" / "THCAtomics.cuh").read_text().splitlines()[-1] == "#include <ATen/cuda/Atomic.cuh>"
    common = Path(includes[1])
    assert (common / "pytorch_cuda_helper.hpp").read_text() == "// helper\n"
    assert Path(includes[2]) == common / "cuda" and (common / "cuda" / "ms_deform_attn_cuda_kernel.cuh").is_file()
    taken = sorted(str(p.relative_to(build)) for p in build.rglob("*") if p.is_file())
    assert taken == sorted(["csrc/common/cuda/ms_deform_attn_cuda_kernel.cuh", "csrc/common/pytorch_cuda_helper.hpp",
                            "csrc/pytorch/cuda/ms_deform_attn_cuda.cu", "msda_binding.cpp",
                            "shim/THC/THCAtomics.cuh"])


def test_sources_come_from_an_archive_or_a_tree(tmp_path):
    archive = tmp_path / "mmcv-2.1.0.tar.gz"
    with tarfile.open(archive, "w:gz") as tar:
        for name, text in FILES.items():
            info = tarfile.TarInfo(name)
            info.size = len(text.encode())
            tar.addfile(info, io.BytesIO(text.encode()))
    _check_prepared(*mb.prepare_sources(archive, tmp_path / "from_archive"), tmp_path / "from_archive")
    tree = tmp_path / "tree"
    for name, text in FILES.items():
        (tree / name).parent.mkdir(parents=True, exist_ok=True)
        (tree / name).write_text(text)
    _check_prepared(*mb.prepare_sources(tree, tmp_path / "from_tree"), tmp_path / "from_tree")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        mb.prepare_sources(tmp_path / "missing.tar.gz", tmp_path / "b1")
    (tree / CU).unlink()
    with pytest.raises(FileNotFoundError, match="ms_deform_attn_cuda.cu"):
        mb.prepare_sources(tree, tmp_path / "b2")


def test_the_binding_compiles_and_asks_for_mmcvs_two_functions(tmp_path):
    cxx, nm = shutil.which("c++") or shutil.which("g++"), shutil.which("nm")
    if cxx is None or nm is None:
        pytest.skip("no C++ compiler or nm on this machine")
    from torch.utils.cpp_extension import include_paths

    src = tmp_path / "binding.cpp"
    src.write_text(mb.BINDING)
    flags = [f"-I{p}" for p in [*include_paths(), sysconfig.get_paths()["include"]]]
    obj = tmp_path / "binding.o"
    r = subprocess.run([cxx, "-std=c++17", "-c", "-fPIC", "-w", "-DTORCH_EXTENSION_NAME=msda", *flags, str(src),
                        "-o", str(obj)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    undefined = subprocess.run([nm, "-C", "--undefined-only", str(obj)], capture_output=True, text=True).stdout
    asked = sorted(line.split(" U ", 1)[1].strip() for line in undefined.splitlines() if "ms_deform" in line)
    tensor = "at::Tensor const&"
    assert asked == sorted([  # mmcv 2.1.0, mmcv/ops/csrc/pytorch/cuda/ms_deform_attn_cuda.cu
        f"ms_deform_attn_cuda_forward({', '.join([tensor] * 5)}, int)",
        f"ms_deform_attn_cuda_backward({', '.join([tensor] * 6)}, at::Tensor&, at::Tensor&, at::Tensor&, int)",
    ])


def test_a_second_preparation_leaves_the_files_untouched(tmp_path):
    """gpu_check builds the op in a background process during the tests, then loads it in its own process
    with the same folder: rewriting the sources (new time stamps) would make ninja compile it all again."""
    tree = tmp_path / "tree"
    for name, text in FILES.items():
        (tree / name).parent.mkdir(parents=True, exist_ok=True)
        (tree / name).write_text(text)
    build = tmp_path / "build"
    mb.prepare_sources(tree, build)
    written = [p for p in build.rglob("*") if p.is_file()]
    for p in written:
        os.utime(p, (1_000_000, 1_000_000))
    mb.prepare_sources(tree, build)
    assert {p: p.stat().st_mtime for p in written} == {p: 1_000_000 for p in written}
    (tree / CU).write_text("// changed\n")  # a changed source is written again
    mb.prepare_sources(tree, build)
    assert (build / "csrc" / "pytorch" / "cuda" / "ms_deform_attn_cuda.cu").read_text() == "// changed\n"


def test_the_background_build_reports_into_its_log(tmp_path):
    proc = mb.start_build(tmp_path / "missing.tar.gz", tmp_path / "build", tmp_path / "build.log")
    assert proc.wait(timeout=300) != 0
    assert "does not exist" in (tmp_path / "build.log").read_text()
