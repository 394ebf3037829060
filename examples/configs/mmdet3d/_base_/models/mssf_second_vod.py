# MSSF-SECOND on View-of-Delft: SECOND (voxels 0.05 x 0.05 x 0.125 m, range 0..51.2 x -25.6..25.6 x -3..2 m)
# whose sparse middle encoder is MSSFSparseEncoder (VoxelBackBone8x layout) with n = 2 MSDFF fusion blocks
# and the semantic-guided head; then mmdet3d's SECOND + SECONDFPN and an anchor head with the VoD anchors.
grid_range = [0, -25.6, -3, 51.2, 25.6, 2]  # the grid (the datasets' point_cloud_range)
voxel_size = [0.05, 0.05, 0.125]
sparse_shape = [41, 1024, 1024]  # (z + 1, y, x) cells, as SparseEncoder configs give it
# The image branch is frozen (freeze_img=True, the only switch: with False the whole ResNet-50 + FPN trains) and
# starts from the paper's mmdet HTC R-50-FPN weights, which you give (training refuses a frozen branch that no
# checkpoint filled): `train --image-checkpoint PATH`, or in a config of your own (docs/frameworks.md)
#     model = dict(img_backbone=dict(init_cfg=dict(type="Pretrained", checkpoint=PATH, prefix="backbone.")),
#                  img_neck=dict(init_cfg=dict(type="Pretrained", checkpoint=PATH, prefix="neck.")))
# or load_from / --resume a checkpoint of this model.
model = dict(
    type="MSSFDetector",
    seg_loss_weight=1.0,
    freeze_img=True,
    data_preprocessor=dict(type="Det3DDataPreprocessor", voxel=True,
                           voxel_layer=dict(max_num_points=5, point_cloud_range=grid_range,
                                            voxel_size=voxel_size, max_voxels=(16000, 40000)),
                           mean=[123.675, 116.28, 103.53],
                           std=[58.395, 57.12, 57.375], bgr_to_rgb=True, pad_size_divisor=32),
    img_backbone=dict(type="mmdet.ResNet", depth=50, num_stages=4, out_indices=(0, 1, 2, 3), frozen_stages=-1,
                      norm_cfg=dict(type="BN", requires_grad=True), norm_eval=False, style="pytorch"),
    img_neck=dict(type="mmdet.FPN", in_channels=[256, 512, 1024, 2048], out_channels=256, num_outs=4),
    pts_voxel_encoder=dict(type="HardSimpleVFE", num_features=7),
    pts_middle_encoder=dict(
        type="MSSFSparseEncoder", in_channels=7, sparse_shape=sparse_shape, point_cloud_range=grid_range,
        voxel_size=voxel_size, layout="VoxelBackBone8x", num_fusion_blocks=2, fusion="msdff",
        fusion_position="before_residual", image_channels=[256, 256, 256, 256], msdff_heads=8, msdff_points=4,
        msdff_value_dim=None, seg_hidden=[256, 256], image_aug="meta"),
    pts_backbone=dict(type="SECOND", in_channels=256, layer_nums=[5, 5], layer_strides=[1, 2], out_channels=[128, 256]),
    pts_neck=dict(type="SECONDFPN", in_channels=[128, 256], upsample_strides=[1, 2], out_channels=[256, 256]),
    pts_bbox_head=dict(
        type="Anchor3DHead", num_classes=3, in_channels=512, feat_channels=512, use_direction_classifier=True,
        assign_per_class=True,
        anchor_generator=dict(
            type="Anchor3DRangeGenerator",
            # Car, Pedestrian, Cyclist: bottom heights as KITTI's, sizes (l, w, h) of VoD's official config
            ranges=[[0, -25.6, -1.78, 51.2, 25.6, -1.78], [0, -25.6, -0.6, 51.2, 25.6, -0.6],
                    [0, -25.6, -0.6, 51.2, 25.6, -0.6]],
            sizes=[[3.9, 1.6, 1.56], [0.8, 0.6, 1.73], [1.76, 0.6, 1.73]], rotations=[0, 1.57], reshape_out=False),
        diff_rad_by_sin=True,
        bbox_coder=dict(type="DeltaXYZWLHRBBoxCoder"),
        loss_cls=dict(type="mmdet.FocalLoss", use_sigmoid=True, gamma=2.0, alpha=0.25, loss_weight=1.0),
        loss_bbox=dict(type="mmdet.SmoothL1Loss", beta=1.0 / 9.0, loss_weight=2.0),
        loss_dir=dict(type="mmdet.CrossEntropyLoss", use_sigmoid=False, loss_weight=0.2)),
    train_cfg=dict(pts=dict(
        assigner=[
            dict(type="Max3DIoUAssigner", iou_calculator=dict(type="mmdet3d.BboxOverlapsNearest3D"),
                 pos_iou_thr=0.6, neg_iou_thr=0.45, min_pos_iou=0.45, ignore_iof_thr=-1),  # Car
            dict(type="Max3DIoUAssigner", iou_calculator=dict(type="mmdet3d.BboxOverlapsNearest3D"),
                 pos_iou_thr=0.5, neg_iou_thr=0.35, min_pos_iou=0.35, ignore_iof_thr=-1),  # Pedestrian
            dict(type="Max3DIoUAssigner", iou_calculator=dict(type="mmdet3d.BboxOverlapsNearest3D"),
                 pos_iou_thr=0.5, neg_iou_thr=0.35, min_pos_iou=0.35, ignore_iof_thr=-1),  # Cyclist
        ],
        allowed_border=0, pos_weight=-1, debug=False)),
    test_cfg=dict(pts=dict(use_rotate_nms=True, nms_across_levels=False, nms_thr=0.01, score_thr=0.1,
                           min_bbox_size=0, nms_pre=100, max_num=50)),
)
