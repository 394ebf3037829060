# MSSF-VoxelNeXt (the paper's MSSF-V) on TJ4DRadSet (single-scan radar + camera), the paper's settings.
# Train: python -m mssf_examples.mmdet3d train examples/configs/mmdet3d/mssf_voxelnext_tj4d.py (docs/frameworks.md).
# Its radar-only twin: voxelnext_tj4d_radar.py (the same model less the fusion blocks and the image branch).
_base_ = [
    "./_base_/models/mssf_voxelnext_tj4d.py",
    "./_base_/datasets/tj4d_radar_voxel_camera.py",
    "./_base_/schedules/vod_onecycle.py",
    "./_base_/default_runtime.py",
]
