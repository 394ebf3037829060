# MSSF-VoxelNeXt on TJ4DRadSet: the VoD model (mssf_voxelnext_vod.py) on the paper's TJ4D voxel range
# 0..70.4 x -40..40 x -4..2 m (voxels 0.05 x 0.05 x 0.125 m: 1408 x 1600 x 48), the 5 input features x, y, z, V_r,
# Power and four classes. The authors' TJ4D config (vx_mm_r50_ablation_n2m4_tj4d.py) uses 0.15 m in z (40 layers):
# for theirs set voxel_size = [0.05, 0.05, 0.15] and sparse_shape = [41, 1600, 1408] below (docs/training.md).
_base_ = ["./mssf_voxelnext_vod.py"]
grid_range = [0, -40, -4, 70.4, 40, 2]
voxel_size = [0.05, 0.05, 0.125]
sparse_shape = [49, 1600, 1408]
model = dict(
    data_preprocessor=dict(voxel_layer=dict(point_cloud_range=grid_range, voxel_size=voxel_size)),
    pts_voxel_encoder=dict(num_features=5),
    pts_middle_encoder=dict(in_channels=5, sparse_shape=sparse_shape, point_cloud_range=grid_range,
                            voxel_size=voxel_size),
    pts_bbox_head=dict(num_classes=4, point_cloud_range=grid_range, voxel_size=voxel_size),
    test_cfg=dict(pts=dict(post_center_limit_range=grid_range)),
)
