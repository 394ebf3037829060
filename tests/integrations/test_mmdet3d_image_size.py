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
    assert "242 x 152 image" in hits[0] and "about 2.0 x this size" in hits[0], hits[0]
