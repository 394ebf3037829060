# TJ4DRadSet, single-scan radar + the camera (the MSSF model). As tj4d_radar.py, plus the image: loaded after
# the point augmentation (no image augmentation, the paper's setting) and resized to img_scale for the network.
_base_ = ["./tj4d_radar.py"]
img_scale = (1280, 960)  # keep_ratio: images up to 1280 x 960 keep their size (the authors do not resize)
input_modality = dict(use_lidar=True, use_camera=True)
train_pipeline = [
    {{_base_.load_points}},
    dict(type="LoadAnnotations3D", with_bbox_3d=True, with_label_3d=True),
    # before the image is loaded, so the image is not flipped (flip_ratio would flip it as well)
    dict(type="RandomFlip3D", sync_2d=False, flip_ratio_bev_horizontal=0.5),
    dict(type="GlobalRotScaleTrans", rot_range=[-0.78539816, 0.78539816], scale_ratio_range=[0.95, 1.05]),
    dict(type="PointsRangeFilter", point_cloud_range={{_base_.point_cloud_range}}),
    dict(type="ObjectRangeFilter", point_cloud_range={{_base_.point_cloud_range}}),
    dict(type="ObjectNameFilter", classes={{_base_.class_names}}),
    dict(type="PointShuffle"),
    dict(type="LoadImageFromFile", backend_args=None),
    dict(type="Resize", scale=img_scale, keep_ratio=True),
    dict(type="Pack3DDetInputs", keys=["points", "img", "gt_bboxes_3d", "gt_labels_3d"]),
]
test_pipeline = [
    {{_base_.load_points}},
    dict(type="PointsRangeFilter", point_cloud_range={{_base_.point_cloud_range}}),
    dict(type="LoadImageFromFile", backend_args=None),
    dict(type="Resize", scale=img_scale, keep_ratio=True),
    dict(type="Pack3DDetInputs", keys=["points", "img"]),
]
train_dataloader = dict(dataset=dict(pipeline=train_pipeline, modality=input_modality))
val_dataloader = dict(dataset=dict(pipeline=test_pipeline, modality=input_modality))
test_dataloader = val_dataloader
