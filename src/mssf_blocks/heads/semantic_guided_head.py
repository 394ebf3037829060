"""``SemanticGuidedHead``: per-voxel foreground score that re-weights the fused voxel features.

Paper Sec. III-E (eq. ``s_seg = Sigmoid(MLP(f_fuse))``, ``f_fuse' = f_fuse * s_seg``): applied to the
output of the last fusion block, supervised by a sigmoid focal loss with foreground = voxel centroid
inside a ground-truth box. The paper's ablation (Table "Effects of the Semantic-Guided Head") switches
the segmentation loss (SL, ``use_loss``) and the score weighting (SW, ``use_weighting``) independently.
"""

from __future__ import annotations

from typing import Optional, Sequence, Tuple, Type, Union

import math

import torch
from torch import Tensor, nn

from mssf_blocks.checks.tensors import to_module_dtype
from mssf_blocks.checks.agreement import check_batch_statistics, check_channels
from mssf_blocks.checks.geometry import check_logits_not_probabilities
from mssf_blocks.errors import MSSFError
from mssf_blocks.functional.heads import points_in_boxes, sigmoid_focal_loss, voxel_foreground_labels
from mssf_blocks.sparse_voxels import SparseVoxels

__all__ = [
    "SemanticGuidedHead",
    "sigmoid_focal_loss",
    "points_in_boxes",
    "voxel_foreground_labels",
]


class SemanticGuidedHead(nn.Module):
    """Foreground/background segmentation of non-empty voxels with score re-weighting.

    ``MLP = [Linear(no bias) - norm - ReLU] * len(hidden) -> Linear(., 1)``; ``score = sigmoid(logit)``;
    the returned voxels carry ``features * score`` (or the input features when ``use_weighting=False``).

    Args:
        in_channels: ``C`` of the voxel features.
        hidden: widths of the hidden layers (default two of 256, ``()`` for a single linear layer).
        use_loss: SL switch: when False, :meth:`loss` returns a zero connected to the graph (so the
            score is learned only through the weighting).
        use_weighting: SW switch: when False, ``forward`` returns the voxels unchanged (scores are still
            computed, e.g. for the loss or diagnostics).
        norm_layer: normalisation layer type taking the width (``nn.BatchNorm1d``), or ``None``.
        prior_prob: if given, the output bias is set to ``-log((1 - pi) / pi)`` so initial scores are
            ``pi`` (the focal-loss paper's 0.01); default ``None`` keeps PyTorch's init (scores ~ 0.5),
            which does not shrink the weighted features at the start of training.
        device, dtype: factory kwargs of the parameters.

    Shapes:
        - voxels: :class:`SparseVoxels` with ``features (N, C)``.
        - output: ``(SparseVoxels with features (N, C), scores (N,))`` [``, logits (N,)`` with
          ``return_logits=True``].

    Host synchronisation: none in ``forward``; one read-back in :meth:`loss` (the targets' checks);
    :meth:`loss_from_boxes` also selects each sample's voxels (``nonzero`` per sample, data-dependent).

    Example:
        >>> import torch
        >>> from mssf_blocks.sparse_voxels import SparseVoxels
        >>> head = SemanticGuidedHead(4, hidden=(8,)).eval()
        >>> vox = SparseVoxels(torch.randn(3, 4), torch.zeros(3, 4, dtype=torch.int32) + torch.tensor(
        ...     [[0, 0, 0, 0], [0, 0, 0, 1], [0, 0, 1, 0]], dtype=torch.int32), (1, 2, 2), 1,
        ...     voxel_size=(0.1, 0.1, 0.1), point_range_min=(0.0, 0.0, 0.0))
        >>> out, scores, logits = head(vox, return_logits=True)
        >>> out.features.shape, scores.shape
        (torch.Size([3, 4]), torch.Size([3]))
    """

    def __init__(
        self,
        in_channels: int,
        hidden: Sequence[int] = (256, 256),
        use_loss: bool = True,
        use_weighting: bool = True,
        norm_layer: Optional[Type[nn.Module]] = nn.BatchNorm1d,
        prior_prob: Optional[float] = None,
        device=None,
        dtype=None,
    ) -> None:
        super().__init__()
        if isinstance(in_channels, bool) or not isinstance(in_channels, int) or in_channels <= 0:
            raise MSSFError(f"in_channels: expected a positive int, got {in_channels!r}")
        try:
            hidden = tuple(hidden)
        except TypeError:
            raise MSSFError(f"hidden: expected a sequence of positive ints, got {hidden!r}") from None
        if any(isinstance(h, bool) or not isinstance(h, int) or h <= 0 for h in hidden):
            raise MSSFError(f"hidden: expected a sequence of positive ints, got {hidden!r}")
        for name, flag in (("use_loss", use_loss), ("use_weighting", use_weighting)):
            if not isinstance(flag, bool):
                raise MSSFError(f"{name}: expected a bool, got {flag!r}")
        if prior_prob is not None and not (isinstance(prior_prob, (int, float)) and 0 < prior_prob < 1):
            raise MSSFError(f"prior_prob: expected a float in (0, 1) or None, got {prior_prob!r}")
        factory = {"device": device, "dtype": dtype}
        self.in_channels = in_channels
        self.hidden = hidden
        self.use_loss = use_loss
        self.use_weighting = use_weighting
        self.prior_prob = prior_prob
        layers = []
        width = in_channels
        for h in hidden:
            # The norm's shift makes a bias in the linear layer redundant.
            layers.append(nn.Linear(width, h, bias=norm_layer is None, **factory))
            if norm_layer is not None:
                layers.append(norm_layer(h, **factory))
            layers.append(nn.ReLU(inplace=True))
            width = h
        self.mlp = nn.Sequential(*layers)
        self.classifier = nn.Linear(width, 1, **factory)
        if prior_prob is not None:
            nn.init.constant_(self.classifier.bias, -math.log((1 - prior_prob) / prior_prob))

    def logits(self, features: Tensor) -> Tensor:
        """``(N,)`` foreground logits of ``(N, C)`` features."""
        check_channels(features, "features", self.in_channels, "SemanticGuidedHead in_channels")
        if not isinstance(features, Tensor) or features.dim() != 2 or features.shape[1] != self.in_channels:
            got = tuple(features.shape) if isinstance(features, Tensor) else type(features).__name__
            raise MSSFError(f"features: expected shape (N, C={self.in_channels}), got {got}")
        # The dtype rule (docs/conventions.md): read in the parameters' dtype, float64 into float32 refused.
        features = to_module_dtype(features, "features", self.classifier.weight.dtype, "SemanticGuidedHead")
        n = features.shape[0]
        if n == 0:
            # Zero rows: skip the MLP (BatchNorm cannot normalise an empty batch) but stay on the graph.
            return features.sum(dim=1) + self.classifier.bias.sum() * 0
        check_batch_statistics(self.mlp, n, "voxels", "a single voxel (N = 1)", "semantic head")
        return self.classifier(self.mlp(features)).squeeze(1)

    def forward(
        self, voxels: SparseVoxels, return_logits: bool = False
    ) -> Union[Tuple[SparseVoxels, Tensor], Tuple[SparseVoxels, Tensor, Tensor]]:
        """Score every voxel and re-weight its features.

        Args:
            voxels: :class:`SparseVoxels` with ``(N, C)`` features.
            return_logits: also return the ``(N,)`` logits (use them for :meth:`loss`).

        Returns:
            ``(voxels', scores)`` or ``(voxels', scores, logits)``; ``voxels'`` has features
            ``features * scores[:, None]`` (unchanged when ``use_weighting=False``).
        """
        if not isinstance(voxels, SparseVoxels):
            raise MSSFError(f"voxels: expected SparseVoxels, got {type(voxels).__name__}")
        check_channels(voxels.features, "voxels.features", self.in_channels, "SemanticGuidedHead in_channels")
        features = to_module_dtype(voxels.features, "voxels.features", self.classifier.weight.dtype,
                                   "SemanticGuidedHead")
        logits = self.logits(features)
        scores = torch.sigmoid(logits)
        out = voxels.replace(features=features * scores[:, None]) if self.use_weighting else voxels
        return (out, scores, logits) if return_logits else (out, scores)

    def loss(
        self,
        logits: Tensor,
        labels: Tensor,
        ignore: Optional[Tensor] = None,
        alpha: float = 0.25,
        gamma: float = 2.0,
    ) -> Tensor:
        """Focal loss of the logits (normalised by ``max(#positives, 1)``), zero when ``use_loss=False``.

        Args:
            logits: ``(N,)`` from ``forward(..., return_logits=True)``.
            labels: ``(N,)`` 0/1 targets (:func:`voxel_foreground_labels`).
            ignore: optional ``(N,)`` bool mask of voxels to leave out.
        """
        if not self.use_loss:
            if not isinstance(logits, Tensor):
                raise MSSFError(f"logits: expected a torch.Tensor, got {type(logits).__name__}")
            # Keep the graph (DDP expects every parameter to receive a gradient) but add nothing.
            return logits.sum() * 0
        if isinstance(logits, Tensor):  # (sigmoid_focal_loss names a non-tensor)
            check_logits_not_probabilities(logits)
        return sigmoid_focal_loss(logits, labels, ignore=ignore, alpha=alpha, gamma=gamma)

    def loss_from_boxes(
        self,
        logits: Tensor,
        centroids: Tensor,
        batch_index: Tensor,
        gt_boxes: Sequence[Tensor],
        margin: float = 0.1,
        origin: str = "center",
    ) -> Tensor:
        """:meth:`loss` with the labels built by :func:`voxel_foreground_labels` from GT boxes."""
        labels, ignore = voxel_foreground_labels(centroids, batch_index, gt_boxes, margin, origin)
        return self.loss(logits, labels, ignore)

    def extra_repr(self) -> str:
        return (
            f"in_channels={self.in_channels}, hidden={self.hidden}, use_loss={self.use_loss}, "
            f"use_weighting={self.use_weighting}, prior_prob={self.prior_prob}"
        )
