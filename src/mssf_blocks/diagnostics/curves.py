"""Fig. 7 of the paper: blur ratio and foreground recall against the segmentation threshold, and their plot.

Definitions in :mod:`mssf_blocks.diagnostics`; import these names from there. matplotlib is imported
only inside :func:`plot_blur_curves`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Optional, Union

import torch
from torch import Tensor

from mssf_blocks.checks.tensors import check_finite, check_floating, check_shape
from mssf_blocks.errors import MSSFError
from mssf_blocks.diagnostics.classify import BlurClassification

__all__ = ["BlurCurves", "blur_ratio", "foreground_recall", "blur_curves", "plot_blur_curves"]


@dataclass(frozen=True)
class BlurCurves:
    """``blur_ratio`` and ``foreground_recall`` sampled at thresholds ``tau`` (all ``(T,)`` float64)."""

    tau: Tensor
    blur_ratio: Tensor
    foreground_recall: Tensor
    n_fore2d: int
    n_fore3d: int
    n_blurred: int


# -- curves -----------------------------------------------------------------------------------------
def _check_scores(scores: Tensor, classes: BlurClassification) -> Tensor:
    if not isinstance(classes, BlurClassification):
        raise MSSFError(f"classes: expected a BlurClassification, got {type(classes).__name__}")
    check_shape(scores, "scores", (classes.fore2d.shape[0],))
    check_floating(scores, "scores")
    check_finite(scores, "scores")
    if classes.n_fore2d == 0:
        raise MSSFError(
            "classes: the ratios are undefined without 2D foreground points (n_fore2d = 0); pool more "
            "frames or check the 2D boxes/masks and projections"
        )
    return scores.detach()


def _tau_tensor(tau, like: Tensor) -> Tensor:
    t = torch.as_tensor(tau, dtype=torch.float64, device=like.device)
    if t.dim() > 1 or not bool(torch.isfinite(t).all()):
        raise MSSFError(f"tau: expected a finite float or a 1-d tensor of thresholds, got {tau!r}")
    return t


def _count_above(values: Tensor, tau: Tensor) -> Tensor:
    """``#{values > t}`` for every ``t`` in ``tau`` via one sort and a binary search."""
    s, _ = torch.sort(values.to(torch.float64))
    return s.numel() - torch.searchsorted(s, tau.reshape(-1), right=True).reshape(tau.shape)


def blur_ratio(scores: Tensor, classes: BlurClassification, tau) -> Tensor:
    """``#{blurred, score > tau} / n_fore2d`` (float64; scalar for a float ``tau``, ``(T,)`` for ``(T,)``).

    Args:
        scores: ``(N,)`` segmentation scores in the order of ``classes``.
        classes: :class:`BlurClassification` of the same points.
        tau: threshold(s).
    """
    s = _check_scores(scores, classes)
    t = _tau_tensor(tau, s)
    return _count_above(s[classes.blurred], t).to(torch.float64) / classes.n_fore2d


def foreground_recall(scores: Tensor, classes: BlurClassification, tau) -> Tensor:
    """``#{3D foreground, score > tau} / n_fore2d`` (float64; scalar or ``(T,)`` like ``tau``)."""
    s = _check_scores(scores, classes)
    t = _tau_tensor(tau, s)
    return _count_above(s[classes.fore3d], t).to(torch.float64) / classes.n_fore2d


def blur_curves(scores: Tensor, classes: BlurClassification, taus: Optional[Tensor] = None) -> BlurCurves:
    """Both curves at thresholds ``taus`` (default ``0, 0.01, ..., 1``)."""
    if taus is None:
        taus = torch.linspace(0.0, 1.0, 101, dtype=torch.float64)
    t = _tau_tensor(taus, scores if isinstance(scores, Tensor) else torch.zeros(0))
    if t.dim() != 1:
        raise MSSFError(f"taus: expected a 1-d tensor of thresholds, got shape {tuple(t.shape)}")
    return BlurCurves(
        tau=t,
        blur_ratio=blur_ratio(scores, classes, t),
        foreground_recall=foreground_recall(scores, classes, t),
        n_fore2d=classes.n_fore2d,
        n_fore3d=classes.n_fore3d,
        n_blurred=classes.n_blurred,
    )



# -- plot -------------------------------------------------------------------------------------------
def plot_blur_curves(
    curves: Union[BlurCurves, Mapping[str, BlurCurves]],
    axes=None,
    path: Optional[str] = None,
    title: Optional[str] = None,
):
    """Plot blur ratio and foreground recall against ``tau`` side by side (paper Fig. 7).

    Needs matplotlib (``pip install matplotlib``, or the ``plot`` extra; the ``dev`` extra includes it).

    Args:
        curves: one :class:`BlurCurves` or ``{label: BlurCurves}`` (one line per model).
        axes: optional pair of matplotlib axes; a new ``1 x 2`` figure otherwise.
        path: if given, the figure is saved there (PNG/PDF by extension).
        title: optional figure title.

    Returns:
        The matplotlib ``Figure``.
    """
    try:
        import matplotlib.pyplot as plt
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(
            "plot_blur_curves needs matplotlib: pip install matplotlib (or 'mssf-blocks[plot]')"
        ) from exc
    if isinstance(curves, BlurCurves):
        curves = {"": curves}
    if not isinstance(curves, Mapping) or not curves or not all(isinstance(c, BlurCurves) for c in curves.values()):
        raise MSSFError("curves: expected a BlurCurves or a non-empty {label: BlurCurves} mapping")
    if axes is None:
        fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    else:
        if len(axes) != 2:
            raise MSSFError(f"axes: expected 2 matplotlib axes, got {len(axes)}")
        fig = axes[0].figure
    ax_b, ax_f = axes
    for label, c in curves.items():
        kw = {"label": label} if label else {}
        ax_b.plot(c.tau.cpu().numpy(), c.blur_ratio.cpu().numpy(), **kw)
        ax_f.plot(c.tau.cpu().numpy(), c.foreground_recall.cpu().numpy(), **kw)
    for ax, name, hint in ((ax_b, "blur ratio", "lower is better"), (ax_f, "foreground recall", "higher is better")):
        ax.set_xlabel(r"segmentation threshold $\tau$")
        ax.set_ylabel(name)
        ax.set_title(f"{name} ({hint})")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.02)
        ax.grid(True, alpha=0.3)
        if any(curves.keys()):
            ax.legend()
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=120)
    return fig
