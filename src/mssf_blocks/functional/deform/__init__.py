"""Multi-scale deformable sampling: one op, one place per backend.

``out[q, m] = sum_{l, p} weights[q, m, l, p] * bilinear(values[l][image_index[q], m'], locations[q, m, l, p])``
(Deformable DETR's sampling core, eq. 3 of Zhu et al., ICLR 2021), bilinear with ``align_corners=False``
and zero padding (pixel ``x = u * W_l - 0.5``; corners outside the map read zeros).

* ``op.py``: the op ``torch.ops.mssf_blocks.deform_sample_project`` (sampling of per-head projected
  values, MSDFF's form): inputs checked once at its entry (``checks.py``), the backend chosen by
  device (``plan_costs.SAMPLING_BACKENDS``), registration for ``torch.compile`` / ``torch.export``, with
  ``kept.py`` (the autograd graphs its forward keeps for its backward under ``torch.compile``);
* the backends, each one place: ``touched/`` (the CPU plans), ``grid.py`` (project every pixel,
  ``F.grid_sample``), ``triton/`` (the Triton kernels);
* ``reference.py``: the float64 reference (Deformable DETR's per-level ``F.grid_sample``) the tests
  hold every backend to;
* ``api.py``: the public functions ``ms_deform_sample`` (no projection, values per head or shared) and
  ``ms_deform_sample_project`` (its ``"touched"`` / ``"auto"`` methods are the op), with ``bag.py``
  (their embedding-bag path for values per head).
"""

from mssf_blocks.functional.deform.api import ms_deform_sample, ms_deform_sample_project
from mssf_blocks.functional.deform.op import deform_sample_project
from mssf_blocks.functional.deform.reference import ms_deform_sample_reference

__all__ = ["deform_sample_project", "ms_deform_sample", "ms_deform_sample_project", "ms_deform_sample_reference"]
