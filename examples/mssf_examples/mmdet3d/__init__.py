"""mmdetection3d 1.x support of the examples: ``MSSFDetector`` (:mod:`.detector`), View-of-Delft and TJ4DRadSet
info files (:mod:`.infos`), ``VoDDataset`` / ``TJ4DDataset`` (:mod:`.dataset`), ``VoDMetric`` / ``TJ4DMetric``
(:mod:`.metric`), MSSF-V's ``MSSFVoxelNeXtHead`` (:mod:`.voxelnext_head`) and the authors' MSSF-V checkpoint
(:mod:`.authors_mssf_v`), their registration (:mod:`.plugin`) and the ``python -m mssf_examples.mmdet3d infos|train|test``
entry (:mod:`.cli`). Only :mod:`.infos` works without mmdet3d; the others import it (docs/frameworks.md,
"mmdetection3d").
"""
