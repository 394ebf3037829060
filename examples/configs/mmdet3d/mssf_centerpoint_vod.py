# MSSF-CenterPoint on View-of-Delft (5-scan radar + camera): the paper's plug-and-play CenterPoint with n = 2 MSDFF
# fusion blocks and the semantic head.
# Train: python -m mssf_examples.mmdet3d train examples/configs/mmdet3d/mssf_centerpoint_vod.py (docs/frameworks.md).
# Its radar-only twin: centerpoint_vod_radar.py (the same model less the fusion blocks and the image branch).
_base_ = [
    "./_base_/models/mssf_centerpoint_vod.py",
    "./_base_/datasets/vod_radar5_camera.py",
    "./_base_/schedules/vod_onecycle.py",
    "./_base_/default_runtime.py",
]
