"""Deployment helpers: the static-shape path switch (``torch.compile`` / ``torch.export`` / ONNX).

See ``docs/deployment.md``. While a graph is captured the blocks take their static-shape path on their
own; :func:`static_path` forces it in eager mode.
"""

from __future__ import annotations

from ._static import static_path, use_static_path

__all__ = ["static_path", "use_static_path"]
