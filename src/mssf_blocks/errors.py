"""The library's single exception type."""

from __future__ import annotations

__all__ = ["MSSFError", "MSSFGeometryWarning"]


class MSSFError(ValueError):
    """Raised for invalid input to any mssf_blocks function or module.

    A subclass of :class:`ValueError`, so ``except ValueError`` keeps working. Messages name the
    argument, what was expected and what was received.
    """


class MSSFGeometryWarning(UserWarning):
    """Warned when the geometry of the inputs looks wrong but could be real (no voxel in the image, all
    voxels in one corner, no voxel holding a point): ``docs/conventions.md``, "Common mistakes"."""
