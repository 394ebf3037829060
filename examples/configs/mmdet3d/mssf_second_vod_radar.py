# An mmdetection3d (1.x) config for MSSF-SECOND on View-of-Delft radar: a radar-only SECOND config
# whose middle encoder is the MSSF one. Read by tests/integrations/test_mmdet3d_plugin.py with
# mmengine.Config.fromfile, which runs custom_imports (registering MSSFSparseEncoder) before building.
custom_imports = dict(imports=["mssf_blocks.integrations.mmdet3d_plugin"], allow_failed_imports=False)

point_cloud_range = [0, -25.6, -3, 51.2, 25.6, 2]
voxel_size = [0.05, 0.05, 0.125]
sparse_shape = [41, 1024, 1024]  # (z + 1, y, x) cells, as SparseEncoder configs give it

model = dict(
    type="VoxelNet",  # extract_feat must pass the camera inputs on (docs/frameworks.md, one call)
    data_preprocessor=dict(
        type="Det3DDataPreprocessor",
        voxel=True,
        voxel_layer=dict(max_num_points=10, point_cloud_range=point_cloud_range, voxel_size=voxel_size,
                         max_voxels=(16000, 40000)),
        mean=[123.675, 116.28, 103.53], std=[58.395, 57.12, 57.375], bgr_to_rgb=True, pad_size_divisor=32,
    ),
    voxel_encoder=dict(type="HardSimpleVFE", num_features=7),
    middle_encoder=dict(
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
        seg_hidden=[256, 256],
        image_aug="meta",
    ),
)
