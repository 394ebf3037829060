# MSSF-SECOND on TJ4DRadSet (single-scan radar + camera), on the paper's TJ4D voxel range.
# Train: python -m mssf_examples.mmdet3d train examples/configs/mmdet3d/mssf_second_tj4d.py (docs/frameworks.md).
# Its radar-only twin: second_tj4d_radar.py (the same model less the fusion blocks and the image branch).
_base_ = [
    "./_base_/models/mssf_second_tj4d.py",
    "./_base_/datasets/tj4d_radar_voxel_camera.py",
    "./_base_/schedules/vod_onecycle.py",
    "./_base_/default_runtime.py",
]
