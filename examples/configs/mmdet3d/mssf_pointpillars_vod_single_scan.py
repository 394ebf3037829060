# MSSF-PointPillars on View-of-Delft's single radar scan (VoD's `radar` folder) + camera: mssf_pointpillars_vod.py
# on the single-scan data (_base_/datasets/vod_radar_camera.py); for a single-scan radar-only twin, pair
# pointpillars_vod_radar.py's model with _base_/datasets/vod_radar.py. The paper's VoD results use 5 scans.
# Info files: python -m mssf_examples.mmdet3d infos --root data/view_of_delft --sensor radar
_base_ = [
    "./_base_/models/mssf_pointpillars_vod.py",
    "./_base_/datasets/vod_radar_camera.py",
    "./_base_/schedules/vod_onecycle.py",
    "./_base_/default_runtime.py",
]
