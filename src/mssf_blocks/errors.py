"""The library's single exception type."""

from __future__ import annotations

__all__ = ["MSSFError"]


class MSSFError(ValueError):
    """Raised for invalid input to any mssf_blocks function or module.

    A subclass of :class:`ValueError`, so ``except ValueError`` keeps working. Messages name the
    argument, what was expected and what was received.
    """
