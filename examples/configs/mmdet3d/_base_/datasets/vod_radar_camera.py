# View-of-Delft, single-scan radar + the camera (the MSSF models): vod_radar5_camera.py on VoD's `radar` folder
# (see vod_radar.py).
_base_ = ["./vod_radar5_camera.py"]
data_root = "data/view_of_delft/radar/"
train_dataloader = dict(dataset=dict(data_root=data_root))
val_dataloader = dict(dataset=dict(data_root=data_root))
test_dataloader = val_dataloader
val_evaluator = dict(ann_file=data_root + "vod_infos_val.pkl")
test_evaluator = val_evaluator
