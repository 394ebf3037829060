"""Issue 42, item 3: with a triton older than the kernels need (torch 2.1 brings triton 2.1, which lacks
``tl.floor`` and the ``enable_fp_fusion`` launch option), ``"auto"`` takes the grid path up front: no
failed first launch and no warning. Forcing ``"triton"`` there is an error naming both versions.

The installed version is mocked (``op._TRITON_VERSION``; its reader with fake package metadata), and the
device is the CPU with the device table mocked to give it ``"triton"``, so the test needs neither a GPU
nor an old triton. Before the fix the old version was tried: the kernels' launch (a stub that raises
here, as triton 2.1's compile does) failed and warned.
"""

from __future__ import annotations

import importlib.metadata
import sys
import types
import warnings

import pytest
import torch

from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.deform import grid
from mssf_blocks.functional.deform import op as sampling_op
from mssf_blocks.functional.plan_costs import TRITON_MIN_VERSION


def _metadata(versions):
    def version(dist):
        if dist not in versions:
            raise importlib.metadata.PackageNotFoundError(dist)
        return versions[dist]

    return version


def test_version_read_from_package_metadata():
    assert sampling_op._triton_version(_metadata({"triton": "2.1.0"})) == (2, 1)
    assert sampling_op._triton_version(_metadata({"pytorch-triton": "3.0.0+45fff310c8"})) == (3, 0)
    assert sampling_op._triton_version(_metadata({"triton": "3.10.1"})) == (3, 10)
    assert sampling_op._triton_version(_metadata({})) is None  # e.g. a source tree: the kernels are tried
    assert TRITON_MIN_VERSION == (3, 0)


def _inputs(seed=0):
    g = torch.Generator().manual_seed(seed)
    levels = [torch.randn(1, 1, 4, 6, 8, generator=g), torch.randn(1, 1, 4, 3, 4, generator=g)]
    q, m, d, p = 5, 2, 3, 2
    locations = torch.rand(q, m, 2, p, 2, generator=g)
    weights = torch.rand(q, m, 2, p, generator=g)
    proj_w, proj_b = torch.randn(m, d, 4, generator=g), torch.randn(m, d, generator=g)
    return levels, torch.zeros(q, dtype=torch.long), locations, weights, proj_w, proj_b


@pytest.fixture
def triton_on_cpu(monkeypatch):
    triton_on_a_device(monkeypatch)


def triton_on_a_device(monkeypatch):
    """The CPU as a device whose table entry is "triton" (as CUDA's is), triton installed, no earlier
    failure, and a kernel launch that fails as triton 2.1's compile does if it is ever reached (also the
    docs' Common-mistakes table's stand-in: tests/helpers/mistakes_library.py)."""
    monkeypatch.delenv(sampling_op.ENV_VAR, raising=False)
    monkeypatch.setenv("TRITON_INTERPRET", "1")  # (CPU tensors: the kernels' own condition)
    monkeypatch.setattr(sampling_op, "SAMPLING_BACKENDS", {"cpu": "triton"})
    monkeypatch.setattr(sampling_op, "_HAS_TRITON", True)
    monkeypatch.setattr(sampling_op, "_TRITON_FAILURE", [])

    def old_compile(*args, **kwargs):
        raise TypeError("forward_kernel() got an unexpected keyword argument 'enable_fp_fusion'")

    stub = types.ModuleType("mssf_blocks.functional.deform.triton.launch")
    stub.forward = stub.backward = old_compile
    package = sys.modules.get("mssf_blocks.functional.deform.triton")
    if package is None:
        import mssf_blocks.functional.deform.triton as package
    monkeypatch.setitem(sys.modules, stub.__name__, stub)
    monkeypatch.setattr(package, "launch", stub, raising=False)


@pytest.mark.parametrize("version", [(2, 1), (2, 3)])
def test_old_triton_takes_the_grid_path_up_front_without_a_warning(triton_on_cpu, monkeypatch, version):
    monkeypatch.setattr(sampling_op, "_TRITON_VERSION", version)
    args = _inputs()
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the failure-then-fallback warning would fail here
        out = sampling_op.deform_sample_project(*args, backend="auto")
    torch.testing.assert_close(out, grid.sample_project(*args), rtol=0, atol=0)
    assert sampling_op.resolve_backend("auto", "cpu", torch.float32, 32) == "grid"
    assert sampling_op._TRITON_FAILURE == []
    with pytest.raises(MSSFError, match=rf"backend: 'triton' cannot serve these inputs: the kernels need triton >= "
                                        rf"3\.0 .*this is triton {version[0]}\.{version[1]}"):
        sampling_op.resolve_backend("triton", "cpu", torch.float32, 32)


def test_new_enough_or_unknown_triton_is_still_chosen(triton_on_cpu, monkeypatch):
    for version in ((3, 0), (3, 9), None):
        monkeypatch.setattr(sampling_op, "_TRITON_VERSION", version)
        assert sampling_op.resolve_backend("auto", "cpu", torch.float32, 32) == "triton"
