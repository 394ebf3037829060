# MSSF-VoxelNeXt on View-of-Delft (the paper's MSSF-V, its main model): VoxelNeXt (voxels 0.05 x 0.05 x 0.125 m,
# range 0..51.2 x -25.6..25.6 x -3..2 m) whose sparse encoder is MSSFSparseEncoder in OpenPCDet's VoxelNeXt layout
# (six residual stages at the paper's doubled widths, stages 4-6 merged into a sparse BEV at stride 8) with n = 2
# MSDFF fusion blocks and the semantic-guided head, then VoxelNeXt's sparse head (MSSFVoxelNeXtHead): no
# pts_backbone / pts_neck, the head reads the encoder's sparse BEV.
# Where VoxelNeXt's own settings are not the paper's, the authors' MSSF-V config (EricLiuhhh/MSSF,
# configs/voxelnext/vx_mm_r50_ablation_n2m4.py) is followed: loss weights 1 and 1 (OpenPCDet's VoxelNeXt config:
# loc_weight 0.25), test score threshold 0.02, NMS IoU 0.2, 83 boxes, centres inside the range (OpenPCDet's: 0.1,
# 0.2, 100 boxes, the range plus 10 m). docs/frameworks.md lists these switches.
grid_range = [0, -25.6, -3, 51.2, 25.6, 2]  # the grid (the datasets' point_cloud_range)
voxel_size = [0.05, 0.05, 0.125]
sparse_shape = [41, 1024, 1024]  # (z + 1, y, x) cells, as SparseEncoder configs give it
num_classes = 3
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
                           voxel_layer=dict(max_num_points=10, point_cloud_range=grid_range,
                                            voxel_size=voxel_size, max_voxels=(16000, 40000)),
                           mean=[123.675, 116.28, 103.53],
                           std=[58.395, 57.12, 57.375], bgr_to_rgb=True, pad_size_divisor=32),
    img_backbone=dict(type="mmdet.ResNet", depth=50, num_stages=4, out_indices=(0, 1, 2, 3), frozen_stages=-1,
                      norm_cfg=dict(type="BN", requires_grad=True), norm_eval=False, style="pytorch"),
    img_neck=dict(type="mmdet.FPN", in_channels=[256, 512, 1024, 2048], out_channels=256, num_outs=4),
    pts_voxel_encoder=dict(type="HardSimpleVFE", num_features=7),
    pts_middle_encoder=dict(
        type="MSSFSparseEncoder", in_channels=7, sparse_shape=sparse_shape, point_cloud_range=grid_range,
        voxel_size=voxel_size, layout="VoxelResBackBone8xVoxelNeXt",
        channels=[32, 32, 64, 128, 256, 256, 256],  # stem, stages 1-6: VoxelNeXt's 16 ... 128 doubled (paper)
        out_channels=256, num_fusion_blocks=2, fusion="msdff", fusion_position="before_residual",
        image_channels=[256, 256, 256, 256], msdff_heads=8, msdff_points=4, msdff_value_dim=None,
        seg_hidden=[256, 256], image_aug="meta"),
    pts_bbox_head=dict(
        type="MSSFVoxelNeXtHead", in_channels=256, num_classes=num_classes, point_cloud_range=grid_range,
        voxel_size=voxel_size, out_size_factor=8, head_channels=256, cls_weight=1.0, loc_weight=1.0),
    train_cfg=dict(pts=dict(gaussian_overlap=0.1, min_radius=2, max_objs=500, code_weights=[1.0] * 8)),
    test_cfg=dict(pts=dict(max_num=500, score_threshold=0.02, nms_thr=0.2, post_max_size=83,
                           post_center_limit_range=grid_range)),
)
