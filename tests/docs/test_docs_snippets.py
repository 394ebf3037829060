"""Every ```python block of README.md and docs/*.md runs against the current code (or is a listed fragment).

Each block is classified here, keyed by ``(file, first code line)``:

* ``@snippet(...)`` blocks run, each as its own test case: the case builds the names the block assumes
  (a small preamble), executes the block's text exactly as written (``exec`` with the doc file as the
  code's filename, so a traceback points into the docs), then asserts what the block promises. A line
  that shows a tensor in a comment (``expr   # tensor([[ 5.0000, ...]])``) is re-evaluated and compared
  with the shown value to its printed precision.
* ``FRAGMENTS`` lists the blocks that cannot sensibly run, with the reason.

A block that is in neither (a new block, or an old one whose first line changed) fails
``test_every_python_block_is_classified`` until someone classifies it; a classification whose block is
gone fails too. Blocks that need spconv skip without it; the real-data block skips without
``../shared/realdata``.

Reading and running the blocks: ``doc_blocks.py``; the inputs the blocks assume: ``doc_scenes.py``; the
signature listings and the mentioned scripts against the code: ``test_docs_references.py``.
"""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path
from typing import Callable, Dict, Tuple

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from doc_blocks import ALL_BLOCKS, BLOCKS_BY_KEY, REPO, Block, exec_block  # noqa: E402
from doc_scenes import (  # noqa: E402
    VOD_VOXEL, camera_scene, fpn, link_tree, pinhole, radar_points, run_detectors_init, spconv_input, vod_batch)

# Tiny tensors and spconv's CPU kernels: one intra-op thread is faster on the shared 2-core machine.
pytestmark = pytest.mark.usefixtures("one_thread")


# ---------------------------------------------------------------------------------------------------
# classification
# ---------------------------------------------------------------------------------------------------
_SIGNATURES = "API signature listing (shapes and `-> result` annotations, not Python)"

FRAGMENTS: Dict[Tuple[str, str], str] = {
    ("docs/frameworks.md", "from mssf_blocks.integrations.openpcdet import augmentor_order, fusion_inputs_from_batch_dict"):
        "runs inside an OpenPCDet model (batch_dict, cfg, fusion_block are OpenPCDet's); "
        "tests/integrations/test_openpcdet_adapter.py builds such batches and calls it",
    ("docs/frameworks.md", "from mssf_blocks.integrations.mmdet3d import fusion_inputs_from_data_samples"):
        "runs inside an mmdet3d detector (its batch_inputs_dict, data samples, img_feats); "
        "tests/integrations/test_mmdet3d_adapter.py builds such batches and calls it",
    ("docs/diagnostics.md", "classify_feature_blurring(centroids (N, 3+), batch_index (N,), uv (N, V, 2) | (N, 2),"):
        _SIGNATURES,
    ("docs/evaluation.md", "from mssf_examples.evaluation.metrics import evaluate, format_table"):
        "data-format sketch: `label_dir` / `frame_ids` stand for a dataset, `(K, 7)` for tensors, `baseline_results` "
        "for a second run (tests/examples/evaluation/test_evaluation_*.py cover evaluate / format_table per protocol)",
    ("docs/fusion.md", "FusionInputs(image_features, lidar2img, image_size, points, points_batch, points_to_sensor=None)"):
        _SIGNATURES,
    ("docs/heads.md", "SemanticGuidedHead(in_channels: int, hidden: Sequence[int] = (256, 256), use_loss: bool = True,"):
        _SIGNATURES,
    ("docs/heads.md", 'sigmoid_focal_loss(logits, targets, ignore=None, alpha=0.25, gamma=2.0, reduction="positives") -> Tensor'):
        _SIGNATURES,
    ("docs/heads.md", 'points_in_boxes(points (P, 3+), boxes (G, 7+), origin="center", margin=0.0, eps=1e-6) -> (P, G) bool'):
        _SIGNATURES,
    ("docs/heads.md", "voxel_foreground_labels(centroids (N, 3+), batch_index (N,), gt_boxes: list[(G_b, 7+)], margin=0.1,"):
        _SIGNATURES,
    ("docs/pillar.md", "HeightEmbedding(num_z: int, channels: int, device=None, dtype=None)"):
        _SIGNATURES,
    ("docs/deployment.md", "import torch"):
        "sketch with a frame's `voxels` / `inputs` and VoD channel widths; tests/test_compile.py and "
        "tests/test_export.py run the same compile / export / ONNX calls on generated inputs",
    ("docs/real-data.md", "from vod.evaluation import Evaluation"):
        "needs the third-party VoD devkit (`vod`, not a dependency), the full VoD label folder and the "
        "prediction folder of a training run",
}

SNIPPETS: Dict[Tuple[str, str], Callable] = {}


def snippet(file: str, first_line: str):
    """Register ``fn(run, tmp_path)`` as the test of the block of ``file`` starting with ``first_line``."""

    def register(fn):
        key = (file, first_line)
        assert key not in SNIPPETS, f"{key} registered twice"
        SNIPPETS[key] = fn
        return fn

    return register


# ---------------------------------------------------------------------------------------------------
# the runnable blocks
# ---------------------------------------------------------------------------------------------------
@snippet("README.md", "import torch, spconv.pytorch as spconv")
def readme_drop_in(run, tmp_path):
    """Runs as written, forward and backward, in a fresh interpreter (so nothing else in the test session
    has patched spconv for it: the block's own ``enable_cpu_backward()`` call must do it)."""
    import os
    import subprocess
    import sys

    pytest.importorskip("spconv.pytorch")
    block = BLOCKS_BY_KEY[("README.md", "import torch, spconv.pytorch as spconv")]
    checks = textwrap.dedent("""
        assert isinstance(x, spconv.SparseConvTensor)
        assert x.features.shape[1] == 32 and x.batch_size == 2
        assert list(x.spatial_shape) == [20, 512, 512]  # the stride-2 SparseConv3d of `down`
        assert "spconv2" in x.indice_dict and "subm2" in x.indice_dict
        assert torch.isfinite(x.features).all()
        no_grad = [n for n, p in stage.named_parameters() if p.grad is None or not torch.isfinite(p.grad).all()]
        assert not no_grad, f"parameters without a finite gradient: {no_grad}"
        # (not query_init: MSDFF's offset / attention projections start at zero weight, as in
        # Deformable DETR, so the query gets no gradient at the first step)
        for part in (stage.downsample, stage.blocks, stage.fusion):
            assert sum(float(p.grad.abs().sum()) for p in part.parameters()) > 0, type(part).__name__
        print("README drop-in: forward and backward ran")
    """)
    code = block.code + checks
    script = tmp_path / "readme_drop_in.py"
    script.write_text(code)
    env = dict(os.environ, PYTHONPATH=str(REPO / "src"), OMP_NUM_THREADS="1")
    out = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and "forward and backward ran" in out.stdout, out.stdout + out.stderr


@snippet("docs/conventions.md", "v = SparseVoxels(torch.zeros(1, 1), torch.tensor([[0, 2, 64, 12]], dtype=torch.int32), (6, 128, 128), 1,")
def conventions_voxel_centre(run, tmp_path):
    from mssf_blocks import SparseVoxels

    ns = run({"torch": torch, "SparseVoxels": SparseVoxels})  # the shown tensor is checked by `run`
    assert ns["__shown_tensors_checked__"] == 1
    assert ns["v"].voxel_centers(torch.float64)[0].tolist() == pytest.approx([5.0, 0.2, -0.5], abs=1e-12)


@snippet("docs/conventions.md", "a, size = image_augmentation_matrix((4, 6), flip=True)")
def conventions_image_flip(run, tmp_path):
    from mssf_blocks import image_augmentation_matrix

    ns = run({"torch": torch, "image_augmentation_matrix": image_augmentation_matrix})
    assert ns["__shown_tensors_checked__"] == 1 and ns["size"] == (4, 6)


@snippet("docs/training.md", "from mssf_examples.data.augment import augment_batches")
def training_augment_batches(run, tmp_path):
    from mssf_examples.scenes.synthetic import Scene, SceneConfig, generate_scene

    scenes = [generate_scene(s, SceneConfig(image_size=(32, 48))) for s in (1, 2)]
    loader = [Scene.collate(scenes), Scene.collate(scenes[::-1])]
    ns = run({"loader": loader})
    out = list(ns["batches"])
    assert len(out) == 2 and all(b.points_to_sensor is not None for b in out)
    assert not torch.equal(out[0].points[0], loader[0].points[0])


@snippet("docs/conventions.md", "m = augmentation_matrix(flip_x=flip, rotation=angle, scale=s)      # points: p' = m @ p")
def conventions_authors_augmentation(run, tmp_path):
    import mssf_blocks as mb

    l2i = pinhole(1, (32, 48), 40.0)
    ns = run({"torch": torch, "augmentation_matrix": mb.augmentation_matrix, "flip": True, "angle": 0.3, "s": 1.02,
              "image_augmentation_matrix": mb.image_augmentation_matrix,
              "apply_image_augmentation": mb.apply_image_augmentation, "image_size": (32, 48), "lidar2img": l2i})
    # An augmented point projects (through points_to_sensor and the flipped lidar2img) to the mirror pixel
    # of the original point: u' = W - 1 - u.
    p = torch.tensor([10.0, 1.0, 0.5, 1.0], dtype=torch.float64)
    before = l2i[0, 0].double() @ p
    after = ns["lidar2img"][0, 0].double() @ ns["points_to_sensor"][0] @ (ns["m"] @ p)
    assert ns["image_size"] == (32, 48)
    assert float(after[0] / after[2]) == pytest.approx(47 - float(before[0] / before[2]), abs=1e-9)
    assert float(after[1] / after[2]) == pytest.approx(float(before[1] / before[2]), abs=1e-9)


@snippet("docs/detectors.md", "from mssf_examples.models.detectors import build_detector")
def detectors_build(run, tmp_path):
    pytest.importorskip("spconv")
    torch.manual_seed(0)
    ns = run({"batch": vod_batch(2)})
    losses, dets = ns["losses"], ns["dets"]
    assert {"det_cls", "det_reg", "seg", "loss"} <= set(losses) <= {"det_cls", "det_reg", "det_dir", "seg", "loss"}
    assert all(torch.isfinite(v).all() for v in losses.values())
    assert isinstance(dets, list) and len(dets) == 2
    for d in dets:
        k = d["boxes"].shape[0]
        assert d["boxes"].shape == (k, 7) and d["scores"].shape == (k,) and d["labels"].shape == (k,)


@snippet("docs/detectors.md", "from mssf_blocks.blocks import FusionBlock")
def detectors_openpcdet_init(run, tmp_path):
    from mssf_blocks import FusionBlock, QueryInit, SemanticGuidedHead

    ns = run_detectors_init(run)
    assert isinstance(ns["self"].conv2, FusionBlock) and isinstance(ns["self"].conv2.query_init, QueryInit)
    assert isinstance(ns["self"].conv2.semantic_head, SemanticGuidedHead)
    assert ns["self"].conv2.head_position == "after_fusion"


@snippet("docs/detectors.md", "inputs = FusionInputs(image_features=img_feats,            # L levels (B, V, C, H_l, W_l)")
def detectors_openpcdet_forward(run, tmp_path):
    """Continues the previous block (its `self`, imports and `point_cloud_range`)."""
    spconv = pytest.importorskip("spconv.pytorch")
    init = BLOCKS_BY_KEY[("docs/detectors.md", "from mssf_blocks.blocks import FusionBlock")]
    ns = run_detectors_init(lambda ns: exec_block(init, ns))
    H, W = 320, 512
    points = radar_points(2)
    ns.update(img_feats=fpn(2, (H, W), cameras=1), batch_dict={"lidar2img": pinhole(2, (H, W), 200.0), "points": points},
              H=H, W=W, aug_inverse=torch.eye(4).expand(2, 4, 4), voxel_size=VOD_VOXEL,
              x_conv1=spconv_input(points, 16, (41, 1024, 1024), 2))  # OpenPCDet's padded z
    ns = run(ns)
    x_conv2, scores = ns["x_conv2"], ns["scores"]
    assert ns["x"].stride == (2, 2, 2)
    assert isinstance(x_conv2, spconv.SparseConvTensor) and x_conv2.features.shape[1] == 32
    assert list(x_conv2.spatial_shape) == [21, 512, 512]
    assert "spconv2" in x_conv2.indice_dict
    assert scores.shape == (x_conv2.features.shape[0],) and ((scores > 0) & (scores < 1)).all()


@snippet("docs/diagnostics.md", "proj = projector(voxels, points, points_batch, lidar2img, image_size)")
def diagnostics_mask_blur(run, tmp_path):
    from mssf_blocks import SFF
    from mssf_blocks.diagnostics import classify_projection, mask_blur_projection

    ns = camera_scene()
    levels = [torch.rand(1, 4, 64 // s, 96 // s) + 0.5 for s in (1, 2)]  # positive: a seen voxel reads non-zero
    ns.update(classify_projection=classify_projection, mask_blur_projection=mask_blur_projection,
              sff=SFF([4, 4], 8).eval(), image_features=levels)
    ns = run(ns)
    proj, cls = ns["proj"], ns["cls"]
    centroid_x = proj.centroid[:, 0].tolist()
    blurred = [x == pytest.approx(20.0, abs=0.5) for x in centroid_x]  # only the voxel behind the car
    assert cls.blurred.tolist() == blurred and sum(blurred) == 1
    assert not proj.valid[cls.blurred].any() and (proj.uv[cls.blurred] == -1).all()
    raw = ns["sff"].sample(levels, proj)
    assert (raw[cls.blurred] == 0).all() and (raw[~cls.blurred].abs().sum(1) > 0).all()
    assert ns["f_img"].shape == (len(centroid_x), 8)


@snippet("docs/fusion.md", "from mssf_blocks.samplers import MSDFF")
def fusion_value_projection_orders(run, tmp_path):
    ns = camera_scene(channels=64)
    proj = ns["projector"](ns["voxels"], ns["points"], ns["points_batch"], ns["lidar2img"], ns["image_size"])
    torch.manual_seed(0)
    levels = fpn(1, (64, 96), strides=(1, 2, 4, 8))
    ns = run({"torch": torch, "query": torch.randn(proj.uv.shape[0], 64), "levels": levels, "projection": proj})
    assert ns["a"](ns["query"], levels, proj).shape == (proj.uv.shape[0], 64)  # the block's assert_close did the check


@snippet("docs/fusion.md", "from mssf_blocks.blocks import FusionBlock")
def fusion_swap_openpcdet(run, tmp_path):
    spconv = pytest.importorskip("spconv.pytorch")
    import swap_openpcdet_stage as ex

    torch.manual_seed(0)
    grid = [round((hi - lo) / v) for lo, hi, v in zip(ex.POINT_CLOUD_RANGE[:3], ex.POINT_CLOUD_RANGE[3:], ex.VOXEL_SIZE)]
    backbone = ex.VoxelResBackBone8x(7, grid).eval()
    feats, coords, frame = ex.random_frame(batch_size=2, points_per_frame=200)
    x = backbone.conv1(backbone.conv_input(spconv.SparseConvTensor(feats, coords, backbone.sparse_shape, 2)))
    ns = {"backbone": backbone, "spconv": spconv, "point_cloud_range": ex.POINT_CLOUD_RANGE, "voxel_size": ex.VOXEL_SIZE,
          "fpn_levels": fpn(2, ex.IMAGE_SIZE, cameras=1), "lidar2img": frame.lidar2img, "image_size": ex.IMAGE_SIZE,
          "points": frame.points, "points_batch": frame.points_batch, "x": x}
    with torch.no_grad():  # forward only (the README drop-in block checks spconv backward on CPU)
        ns = run(ns, insert={"x = stage(x, inputs) if isinstance(stage, FusionBlock) else stage(x)": "stage = backbone.conv2"})
        out = ns["x"]
        assert isinstance(out, spconv.SparseConvTensor) and out.features.shape[1] == 32
        assert {"spconv2", "res2"} <= set(out.indice_dict)
        assert backbone.conv3(out).features.shape[1] == 64  # feeds conv3 as before


@snippet("docs/heads.md", "import torch")
def heads_typical_use(run, tmp_path):
    """Runs as printed; the labels come from the block's own centroids (FusionBlockOutput), which are the
    projector's centroids of the voxels the head read."""
    from mssf_blocks import FusionBlockOutput, SparseVoxels, VoxelCentroidProjector, points_in_boxes

    ns = run({})
    out, labels, ignore, loss = ns["out"], ns["labels"], ns["ignore"], ns["loss"]
    assert isinstance(out, FusionBlockOutput) and isinstance(ns["x"], SparseVoxels)
    inputs = ns["inputs"]
    proj = VoxelCentroidProjector()(out.head_voxels, inputs.points, inputs.points_batch, inputs.lidar2img,
                                    inputs.image_size)
    torch.testing.assert_close(out.centroids, proj.centroid)  # no second projection needed: the same centroids
    # points 0 and 3 lie inside the car box (each in its own 0.5 m voxel), points 1 and 2 outside
    inside = points_in_boxes(out.centroids, ns["gt_boxes"][0])[:, 0]
    assert labels.tolist() == inside.float().tolist() and int(labels.sum()) == 2 and not ignore.any()
    assert loss.dim() == 0 and torch.isfinite(loss) and loss > 1.5
    assert ns["logits"].shape == labels.shape and ns["x"].features.shape == (labels.shape[0], 128)


@snippet("docs/pillar.md", "import torch")
def pillar_lift_fuse(run, tmp_path):
    ns = run({})  # runs as printed
    out, v, B = ns["bev"], ns["v"], ns["B"]
    hb, wb = out.shape[-2:]
    assert out.shape == (B, ns["C"], 80, 80)
    occupied = torch.zeros(B, hb, wb, dtype=torch.bool)
    occupied[v.coords[:, 0].long(), v.coords[:, 2].long(), v.coords[:, 3].long()] = True
    assert (out.permute(0, 2, 3, 1)[~occupied] == 0).all() and occupied.any()


REAL_DATA_FIRST_LINE = (
    "from mssf_examples.data.kitti_io import KittiFormatDataset, VOD_RADAR, TJ4D_RADAR, TJ4D_CLASSES, frames_to_batch"
)


@snippet("docs/real-data.md", REAL_DATA_FIRST_LINE)
def real_data_api(run, tmp_path, realdata_root=None):
    """The block's dataset paths point at trees of symlinks to ``../shared/realdata/vod`` (two frames).

    The TJ4DRadSet tree holds the same VoD files: the block only constructs that dataset (reads no frame).
    """
    from mssf_examples.data.batch import RadarCameraBatch

    vod_src = realdata_root / "vod"
    ids = sorted(p.stem for p in (vod_src / "radar" / "velodyne").glob("*.bin"))
    files = {"velodyne": vod_src / "radar" / "velodyne", "calib": vod_src / "radar" / "calib",
             "image_2": vod_src / "image_2", "label_2": vod_src / "label_2"}
    vod_root, tj4d_root = tmp_path / "view_of_delft", tmp_path / "TJ4DRadSet"
    link_tree(vod_root / "radar_5frames" / "training", files)
    (vod_root / "radar_5frames" / "ImageSets").mkdir()
    (vod_root / "radar_5frames" / "ImageSets" / "train.txt").write_text("\n".join(ids) + "\n")
    link_tree(tj4d_root / "training", files)
    (tj4d_root / "ImageSets").mkdir()
    (tj4d_root / "ImageSets" / "val.txt").write_text(ids[0] + "\n")
    ns = run({}, replace={'"/data/view_of_delft"': repr(str(vod_root)), '"/data/TJ4DRadSet"': repr(str(tj4d_root))})
    frame, batch, tj4d = ns["frame"], ns["batch"], ns["tj4d"]
    p, g = frame.points.shape[0], frame.boxes.shape[0]
    assert frame.points.shape == (p, 7) and frame.boxes.shape == (g, 7) and frame.labels.shape == (g,)
    assert frame.image.dtype == torch.uint8 and frame.image.shape[0] == 3
    assert frame.lidar2img.shape == (3, 4) and frame.lidar2img.dtype == torch.float64
    assert isinstance(batch, RadarCameraBatch) and len(batch.points) == 2 and batch.lidar2img.shape[:2] == (2, 1)
    assert len(tj4d) == 1


real_data_api.needs_realdata = True


@snippet("docs/scenes.md", "import torch")
def scenes_usage(run, tmp_path):
    from mssf_examples.data.batch import RadarCameraBatch

    ns = run({})  # runs as is
    scene, batch = ns["scene"], ns["batch"]
    p = scene.points.shape[0]
    assert scene.points.shape == (p, 7) and scene.points.dtype == torch.float32
    assert scene.image.dim() == 3 and scene.image.shape[0] == 3 and scene.image.dtype == torch.float32
    assert 0 <= scene.image.min() and scene.image.max() <= 1
    assert scene.lidar2img.shape == (3, 4) and scene.lidar2img.dtype == torch.float64
    assert len(ns["train"]) == 512 and len(ns["val"]) == 128
    assert isinstance(batch, RadarCameraBatch) and len(batch.points) == 4 and batch.lidar2img.shape == (4, 1, 3, 4)


# ---------------------------------------------------------------------------------------------------
# the tests
# ---------------------------------------------------------------------------------------------------
def test_every_python_block_is_classified():
    keys = [b.key for b in ALL_BLOCKS]
    duplicates = sorted({k for k in keys if keys.count(k) > 1})
    assert not duplicates, f"python blocks with the same first line in one file (give them distinct ones): {duplicates}"
    both = set(SNIPPETS) & set(FRAGMENTS)
    assert not both, f"classified as runnable and as fragment: {sorted(both)}"
    unclassified = [b.id + f" (line {b.line})" for b in ALL_BLOCKS if b.key not in SNIPPETS and b.key not in FRAGMENTS]
    assert not unclassified, (
        "python blocks in README.md / docs/*.md that tests/docs/test_docs_snippets.py does not know: run them with "
        "@snippet(...) or list them in FRAGMENTS with the reason:\n  " + "\n  ".join(unclassified))
    stale = sorted((set(SNIPPETS) | set(FRAGMENTS)) - set(keys))
    assert not stale, f"classified blocks no longer in the docs (first line changed or block removed): {stale}"


RUNNABLE = [b for b in ALL_BLOCKS if b.key in SNIPPETS]


@pytest.mark.parametrize("block", RUNNABLE, ids=[b.id for b in RUNNABLE])
def test_doc_block_runs(block, tmp_path, request):
    fn = SNIPPETS[block.key]
    kwargs = {}
    if getattr(fn, "needs_realdata", False):
        kwargs["realdata_root"] = request.getfixturevalue("realdata_root")

    def run(namespace, insert=None, replace=None):
        b = block
        for old, new in (replace or {}).items():
            assert old in b.code, f"{b.id}: {old!r} not in the block"
            b = Block(b.file, b.index, b.line, b.code.replace(old, new))
        return exec_block(b, namespace, insert)

    fn(run, tmp_path, **kwargs)
