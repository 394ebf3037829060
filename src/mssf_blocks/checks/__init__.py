"""Every input check of the library, in one place (``docs/architecture.md``, "Where checks go").

* ``tensors.py`` - shapes (named dims), dtypes, finite values, index ranges, triples and ints: the
  checks every function runs at its entry; value-reading ones are :func:`~.tensors.value_check` s,
  skipped while a graph is captured.
* ``agreement.py`` - arguments that must agree (batch sizes, channels, BatchNorm batch statistics).
* ``image_features.py`` - image levels and the projection a sampler reads.
* ``geometry.py`` - geometry sanity: grid against shape, level sizes, coverage warnings, frames of boxes
  and angles; ``first_call.py`` - the one-time checks of a projector's first batch; ``coverage.py`` - the
  running coverage figures; ``calibration.py`` - a framework's calibration against its image size.
* ``arguments.py`` - plain arguments: image sizes, angles, triples, ints, strides.
* ``boxes.py`` - 3D boxes and the label arguments; ``matrices.py`` - ``points_to_sensor`` and 4 x 4 affines.
* ``deform.py`` - the sampling op's inputs; ``spconv_inputs.py`` - what reaches spconv.

The feature-blurring diagnostics keep their few checks beside their own result types
(``diagnostics/``): those checks read ``BlurClassification``, which lives there.

One switch, :func:`set_geometry_checks`, decides where the data-reading geometry checks run (CPU tensors
only by default: on an accelerator each would cost a host synchronisation).
"""

from mssf_blocks.checks.geometry import geometry_checks_enabled, set_geometry_checks

__all__ = ["set_geometry_checks", "geometry_checks_enabled"]
