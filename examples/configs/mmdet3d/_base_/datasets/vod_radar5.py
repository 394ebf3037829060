# View-of-Delft, 5-scan radar only (the radar-only twins). Info files: python -m mssf_examples.mmdet3d infos
# --root data/view_of_delft --sensor radar_5frames (writes vod_infos_{train,val}.pkl into data_root).
dataset_type = "VoDDataset"
data_root = "data/view_of_delft/radar_5frames/"
class_names = ["Car", "Pedestrian", "Cyclist"]
point_cloud_range = [0, -25.6, -3, 51.2, 25.6, 2]
metainfo = dict(classes=class_names)
input_modality = dict(use_lidar=True, use_camera=False)
backend_args = None
# x, y, z, RCS, v_r, v_r_comp, time (the paper's f_in)
load_points = dict(type="LoadPointsFromFile", coord_type="LIDAR", load_dim=7, use_dim=7, backend_args=backend_args)
train_pipeline = [
    load_points,
    dict(type="LoadAnnotations3D", with_bbox_3d=True, with_label_3d=True),
    dict(type="RandomFlip3D", sync_2d=False, flip_ratio_bev_horizontal=0.5),
    dict(type="GlobalRotScaleTrans", rot_range=[-0.78539816, 0.78539816], scale_ratio_range=[0.95, 1.05]),
    dict(type="PointsRangeFilter", point_cloud_range=point_cloud_range),
    dict(type="ObjectRangeFilter", point_cloud_range=point_cloud_range),
    dict(type="ObjectNameFilter", classes=class_names),
    dict(type="PointShuffle"),
    dict(type="Pack3DDetInputs", keys=["points", "gt_bboxes_3d", "gt_labels_3d"]),
]
test_pipeline = [
    load_points,
    dict(type="PointsRangeFilter", point_cloud_range=point_cloud_range),
    dict(type="Pack3DDetInputs", keys=["points"]),
]
train_dataloader = dict(
    batch_size=4, num_workers=4, persistent_workers=True,
    sampler=dict(type="DefaultSampler", shuffle=True),
    dataset=dict(type=dataset_type, data_root=data_root, ann_file="vod_infos_train.pkl",
                 data_prefix=dict(pts="training/velodyne", img="training/image_2"), pipeline=train_pipeline,
                 modality=input_modality, metainfo=metainfo, box_type_3d="LiDAR", test_mode=False,
                 pcd_limit_range=point_cloud_range, backend_args=backend_args))
val_dataloader = dict(
    batch_size=1, num_workers=1, persistent_workers=True, drop_last=False,
    sampler=dict(type="DefaultSampler", shuffle=False),
    dataset=dict(type=dataset_type, data_root=data_root, ann_file="vod_infos_val.pkl",
                 data_prefix=dict(pts="training/velodyne", img="training/image_2"), pipeline=test_pipeline,
                 modality=input_modality, metainfo=metainfo, box_type_3d="LiDAR", test_mode=True,
                 pcd_limit_range=point_cloud_range, backend_args=backend_args))
test_dataloader = val_dataloader
val_evaluator = dict(type="VoDMetric", ann_file=data_root + "vod_infos_val.pkl")
test_evaluator = val_evaluator
