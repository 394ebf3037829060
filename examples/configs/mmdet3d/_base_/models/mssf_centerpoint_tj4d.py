# MSSF-CenterPoint on TJ4DRadSet: the VoD model (mssf_centerpoint_vod.py) on the paper's TJ4D voxel range
# 0..70.4 x -40..40 x -4..2 m (voxels 0.05 x 0.05 x 0.125 m: 1408 x 1600 x 48, sparse shape z + 1 = 49), the 5 input
# features x, y, z, V_r, Power and four classes; the head as the authors' TJ4D CenterPoint config
# (centerpoint_voxel005_second_secfpn_tj4d_multimodal: one task for the four classes, 256 shared channels). Their
# voxels are 0.15 m high: voxel_size [0.05, 0.05, 0.15], sparse_shape [41, 1600, 1408], grid_size [1408, 1600, 40]
# give theirs (conv_out still has 2 z cells: 128 x 2 = 256 BEV channels either way).
_base_ = ["./mssf_centerpoint_vod.py"]
grid_range = [0, -40, -4, 70.4, 40, 2]
voxel_size = [0.05, 0.05, 0.125]
model = dict(
    data_preprocessor=dict(voxel_layer=dict(point_cloud_range=grid_range, voxel_size=voxel_size)),
    pts_voxel_encoder=dict(num_features=5),
    pts_middle_encoder=dict(in_channels=5, sparse_shape=[49, 1600, 1408], point_cloud_range=grid_range,
                            voxel_size=voxel_size),
    pts_bbox_head=dict(
        tasks=[dict(num_class=4, class_names=["Car", "Pedestrian", "Cyclist", "Truck"])],
        share_conv_channel=256,
        bbox_coder=dict(pc_range=grid_range[:2], post_center_range=grid_range, voxel_size=voxel_size[:2])),
    train_cfg=dict(pts=dict(grid_size=[1408, 1600, 48], voxel_size=voxel_size, point_cloud_range=grid_range)),
    test_cfg=dict(pts=dict(post_center_limit_range=grid_range, voxel_size=voxel_size[:2])),
)
