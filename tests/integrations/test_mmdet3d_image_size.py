"""Images stored at another size than the calibration's (``P2`` / ``lidar2img`` kept): mmdet3d's pipeline loads
them and the detector would fuse every point with the wrong pixels. Inside the real mmdetection3d 1.4.0, on a
generated View-of-Delft tree whose images are then halved on disk (calibration untouched), the first
``test_step`` of ``mssf_pointpillars_vod.py`` warns, naming the calibration and the measured principal point;
the same tree with its images as written does not.
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from mmdet3d_vod_tree import require_mmdet3d, write_tree  # noqa: E402
from test_mmdet3d_train import small_cfg  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")
HINT = "images resized without updating the calibration (lidar2img / P2)?"


def measured_scale(message: str) -> float:
    """The size factor the warning gives ("the calibration was made for images about S x this size")."""
    import re

    return float(re.search(r"made for images about ([0-9.]+) x this size", message).group(1))


def halve_images(data_root: Path) -> int:
    from PIL import Image

    n = 0
    for f in sorted((data_root / "training" / "image_2").glob("*.jpg")):
        with Image.open(f) as im:
            small = im.resize((im.width // 2, im.height // 2), Image.BILINEAR)
        small.save(f, quality=95)
        n += 1
    return n


def first_test_step(data_root: Path, tmp_path: Path):
    """``model.test_step`` of the config's first validation batch; the geometry warnings it raised."""
    from mmdet3d.registry import MODELS
    from mmengine.registry import init_default_scope
    from mmengine.runner import Runner

    import mssf_examples.mmdet3d.plugin  # noqa: F401  (the config's custom_imports)
    from mssf_blocks.errors import MSSFGeometryWarning

    init_default_scope("mmdet3d")

    cfg = small_cfg("mssf_pointpillars_vod.py", data_root, tmp_path)
    cfg.val_dataloader.num_workers, cfg.val_dataloader.persistent_workers = 0, False
    loader = Runner.build_dataloader(cfg.val_dataloader)
    model = MODELS.build(cfg.model).eval()
    batch = next(iter(loader))
    with warnings.catch_warnings(record=True) as caught, torch.no_grad():
        warnings.simplefilter("always")
        model.test_step(batch)
    meta = batch["data_samples"][0].metainfo
    return [str(w.message) for w in caught if issubclass(w.category, MSSFGeometryWarning)], meta


def test_halved_images_with_full_size_calibration_warn(tmp_path):
    require_mmdet3d()
    data_root = write_tree(tmp_path / "vod", train=1, val=1)
    plain, meta = first_test_step(data_root, tmp_path / "wd0")
    assert tuple(meta["ori_shape"]) == (304, 484)
    assert not [m for m in plain if HINT in m], plain  # the images as the calibration describes them
    assert halve_images(data_root) == 2
    msgs, meta = first_test_step(data_root, tmp_path / "wd1")
    assert tuple(meta["ori_shape"]) == (152, 242)
    hits = [m for m in msgs if HINT in m]
    assert hits, msgs
    # the measured figure: the principal point at about twice the image centre, the calibration's size
    assert "242 x 152 image" in hits[0], hits[0]
    assert 1.9 < measured_scale(hits[0]) < 2.1, hits[0]


@pytest.mark.parametrize("frame", ["vod/radar/calib/01047.txt", "kitti/calib/000000.txt"])
def test_real_calibrations_against_resized_images(frame, realdata_root):
    """The real View-of-Delft and KITTI calibrations (``lidar2img = P2 R0 Tr``) in ``camera_from_meta``: silent
    with their images' size; a warning naming the factor for images stored at 1/2, 0.8 x, 2 x that size; silent
    at 0.9 x (within a real camera's principal-point spread)."""
    from PIL import Image

    from mssf_blocks.errors import MSSFGeometryWarning
    from mssf_blocks.integrations.mmdet3d import camera_from_meta
    from mssf_examples.data.kitti_calib import read_calibration

    calib = realdata_root / frame
    image = next((calib.parents[2 if frame.startswith("vod") else 1] / "image_2").glob(calib.stem + ".*"))
    with Image.open(image) as im:
        w, h = im.size
    l2i = torch.eye(4, dtype=torch.float64)
    l2i[:3] = read_calibration(calib).lidar2img.double()
    for factor in (1.0, 0.9, 0.5, 0.8, 2.0):
        meta = {"lidar2img": l2i.numpy(), "ori_shape": (round(h * factor), round(w * factor))}
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            camera_from_meta(meta)
        hits = [str(c.message) for c in caught if issubclass(c.category, MSSFGeometryWarning) and HINT in str(c.message)]
        if factor == 1.0 or factor == 0.9:
            assert not hits, (factor, hits)
        else:
            assert len(hits) == 1 and abs(measured_scale(hits[0]) * factor - 1) < 0.1, (factor, hits)
