"""OpenPCDet's half of ``framework_gap.py``: the shipped MSSF-VoxelNeXt config and its radar-only twin, sized as
the demo's voxel model, trained and evaluated by OpenPCDet's own ``tools/train.py`` (through
``python -m mssf_examples.openpcdet --cpu``, the documented way to run it without CUDA).

OpenPCDet is used from its source archive (``../shared/thirdparty/openpcdet-8caccce.tar.gz``, unpacked once
into ``--out``), or from a clone given with ``--openpcdet``. What changes against the shipped YAMLs is what makes
them the demo's model on the demo's data, as in ``_gap_mmdet3d.py``: the range, the voxel size and the widths
of ``demo_preset``, one fusion block, the demo's image branch (its checkpoint, images in [0, 1], resized to the
demo's size by ``IMAGE_BRANCH.IMAGE_SIZE``), no augmentation, and the demo's budget (``train.py`` counts epochs:
``steps x batch / train scenes`` of them).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tarfile
import time
from pathlib import Path
from typing import Dict, List

import yaml

ROOT = Path(__file__).resolve().parents[1]
ARCHIVE = ROOT.parent / "shared" / "thirdparty" / "openpcdet-8caccce.tar.gz"
CONFIGS = ROOT / "examples" / "configs" / "openpcdet"
MODELS = {"MSSF-V": "mssf_voxelnext", "VoxelNeXt (radar only)": "voxelnext_radar"}
CLASSES = ("Car", "Pedestrian", "Cyclist")


def openpcdet_root(out: Path, given) -> Path:
    """The clone given, or the archive unpacked under ``out`` (once)."""
    if given is not None:
        root = Path(given).resolve()
        if not (root / "tools" / "train.py").is_file():
            raise SystemExit(f"--openpcdet: expected an OpenPCDet clone (tools/train.py), got {root}")
        return root
    root = out / "OpenPCDet-8caccce"
    if not (root / "tools" / "train.py").is_file():
        if not ARCHIVE.is_file():
            raise SystemExit(f"OpenPCDet: {ARCHIVE} not found; give a clone with --openpcdet")
        with tarfile.open(ARCHIVE) as tar:
            tar.extractall(out, filter="data")
    return root


def _write_yaml(path: Path, data: dict, header: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"# {header}\n" + yaml.safe_dump(data, sort_keys=False, default_flow_style=None))


def write_configs(tools: Path, data_path: Path, preset, budget: Dict, ckpt: Path) -> Dict[str, str]:
    """The demo-sized dataset YAML and the two model YAMLs under ``tools/cfgs``; returns {model: cfg_file}."""
    ds = yaml.safe_load((CONFIGS / "dataset_configs" / "vod_radar5_dataset.yaml").read_text())
    ds["DATA_PATH"] = str(data_path)
    ds["POINT_CLOUD_RANGE"] = [float(v) for v in preset.point_cloud_range]
    ds["DATA_AUGMENTOR"]["AUG_CONFIG_LIST"] = []  # the demo trains without augmentation
    for step in ds["DATA_PROCESSOR"]:
        if step["NAME"] == "transform_points_to_voxels":
            step["VOXEL_SIZE"] = [float(v) for v in preset.voxel_size]
    _write_yaml(tools / "cfgs" / "dataset_configs" / "gap_vod_dataset.yaml", ds,
                "framework_gap.py: vod_radar5_dataset.yaml on the demo's scenes (range, voxels, no augmentation)")
    files = {}
    for model, name in MODELS.items():
        cfg = yaml.safe_load((CONFIGS / "vod_models" / f"{name}.yaml").read_text())
        cfg["DATA_CONFIG"]["_BASE_CONFIG_"] = "cfgs/dataset_configs/gap_vod_dataset.yaml"
        m = cfg["MODEL"]
        bb = m["BACKBONE_3D"]
        bb.update(CHANNELS=list(preset.voxelnext_channels), OUT_CHANNELS=preset.voxelnext_out, AUG_ORDER=[],
                  IMAGE_CHANNELS=[preset.fpn_channels] * preset.num_image_levels, MSDFF_HEADS=preset.msdff_heads,
                  MSDFF_POINTS=preset.msdff_points, MSDFF_VALUE_PROJECTION=preset.msdff_value_projection,
                  SEG_HIDDEN=list(preset.seg_hidden))
        if "IMAGE_BRANCH" in m:
            bb["NUM_FUSION_BLOCKS"] = budget["fusion_blocks"]
            m["IMAGE_BRANCH"].update(DEPTH=preset.image_depth, BASE_CHANNELS=preset.image_base_channels,
                                     FPN_CHANNELS=preset.fpn_channels, NUM_OUTS=preset.num_image_levels,
                                     CHECKPOINT=str(ckpt), MEAN=[0.0, 0.0, 0.0], STD=[1.0, 1.0, 1.0],
                                     IMAGE_SIZE=list(budget["image_size"]))
        m["DENSE_HEAD"].update(INPUT_FEATURES=preset.voxelnext_out, SHARED_CONV_CHANNEL=preset.head_channels)
        cfg["OPTIMIZATION"].update(BATCH_SIZE_PER_GPU=budget["batch_size"], LR=budget["lr"])
        _write_yaml(tools / "cfgs" / "gap_models" / f"{name}.yaml", cfg,
                    f"framework_gap.py: vod_models/{name}.yaml sized as the demo's voxel model")
        files[model] = f"cfgs/gap_models/{name}.yaml"
    return files


def _env() -> dict:
    paths = [str(ROOT / "src"), str(ROOT / "examples")] + [p for p in os.environ.get("PYTHONPATH", "").split(":") if p]
    return dict(os.environ, PYTHONPATH=":".join(paths), OMP_NUM_THREADS="1")


def _run(cmd: List[str], cwd: Path, log: Path) -> None:
    with open(log, "a") as f:
        f.write("$ " + " ".join(cmd) + "\n")
        f.flush()
        rc = subprocess.run(cmd, cwd=cwd, env=_env(), stdout=f, stderr=subprocess.STDOUT).returncode
    if rc != 0:
        tail = log.read_text()[-3000:]
        raise SystemExit(f"OpenPCDet: {' '.join(cmd[3:6])} failed (rc {rc}); the end of {log}:\n{tail}")


_ROW = re.compile(r"^\s+(\w+)\s+AP3D R40\s+([\d.]+)\s+APBEV R40\s+([\d.]+)\s+AP3D R11\s+([\d.]+)")


def parse_vod_log(text: str) -> Dict[str, float]:
    """The last ``VoD <region>:`` tables of an OpenPCDet log (``VoDDataset.evaluation``), as the mmdet3d metric
    names them (``VoD/<region>/<Class>/AP3D_R11``; ``mAP`` the mean over the classes)."""
    out: Dict[str, float] = {}
    region = None
    for line in text.splitlines():
        head = re.match(r".*VoD (entire_area|driving_corridor):\s*$", line)
        if head:
            region = head.group(1)
            continue
        row = _ROW.match(line) if region else None
        if row and row.group(1) in CLASSES:
            r40, bev40, r11 = (float(row.group(i)) for i in (2, 3, 4))
            out.update({f"VoD/{region}/{row.group(1)}/AP3D_R40": r40, f"VoD/{region}/{row.group(1)}/APBEV_R40": bev40,
                        f"VoD/{region}/{row.group(1)}/AP3D_R11": r11})
    for region in ("entire_area", "driving_corridor"):
        for key in ("AP3D_R11", "AP3D_R40", "APBEV_R40"):
            vals = [out.get(f"VoD/{region}/{c}/{key}") for c in CLASSES]
            if all(v is not None for v in vals):
                out[f"VoD/{region}/mAP/{key}"] = sum(vals) / len(vals)
    return out


def run_openpcdet(args, scene_cfg, preset, tree: Path, ckpt: Path) -> Dict:
    out_dir = args.out / "openpcdet"
    out_dir.mkdir(parents=True, exist_ok=True)
    root = openpcdet_root(out_dir, getattr(args, "openpcdet", None))
    tools = root / "tools"
    data = out_dir / "data" / "radar_5frames"  # its own info files beside links to the tree's frames
    data.mkdir(parents=True, exist_ok=True)
    for sub in ("training", "ImageSets"):
        link = data / sub
        if not link.exists():
            link.symlink_to((tree / "radar_5frames" / sub).resolve(), target_is_directory=True)
    epochs = max(1, round(args.steps * args.batch_size / args.train_scenes))
    budget = dict(batch_size=args.batch_size, lr=args.lr, fusion_blocks=args.fusion_blocks,
                  image_size=tuple(scene_cfg.image_size))
    files = write_configs(tools, data, preset, budget, ckpt)
    log = out_dir / "openpcdet.log"
    py = [sys.executable, "-m", "mssf_examples.openpcdet", "--cpu"]
    _run(py + ["create_vod_infos", "cfgs/dataset_configs/gap_vod_dataset.yaml", "--workers", "1"], tools, log)
    results = {}
    for model, cfg_file in files.items():
        t0 = time.perf_counter()
        tag = f"gap_seed{args.seed}"
        _run(py + ["train.py", "--cfg_file", cfg_file, "--batch_size", str(args.batch_size), "--epochs", str(epochs),
                   "--workers", str(args.workers), "--extra_tag", tag, "--max_ckpt_save_num", "1", "--wo_gpu_stat",
                   "--fix_random_seed", "--max_waiting_mins", "0"], tools, log)
        run_dir = root / "output" / "gap_models" / Path(cfg_file).stem / tag
        logs = sorted(run_dir.glob("train_*.log"), key=lambda p: p.stat().st_mtime)  # this run's: the newest
        text = logs[-1].read_text() if logs else ""
        results[model] = {"config": f"examples/configs/openpcdet/vod_models/{Path(cfg_file).name}",
                          "metrics": parse_vod_log(text), "epochs": epochs, "seconds": time.perf_counter() - t0}
    return results
