# MSSF-PointPillars on TJ4DRadSet (the paper's MSSF-PP): the VoD model (mssf_pointpillars_vod.py) on the paper's
# TJ4D pillar range 0..69.12 x -39.68..39.68 x -4..2 m (pillars 0.16 m, 6 m high: 432 x 496), the 5 input features
# x, y, z, V_r, Power, four classes and the paper's TJ4D anchor sizes (its (w, l, h), given here as mmdet3d's
# (l, w, h)). Anchor bottoms as KITTI's (car, truck -1.78; pedestrian, cyclist -0.6): not from the paper.
_base_ = ["./mssf_pointpillars_vod.py"]
grid_range = [0, -39.68, -4, 69.12, 39.68, 2]
_iou = dict(type="mmdet3d.BboxOverlapsNearest3D")
model = dict(
    pts_middle_encoder=dict(in_channels=5, point_cloud_range=grid_range, voxel_size=[0.16, 0.16, 6]),
    pts_bbox_head=dict(
        num_classes=4,
        anchor_generator=dict(
            ranges=[[0, -39.68, -1.78, 69.12, 39.68, -1.78], [0, -39.68, -0.6, 69.12, 39.68, -0.6],
                    [0, -39.68, -0.6, 69.12, 39.68, -0.6], [0, -39.68, -1.78, 69.12, 39.68, -1.78]],
            # Car, Pedestrian, Cyclist, Truck
            sizes=[[4.56, 1.84, 1.70], [0.8, 0.6, 1.69], [1.77, 0.78, 1.60], [10.76, 2.66, 3.47]])),
    train_cfg=dict(pts=dict(assigner=[
        dict(type="Max3DIoUAssigner", iou_calculator=_iou, pos_iou_thr=0.6, neg_iou_thr=0.45, min_pos_iou=0.45,
             ignore_iof_thr=-1),  # Car
        dict(type="Max3DIoUAssigner", iou_calculator=_iou, pos_iou_thr=0.5, neg_iou_thr=0.35, min_pos_iou=0.35,
             ignore_iof_thr=-1),  # Pedestrian
        dict(type="Max3DIoUAssigner", iou_calculator=_iou, pos_iou_thr=0.5, neg_iou_thr=0.35, min_pos_iou=0.35,
             ignore_iof_thr=-1),  # Cyclist
        dict(type="Max3DIoUAssigner", iou_calculator=_iou, pos_iou_thr=0.6, neg_iou_thr=0.45, min_pos_iou=0.45,
             ignore_iof_thr=-1),  # Truck
    ])),
)
