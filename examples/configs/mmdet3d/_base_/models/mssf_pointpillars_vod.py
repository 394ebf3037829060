# MSSF-PointPillars on View-of-Delft (the paper's MSSF-PP): the radar PointPillars of VoD's official config
# (pillars 0.16 m, range 0..51.2 x -25.6..25.6 x -3..2 m, VoD anchors) with n = 2 MSDFF fusion blocks in
# its 2D backbone and the semantic-guided head. The whole BEV path (pillar feature net, blocks, deblocks)
# is MSSFPillarEncoder, which takes the points: no voxelisation in the data preprocessor.
grid_range = [0, -25.6, -3, 51.2, 25.6, 2]  # the grid (the datasets' point_cloud_range)
pillar_size = [0.16, 0.16, 5]
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
    data_preprocessor=dict(type="Det3DDataPreprocessor", voxel=False, mean=[123.675, 116.28, 103.53],
                           std=[58.395, 57.12, 57.375], bgr_to_rgb=True, pad_size_divisor=32),
    img_backbone=dict(type="mmdet.ResNet", depth=50, num_stages=4, out_indices=(0, 1, 2, 3), frozen_stages=-1,
                      norm_cfg=dict(type="BN", requires_grad=True), norm_eval=False, style="pytorch"),
    img_neck=dict(type="mmdet.FPN", in_channels=[256, 512, 1024, 2048], out_channels=256, num_outs=4),
    pts_middle_encoder=dict(
        type="MSSFPillarEncoder", in_channels=7, point_cloud_range=grid_range, voxel_size=pillar_size,
        lift_z_size=0.125, pfn_channels=64, layer_nums=[3, 5, 5], layer_strides=[2, 2, 2], num_filters=[64, 128, 256],
        upsample_strides=[1, 2, 4], num_upsample_filters=[128, 128, 128],
        num_fusion_blocks=2, fusion="msdff", fusion_position="before_residual",
        image_channels=[256, 256, 256, 256], msdff_heads=8, msdff_points=4, seg_hidden=[256, 256]),
    pts_bbox_head=dict(
        type="Anchor3DHead", num_classes=3, in_channels=384, feat_channels=384, use_direction_classifier=True,
        assign_per_class=True,
        anchor_generator=dict(
            type="AlignedAnchor3DRangeGenerator",
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
