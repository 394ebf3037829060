"""Compare ``evaluate(protocol="tj4d")`` with the MSSF authors' own TJ4DRadSet evaluation.

Usage (a checkout of https://github.com/EricLiuhhh/MSSF; numba and vod-tudelft installed)::

    python tests/examples/helpers/tj4d_authors_oracle.py --repo /path/to/MSSF --frames 200 --seeds 1 2 3

Their ``mmdet3d/evaluation/functional/kitti_utils/eval_tj4d.py`` and ``rotate_iou.py`` run unmodified,
loaded by path; the rotated IoU is a numba CUDA kernel, so it runs under numba's CUDA simulator
(``NUMBA_ENABLE_CUDASIM=1``, set before numba is imported) on a machine without GPU. The GT difficulty
is their converter's ``add_difficulty_to_annos`` (``tools/dataset_converters/tj4d_data_utils.py``),
taken from the file alone (its module imports mmengine). Label and prediction files are generated as in
``test_evaluation_vod_kit.py`` with trucks added, ranges to 90 m, occlusion 0-3 and truncations above
0.5, and read with the VoD kit's reader (the same KITTI parser the authors' pipeline uses). Prints the
largest difference over every per-class AP (both IoU sets, three range bins, 3D and BEV) and the
overall mAPs; exits 1 when it is 0.01 or more.
"""

from __future__ import annotations

import os

os.environ["NUMBA_ENABLE_CUDASIM"] = "1"  # before numba: the authors' IoU is a CUDA kernel

import argparse  # noqa: E402
import ast  # noqa: E402
import contextlib  # noqa: E402
import importlib  # noqa: E402
import importlib.util  # noqa: E402
import io  # noqa: E402
import math  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import types  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

HERE = Path(__file__).resolve().parent
sys.path[:0] = [str(HERE.parents[2] / "src"), str(HERE.parents[2] / "examples")]

from mssf_examples.evaluation.metrics import evaluate  # noqa: E402
from mssf_examples.data.kitti_export import kitti_lines, write_kitti_file  # noqa: E402
from mssf_examples.data.kitti_io import parse_labels  # noqa: E402

CLASSES = ["Car", "Pedestrian", "Cyclist", "Truck"]
LEVELS = (("easy", "range_0_50"), ("moderate", "range_0_70"), ("hard", "range_all"))


def load(repo: Path):
    """The VoD-kit oracle helpers, the authors' eval module and their difficulty function."""
    spec = importlib.util.spec_from_file_location("vod_kit_oracle", HERE.parent / "evaluation" / "test_evaluation_vod_kit.py")
    oracle = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(oracle)
    folder = repo / "mmdet3d" / "evaluation" / "functional" / "kitti_utils"
    package = types.ModuleType("_mssf_authors_kitti_utils")
    package.__path__ = [str(folder)]
    sys.modules[package.__name__] = package
    authors = importlib.import_module(f"{package.__name__}.eval_tj4d")
    source = (repo / "tools" / "dataset_converters" / "tj4d_data_utils.py").read_text()
    fn = next(n for n in ast.parse(source).body if isinstance(n, ast.FunctionDef) and n.name == "add_difficulty_to_annos")
    namespace = {"np": np}
    exec(compile(ast.Module([fn], []), "tj4d_data_utils.py", "exec"), namespace)
    return oracle, authors, namespace["add_difficulty_to_annos"]


def generate(oracle, seed: int, num_frames: int):
    rng = np.random.default_rng(seed)
    calib = oracle.calibration()
    sizes = dict(oracle.SIZES, Truck=(8.0, 2.5, 3.0))
    gt_frames, det_frames = [], []
    for _ in range(num_frames):
        if rng.random() < 0.06:
            gt_frames.append([])
            det_frames.append([])
            continue
        boxes, kinds = [], []
        for _ in range(int(rng.integers(1, 8))):
            kind = str(rng.choice(CLASSES + ["Van"], p=[0.35, 0.25, 0.2, 0.15, 0.05]))
            x = rng.choice([rng.uniform(3, 45), rng.uniform(45, 55), rng.uniform(55, 90)], p=[0.5, 0.2, 0.3])
            boxes.append(_box(rng, sizes[kind], x, rng.uniform(-15, 15)))
            kinds.append(kind)
            if rng.random() < 0.12:  # an overlapping neighbour
                b = boxes[-1].copy()
                b[:2] += rng.normal(0, 0.5, 2)
                boxes.append(b)
                kinds.append(kind)
        lines = kitti_lines(torch.tensor(np.array(boxes)), torch.zeros(len(boxes), dtype=torch.long), CLASSES, calib,
                            oracle.IMAGE_SIZE, truncated=0.0, occluded=0, names=kinds)
        occlusion = rng.integers(0, 4, len(lines))
        truncation = rng.choice([0.0, 0.2, 0.6], len(lines), p=[0.8, 0.1, 0.1])
        lines = [" ".join([f[0], f"{t:.2f}", str(int(o))] + f[3:])
                 for f, o, t in zip((ln.split() for ln in lines), occlusion, truncation)]
        gt_frames.append(lines)
        out, names, scores = [], [], []
        for b, kind in zip(boxes, kinds):
            if rng.random() < 0.15:
                continue
            for dup in range(1 + int(rng.random() < 0.15)):
                d = b.copy()
                d[:3] += rng.normal(0, [0.3, 0.3, 0.12]) * (1 + 0.6 * dup)
                d[3:6] *= rng.uniform(0.85, 1.15, 3)
                d[6] += rng.normal(0, 0.15)
                out.append(d)
                names.append(str(rng.choice(CLASSES)) if rng.random() < 0.05 else ("Car" if kind == "Van" else kind))
                scores.append(round(float(rng.uniform(0.2, 1.0) - 0.2 * dup), 2))
        for _ in range(int(rng.integers(0, 4))):  # false positives, near and far
            kind = str(rng.choice(CLASSES))
            out.append(_box(rng, sizes[kind], rng.uniform(3, 85), rng.uniform(-15, 15)))
            names.append(kind)
            scores.append(round(float(rng.uniform(0.05, 0.7)), 2))
        det_frames.append(kitti_lines(torch.tensor(np.array(out)), torch.zeros(len(out), dtype=torch.long), CLASSES,
                                      calib, oracle.IMAGE_SIZE, scores=torch.tensor(scores, dtype=torch.float64),
                                      names=names) if out else [])
    return gt_frames, det_frames


def _box(rng, size, x, y):
    l, w, h = (s * rng.uniform(0.9, 1.1) for s in size)
    return np.array([x, y, -1.4 + h / 2 + rng.normal(0, 0.1), l, w, h, rng.uniform(-math.pi, math.pi)])


def compare(oracle, authors, add_difficulty, gt_frames, det_frames) -> float:
    _, common = oracle.load_kit()
    folder = Path(tempfile.mkdtemp())
    ids = [f"{i:05d}" for i in range(len(gt_frames))]
    for fid, g, d in zip(ids, gt_frames, det_frames):
        write_kitti_file(folder / "label" / f"{fid}.txt", g)
        write_kitti_file(folder / "det" / f"{fid}.txt", d)
    gt_annos = common.get_label_annotations(folder / "label", ids)
    dt_annos = common.get_label_annotations(folder / "det", ids)
    for anno in gt_annos:
        add_difficulty({"annos": anno})
    with contextlib.redirect_stdout(io.StringIO()):  # their class order (configs/_base_/datasets/tj4d-3d-4class.py)
        _, theirs = authors.kitti_eval(gt_annos, dt_annos, ["Pedestrian", "Cyclist", "Car", "Truck"],
                                       eval_types=["bbox", "bev", "3d"])
    gts = [parse_labels("\n".join(g)) for g in gt_frames]
    dets = [parse_labels("\n".join(d)) for d in det_frames]
    dets = [d if d.score is not None else oracle._with_empty_score(d) for d in dets]
    worst = 0.0
    for postfix, value in (("strict", 0.5), ("loose", 0.25)):
        ours = evaluate(dets, gts, CLASSES, {c: value for c in CLASSES}, protocol="tj4d")
        for cname in CLASSES:
            for level, region in LEVELS:
                for metric in ("3D", "BEV"):
                    a, b = ours[region][cname][f"AP{metric}_R40"], theirs[f"KITTI/{cname}_{metric}_{level}_{postfix}"]
                    worst = max(worst, abs((0.0 if math.isnan(a) else a) - b))
    ours = evaluate(dets, gts, CLASSES, protocol="tj4d")
    for level, region in LEVELS:
        for metric in ("3D", "BEV"):
            worst = max(worst, abs(ours[region]["mAP"][f"AP{metric}_R40"] - theirs[f"KITTI/Overall_{metric}_{level}"]))
    return worst


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repo", type=Path, required=True, help="checkout of EricLiuhhh/MSSF")
    ap.add_argument("--frames", type=int, default=200)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    args = ap.parse_args(argv)
    oracle, authors, add_difficulty = load(args.repo)
    worst = 0.0
    for seed in args.seeds:
        diff = compare(oracle, authors, add_difficulty, *generate(oracle, seed, args.frames))
        print(f"seed {seed}: {args.frames} frames, max |ours - authors| = {diff:.3g}", flush=True)
        worst = max(worst, diff)
    return 0 if worst < 0.01 else 1


if __name__ == "__main__":
    sys.exit(main())
