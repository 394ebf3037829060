"""The Triton backend of the sampling op (CUDA; CPU tensors under ``TRITON_INTERPRET=1``).

``launch.py`` projects every pixel into the kernels' value buffer and launches ``kernels.py`` (forward
and backward). Neither is imported by ``import mssf_blocks``: the op imports ``launch`` when the
backend first runs, so ``triton`` is imported only then. This module reads the installed triton's version
from its package metadata (:func:`installed_version`), without importing it.
"""

from __future__ import annotations

import importlib.metadata
import re
from typing import Optional, Tuple

__all__ = ["installed_version"]

#: Distributions that install the ``triton`` module (PyPI's, and the builds torch's own index pins).
_DISTRIBUTIONS = ("triton", "pytorch-triton", "pytorch-triton-rocm", "pytorch-triton-xpu")


def installed_version(version=importlib.metadata.version) -> Optional[Tuple[int, int]]:
    """The installed triton's ``(major, minor)`` from its package metadata (``triton`` is not imported), or
    ``None`` when no distribution names it (e.g. a source tree on the path: then the kernels are tried).
    The op compares it with ``plan_costs.TRITON_MIN_VERSION``."""
    for dist in _DISTRIBUTIONS:
        try:
            text = version(dist)
        except importlib.metadata.PackageNotFoundError:
            continue
        m = re.match(r"(\d+)\.(\d+)", text or "")
        if m:
            return int(m.group(1)), int(m.group(2))
    return None
