# TJ4DRadSet, single-scan radar only, on the paper's voxel range 0..70.4 x -40..40 x -4..2 m (the voxel models,
# SECOND and CenterPoint; tj4d_radar.py holds the pillar range of PointPillars). As tj4d_radar.py with the range
# filters and pcd_limit_range on that range.
_base_ = ["./tj4d_radar.py"]
point_cloud_range = [0, -40, -4, 70.4, 40, 2]
_ranged = ("PointsRangeFilter", "ObjectRangeFilter")
train_pipeline = [dict(s, point_cloud_range=point_cloud_range) if s["type"] in _ranged else s
                  for s in _base_.train_pipeline]
test_pipeline = [dict(s, point_cloud_range=point_cloud_range) if s["type"] in _ranged else s
                 for s in _base_.test_pipeline]
train_dataloader = dict(dataset=dict(pipeline=train_pipeline, pcd_limit_range=point_cloud_range))
val_dataloader = dict(dataset=dict(pipeline=test_pipeline, pcd_limit_range=point_cloud_range))
test_dataloader = val_dataloader
