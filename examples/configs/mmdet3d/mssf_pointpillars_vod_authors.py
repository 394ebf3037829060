# MSSF-PointPillars on View-of-Delft configured as the MSSF authors' released model (EricLiuhhh/MSSF,
# pointpillars_hv_secfpn_8xb6-160e_vod-3d-3class_mm_bb_bevfeat_lr0001): their module structure
# (MSSFPillarEncoder layout="authors": their PointPillarsScatterFuse and SECONDFuse fusion stages, with their forward
# switches, docs/differences.md) and their five FPN levels, so that their checkpoint loads strictly
# (docs/frameworks.md, "The authors' MSSF-PP checkpoint"):
#     python -m mssf_examples.mmdet3d convert-authors THEIR.pth --config THIS_FILE --out CONVERTED.pth
#     python -m mssf_examples.mmdet3d test THIS_FILE CONVERTED.pth
# Their anchors are these (same sizes and bottoms); the converter reorders the head's outputs from their class
# order (Pedestrian, Cyclist, Car) to this config's. Data, schedule and evaluation are mssf_pointpillars_vod.py's.
_base_ = ["./mssf_pointpillars_vod.py"]
model = dict(
    img_neck=dict(num_outs=5),
    pts_middle_encoder=dict(layout="authors", image_channels=[256, 256, 256, 256, 256]),
)
