# MSSF-CenterPoint on View-of-Delft: MSSF-SECOND (mssf_second_vod.py: voxels 0.05 x 0.05 x 0.125 m, the image branch,
# n = 2 MSDFF fusion blocks, the semantic head, SECOND + SECONDFPN) with the sparse encoder in CenterPoint's residual
# layout (VoxelResBackBone8x: 16 / 32 / 64 / 128 channels, conv_out 128, so 128 x 2 z cells = 256 BEV channels) and
# mmdet3d's centre head in place of the anchor head. The head follows the MSSF authors' VoD CenterPoint config
# (centerpoint_voxel005_second_secfpn_vod_multimodal: one task per class, 64 shared channels, Gaussian overlap 0.1,
# rotated NMS at 0.2): the paper states none of it. CenterHeadWithoutVelocity is mmdet3d's CenterHead on 7-value
# boxes (mmdet3d 1.4's expects nuScenes' velocity; mssf_examples.mmdet3d.center_head says how it differs).
_base_ = ["./mssf_second_vod.py"]
grid_range = [0, -25.6, -3, 51.2, 25.6, 2]
voxel_size = [0.05, 0.05, 0.125]
model = dict(
    pts_middle_encoder=dict(layout="VoxelResBackBone8x"),
    # 1 x 1 convolution for the stride-1 branch, as mmdet3d's and the authors' CenterPoint configs
    pts_neck=dict(use_conv_for_no_stride=True),
    pts_bbox_head=dict(
        _delete_=True,
        type="CenterHeadWithoutVelocity",
        in_channels=512,
        # the dataset's label order (a task's labels are consecutive: mmdet3d offsets them task by task)
        tasks=[dict(num_class=1, class_names=["Car"]), dict(num_class=1, class_names=["Pedestrian"]),
               dict(num_class=1, class_names=["Cyclist"])],
        common_heads=dict(reg=(2, 2), height=(1, 2), dim=(3, 2), rot=(2, 2)),
        share_conv_channel=64,
        bbox_coder=dict(type="CenterPointBBoxCoder", pc_range=grid_range[:2], post_center_range=grid_range,
                        max_num=500, score_threshold=0.1, out_size_factor=8, voxel_size=voxel_size[:2], code_size=7),
        separate_head=dict(type="SeparateHead", init_bias=-2.19, final_kernel=3),
        loss_cls=dict(type="mmdet.GaussianFocalLoss", reduction="mean"),
        loss_bbox=dict(type="mmdet.L1Loss", reduction="mean", loss_weight=0.25),
        norm_bbox=True),
    train_cfg=dict(_delete_=True, pts=dict(
        grid_size=[1024, 1024, 40], voxel_size=voxel_size, point_cloud_range=grid_range, out_size_factor=8,
        dense_reg=1, gaussian_overlap=0.1, max_objs=500, min_radius=2, code_weights=[1.0] * 8)),
    test_cfg=dict(_delete_=True, pts=dict(
        post_center_limit_range=grid_range, max_per_img=500, max_pool_nms=False, min_radius=[4, 12, 10, 1, 0.85, 0.175],
        score_threshold=0.1, out_size_factor=8, voxel_size=voxel_size[:2], nms_type="rotate", pre_max_size=1000,
        post_max_size=83, nms_thr=0.2)),
)
