"""Feature-blurring diagnostics: the paper's Fig. 1 and Fig. 7 as functions.

Feature blurring (paper Sec. I, Fig. 1): a radar point whose projection falls on an object in the
image samples that object's features even when the point itself is not on the object in 3D (it lies
in front of, behind or beside it). Definitions, per projected point (voxel centroid):

* **2D foreground** - its projection falls inside a 2D instance mask or 2D ground-truth box
  (Fig. 1 uses SAM masks, Fig. 7 uses 2D GT boxes);
* **3D foreground** - 2D foreground *and* inside a 3D ground-truth box (of its own sample);
* **3D blurred** - 2D foreground but not 3D foreground.

Fig. 7 (Sec. IV-E "Effects of the Feature-Blurring Problem"), with ``n_fore2d`` the number of 2D
foreground points and the counts taken over every given point (pool frames by concatenating them)::

    blur_ratio(tau)        = #{blurred points with score > tau} / n_fore2d      (lower is better)
    foreground_recall(tau) = #{3D foreground points with score > tau} / n_fore2d  (higher is better)

where the score is the semantic-guided head's sigmoid score. Both curves fall from
``n_blurred / n_fore2d`` and ``n_fore3d / n_fore2d`` (which add up to 1) to 0 as ``tau`` grows.

"Mask blur" (the ablation of Table "Effects of the Feature-Blurring Problem") is an oracle experiment:
the image features sampled by 3D blurred points (found with the ground truth) are masked out
(:func:`mask_blur_projection`, :func:`mask_blur_valid`, :func:`mask_blurred_features`).

Fig. 1(d) (per-instance ratio ``#3D fore / #2D fore``) is :func:`instance_foreground_counts`.

Image coordinates follow the library convention: ``uv`` is normalised, ``((u + 0.5) / W, (v + 0.5) / H)``
with OpenCV pixel coordinates ``(u, v)`` (pixel ``i``'s centre at ``i``); 2D boxes are
``(x1, y1, x2, y2)`` in those pixel coordinates (KITTI ``label_2`` boxes), edges included.

The functions live in three modules by concept: :mod:`.classify` (the per-point classes),
:mod:`.curves` (Fig. 7's curves and their plot) and :mod:`.mask_blur` (the "Mask Blur" oracle
ablation); import them from here.
"""

from mssf_blocks.diagnostics.classify import BlurClassification, classify_feature_blurring, classify_projection, instance_foreground_counts
from mssf_blocks.diagnostics.curves import BlurCurves, blur_curves, blur_ratio, foreground_recall, plot_blur_curves
from mssf_blocks.diagnostics.mask_blur import mask_blur_projection, mask_blur_valid, mask_blurred_features

__all__ = [
    "BlurClassification",
    "BlurCurves",
    "classify_feature_blurring",
    "classify_projection",
    "blur_ratio",
    "foreground_recall",
    "blur_curves",
    "mask_blur_valid",
    "mask_blur_projection",
    "mask_blurred_features",
    "instance_foreground_counts",
    "plot_blur_curves",
]
