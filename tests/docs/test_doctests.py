"""Every docstring example in the package runs and prints what it says."""

import doctest
import importlib
import importlib.util
import pkgutil

import pytest

import mssf_blocks

# modules that need an optional package at import (imported lazily by the library itself)
_NEEDS_TRITON = ("mssf_blocks.functional.deform.triton.kernels", "mssf_blocks.functional.deform.triton.launch")
_HAS_TRITON = importlib.util.find_spec("triton") is not None
MODULES = sorted(m.name for m in pkgutil.walk_packages(mssf_blocks.__path__, "mssf_blocks.")
                 if _HAS_TRITON or m.name not in _NEEDS_TRITON)


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples(name):
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.NORMALIZE_WHITESPACE | doctest.ELLIPSIS, verbose=False)
    assert result.failed == 0, f"{result.failed} docstring example(s) failed in {name}"


def test_core_imports_nothing_optional():
    """The core must import with only torch, numpy and einops: no spconv, matplotlib or tqdm at module level."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "class Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] in ('spconv', 'matplotlib', 'tqdm', 'cumm', 'triton'):\n"
        "            raise ImportError('blocked ' + name)\n"
        "sys.meta_path.insert(0, Block())\n"
        "import pkgutil, importlib, mssf_blocks\n"
        "for m in pkgutil.walk_packages(mssf_blocks.__path__, 'mssf_blocks.'):\n"
        f"    if m.name not in {_NEEDS_TRITON!r}:  # (triton: imported when the CUDA backend runs)\n"
        "        importlib.import_module(m.name)\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr
