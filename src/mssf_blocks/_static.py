"""Which execution path the blocks take: the eager fast paths, or the static-shape path.

The eager paths of the fusion blocks size some intermediates by the data (MSDFF's touched-pixel plans,
SFF's gathered corner pixels, the visible-voxel rows of the output norm, the centroid join's
``unique``). Graph capture cannot follow those sizes without a new graph per frame, and exporters need
a fixed set of operators, so while a graph is captured (:func:`~mssf_blocks._checks.is_tracing`) every
block takes its *static-shape path* instead: the same result from operators whose output sizes depend
on input sizes only (``grid_sample``, masks, sorts). :func:`static_path` forces it in eager mode too
(e.g. to check it against the eager path, or for CUDA graphs).
"""

from __future__ import annotations

import contextlib
from typing import Iterator

from ._checks import is_tracing

__all__ = ["static_path", "use_static_path"]

_FORCED = [0]  # nesting depth of static_path() (a list: read by dynamo as a guarded global)


@contextlib.contextmanager
def static_path(enabled: bool = True) -> Iterator[None]:
    """Run the fusion blocks on their static-shape (compile- and export-friendly) path in this block.

    Example:
        >>> import torch
        >>> from mssf_blocks.functional import bilinear_sample
        >>> img, uv = torch.arange(4.0).view(1, 1, 2, 2), torch.tensor([[[0.75, 0.25]]])
        >>> with static_path():
        ...     bilinear_sample(img, uv, torch.tensor([0])).flatten().tolist()
        [1.0]
    """
    _FORCED[0] += 1 if enabled else 0
    try:
        yield
    finally:
        _FORCED[0] -= 1 if enabled else 0


def use_static_path() -> bool:
    """Whether the blocks take the static-shape path now (graph capture, or inside :func:`static_path`)."""
    return _FORCED[0] > 0 or is_tracing()
