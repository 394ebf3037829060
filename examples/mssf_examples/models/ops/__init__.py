"""Detection operators used by the example detectors: box coding (``boxes``), target assignment
(``targets``), rotated BEV non-maximum suppression (``nms``) and box overlaps (``iou``).

Import from the sub-modules, e.g. ``from mssf_examples.models.ops.nms import nms_bev``.
"""
