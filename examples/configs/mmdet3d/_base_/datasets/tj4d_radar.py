# TJ4DRadSet, single-scan radar only (the radar-only twin). Info files: python -m mssf_examples.mmdet3d infos
# --dataset tj4d --root data/TJ4DRadSet (writes tj4d_infos_{train,val}.pkl into data_root).
dataset_type = "TJ4DDataset"
data_root = "data/TJ4DRadSet/"
class_names = ["Car", "Pedestrian", "Cyclist", "Truck"]
point_cloud_range = [0, -39.68, -4, 69.12, 39.68, 2]  # the paper's pillar-based range
metainfo = dict(classes=class_names)
input_modality = dict(use_lidar=True, use_camera=False)
backend_args = None
# stored: x, y, z, V_r, Range, Power, Alpha, Beta; used: x, y, z, V_r, Power (the paper's f_in has the
# ego-motion compensated v_rc, which the release does not hold: V_r stands in, as mssf_examples.data.kitti_io.TJ4D_RADAR)
load_points = dict(type="LoadPointsFromFile", coord_type="LIDAR", load_dim=8, use_dim=[0, 1, 2, 3, 5],
                   backend_args=backend_args)
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
    dataset=dict(type=dataset_type, data_root=data_root, ann_file="tj4d_infos_train.pkl",
                 data_prefix=dict(pts="training/velodyne", img="training/image_2"), pipeline=train_pipeline,
                 modality=input_modality, metainfo=metainfo, box_type_3d="LiDAR", test_mode=False,
                 pcd_limit_range=point_cloud_range, backend_args=backend_args))
val_dataloader = dict(
    batch_size=1, num_workers=1, persistent_workers=True, drop_last=False,
    sampler=dict(type="DefaultSampler", shuffle=False),
    dataset=dict(type=dataset_type, data_root=data_root, ann_file="tj4d_infos_val.pkl",
                 data_prefix=dict(pts="training/velodyne", img="training/image_2"), pipeline=test_pipeline,
                 modality=input_modality, metainfo=metainfo, box_type_3d="LiDAR", test_mode=True,
                 pcd_limit_range=point_cloud_range, backend_args=backend_args))
test_dataloader = val_dataloader
val_evaluator = dict(type="TJ4DMetric", ann_file=data_root + "tj4d_infos_val.pkl")
test_evaluator = val_evaluator
