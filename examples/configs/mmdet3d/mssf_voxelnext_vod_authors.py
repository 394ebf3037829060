# MSSF-V on View-of-Delft built as the MSSF authors built it (EricLiuhhh/MSSF, vx_mm_r50_ablation_n2m4.py), for their
# released checkpoint: their encoder (layout="authors": the VoxelNeXt stages with their fusion modules' forward, a
# regular conv_out, a biased shared_conv; the older spelling authors_layout=True builds the same module), five FPN
# levels (num_outs=5), their head and test settings (as mssf_voxelnext_vod.py).
# Convert their checkpoint: mssf_examples.mmdet3d.authors_mssf_v.convert_authors_mssf_v (docs/frameworks.md).
_base_ = ["./mssf_voxelnext_vod.py"]
model = dict(
    img_neck=dict(num_outs=5),
    pts_middle_encoder=dict(layout="authors", image_channels=[256, 256, 256, 256, 256]),
)
