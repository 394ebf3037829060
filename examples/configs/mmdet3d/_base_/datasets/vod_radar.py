# View-of-Delft, single-scan radar only (VoD's `radar` folder; the radar-only twins). The same 7 columns as the
# 5-scan files (x, y, z, RCS, v_r, v_r_comp, time; time 0), so only the folder differs from vod_radar5.py. Info files:
# python -m mssf_examples.mmdet3d infos --root data/view_of_delft --sensor radar
_base_ = ["./vod_radar5.py"]
data_root = "data/view_of_delft/radar/"
train_dataloader = dict(dataset=dict(data_root=data_root))
val_dataloader = dict(dataset=dict(data_root=data_root))
test_dataloader = val_dataloader
val_evaluator = dict(ann_file=data_root + "vod_infos_val.pkl")
test_evaluator = val_evaluator
