# TJ4DRadSet, single-scan radar + the camera, on the paper's range of the voxel models (0..70.4 x -40..40 x -4..2 m;
# tj4d_radar_camera.py has the pillar range). As tj4d_radar_camera.py otherwise.
_base_ = ["./tj4d_radar_camera.py"]
point_cloud_range = [0, -40, -4, 70.4, 40, 2]
train_pipeline = [dict(t, point_cloud_range=point_cloud_range) if "point_cloud_range" in t else t
                  for t in _base_.train_pipeline]
test_pipeline = [dict(t, point_cloud_range=point_cloud_range) if "point_cloud_range" in t else t
                 for t in _base_.test_pipeline]
train_dataloader = dict(dataset=dict(pipeline=train_pipeline, pcd_limit_range=point_cloud_range))
val_dataloader = dict(dataset=dict(pipeline=test_pipeline, pcd_limit_range=point_cloud_range))
test_dataloader = val_dataloader
