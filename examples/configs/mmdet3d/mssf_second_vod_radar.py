# An mmdetection3d (1.x) config for MSSF-SECOND on View-of-Delft radar: a radar-only SECOND config
# whose middle encoder is the MSSF one. Read by tests/integrations/test_mmdet3d_plugin.py with
# mmengine.Config.fromfile, which runs custom_imports (registering MSSFSparseEncoder) before building.
custom_imports = dict(imports=["mssf_blocks.integrations.mmdet3d_plugin"], allow_failed_imports=False)

point_cloud_range = [0, -25.6, -3, 51.2, 25.6, 2]
voxel_size = [0.05, 0.05, 0.125]
sparse_shape = [41, 1024, 1024]  # (z + 1, y, x) cells, as SparseEncoder configs give it

model = dict(
    # an MVX detector has points, image features and metainfo where it runs the middle encoder;
    # extract_pts_feat's pts_middle_encoder call passes them on (docs/frameworks.md, one call)
    type="MVXFasterRCNN",
    img_backbone=dict(type="mmdet.ResNet", depth=50, num_stages=4, out_indices=(0, 1, 2, 3), frozen_stages=1,
                      norm_cfg=dict(type="BN", requires_grad=False), norm_eval=True, style="caffe"),
    img_neck=dict(type="mmdet.FPN", in_channels=[256, 512, 1024, 2048], out_channels=256, num_outs=4),
    data_preprocessor=dict(
        type="Det3DDataPreprocessor",
        voxel=True,
        voxel_layer=dict(max_num_points=10, point_cloud_range=point_cloud_range, voxel_size=voxel_size,
                         max_voxels=(16000, 40000)),
        mean=[123.675, 116.28, 103.53], std=[58.395, 57.12, 57.375], bgr_to_rgb=True, pad_size_divisor=32,
    ),
    pts_voxel_encoder=dict(type="HardSimpleVFE", num_features=7),
    pts_middle_encoder=dict(
        type="MSSFSparseEncoder",
        in_channels=7,
        sparse_shape=sparse_shape,
        point_cloud_range=point_cloud_range,
        voxel_size=voxel_size,
        layout="VoxelBackBone8x",
        num_fusion_blocks=2,
        fusion="msdff",
        fusion_position="before_residual",
        image_channels=[256, 256, 256, 256],  # the image neck's levels
        msdff_heads=8,
        msdff_points=4,
        msdff_value_dim=None,  # MSDFF value width: None = the image channels (paper); "voxel_channels"
        seg_hidden=[256, 256],
        image_aug="meta",
    ),
)
