# The radar-only twin of mssf_second_tj4d.py: the same detector with no fusion blocks, no semantic head and no image
# branch, on the radar-only pipeline.
_base_ = [
    "./_base_/models/mssf_second_tj4d.py",
    "./_base_/datasets/tj4d_radar_voxel.py",
    "./_base_/schedules/vod_onecycle.py",
    "./_base_/default_runtime.py",
]
model = dict(
    img_backbone=None,
    img_neck=None,
    pts_middle_encoder=dict(num_fusion_blocks=0, image_channels=None, seg_hidden=None),
)
