# MSSF-SECOND on TJ4DRadSet: the VoD model (mssf_second_vod.py) on the paper's TJ4D voxel range
# 0..70.4 x -40..40 x -4..2 m (voxels 0.05 x 0.05 x 0.125 m: 1408 x 1600 x 48, sparse shape z + 1 = 49), the 5 input
# features x, y, z, V_r, Power, four classes and the paper's TJ4D anchor sizes (its (w, l, h) given as mmdet3d's
# (l, w, h)). Anchor bottoms as KITTI's (car, truck -1.78; pedestrian, cyclist -0.6): not from the paper. The
# authors' TJ4D voxels are 0.15 m high (z 40 cells): voxel_size [0.05, 0.05, 0.15] and sparse_shape [41, 1600, 1408]
# in every place below give theirs.
_base_ = ["./mssf_second_vod.py"]
grid_range = [0, -40, -4, 70.4, 40, 2]
voxel_size = [0.05, 0.05, 0.125]
_iou = dict(type="mmdet3d.BboxOverlapsNearest3D")
model = dict(
    data_preprocessor=dict(voxel_layer=dict(point_cloud_range=grid_range, voxel_size=voxel_size)),
    pts_voxel_encoder=dict(num_features=5),
    pts_middle_encoder=dict(in_channels=5, sparse_shape=[49, 1600, 1408], point_cloud_range=grid_range,
                            voxel_size=voxel_size),
    pts_bbox_head=dict(
        num_classes=4,
        anchor_generator=dict(
            ranges=[[0, -40, -1.78, 70.4, 40, -1.78], [0, -40, -0.6, 70.4, 40, -0.6], [0, -40, -0.6, 70.4, 40, -0.6],
                    [0, -40, -1.78, 70.4, 40, -1.78]],
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
