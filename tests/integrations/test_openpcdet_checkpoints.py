"""Evaluating a trained MSSF checkpoint with OpenPCDet's ``test.py`` needs no pre-trained image-branch file
(the checkpoint holds the branch), while training from scratch still refuses a frozen branch without one.

The documented commands through ``python -m mssf_examples.openpcdet``, from OpenPCDet's tools/, on the
generated tree of test_openpcdet_vod (its ``tools`` fixture) with the CPU sizes of its documented-command test.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

pytest.importorskip("spconv")

sys.path.insert(0, str(Path(__file__).parent))
from test_openpcdet_vod import load, tools  # noqa: E402,F401  (the module-scoped fixture)

from mssf_blocks import MSSFError  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")
CPU = ["--workers", "0", "--batch_size", "2", "--set", "MODEL.IMAGE_BRANCH.DEPTH", "18",
       "MODEL.IMAGE_BRANCH.BASE_CHANNELS", "8", "OPTIMIZATION.PCT_START", "0.5"]
CFG = ["--cfg_file", "cfgs/vod_models/mssf_second.yaml"]


def test_test_py_on_a_trained_checkpoint_needs_no_image_branch_file(tools, monkeypatch):
    from easydict import EasyDict

    from mssf_examples.models.image_branch import ImageBranch
    from mssf_examples.openpcdet.__main__ import main

    monkeypatch.setattr("time.sleep", lambda seconds: None)
    htc = tools.root.parent / "checkpoints" / "htc_r50_fpn_image_branch.pth"  # the config's CHECKPOINT
    htc.parent.mkdir(exist_ok=True)
    torch.save(ImageBranch(depth=18, base_channels=8, fpn_channels=256, num_outs=4).state_dict(), htc)
    tag = ["--extra_tag", "no_htc_test"]
    main(["--pure-torch-nms", "train.py", *CFG, "--epochs", "1", "--wo_gpu_stat", *tag, *CPU])
    out = tools.root.parent / "output" / "vod_models" / "mssf_second" / "no_htc_test"
    trained = out / "ckpt" / "checkpoint_epoch_1.pth"
    htc.unlink()  # a user evaluating a checkpoint they were given

    main(["--pure-torch-nms", "test.py", *CFG, "--ckpt", str(trained), *tag, *CPU])
    logs = list((out / "eval").rglob("log_eval_*.txt"))
    assert logs and "VoD driving_corridor:" in logs[-1].read_text()

    # the branch's weights are the checkpoint's (in-process: build, load as test.py does)
    from pcdet.datasets import build_dataloader
    from pcdet.models import build_network

    from mssf_examples.openpcdet.image_module import expect_trained_checkpoint

    cfg = load("mssf_second")
    cfg.MODEL.IMAGE_BRANCH.update(DEPTH=18, BASE_CHANNELS=8)
    dataset, _, _ = build_dataloader(cfg.DATA_CONFIG, cfg.CLASS_NAMES, batch_size=1, dist=False, workers=0,
                                     training=False)
    state = torch.load(trained, map_location="cpu", weights_only=False)["model_state"]
    expect_trained_checkpoint(True)
    try:
        model = build_network(cfg.MODEL, num_class=3, dataset=dataset)
        assert model.image_branch.awaiting_checkpoint
        with pytest.raises(MSSFError, match="MODEL.IMAGE_BRANCH: its weights were to come from a trained"):
            model.image_branch({"images": torch.zeros(1, 3, 64, 64)})
        model.load_params_from_file(str(trained), logger=EasyDict(info=lambda *a: None), to_cpu=True)
        w = model.image_branch.branch.backbone.conv1.weight
        torch.testing.assert_close(w, state["image_branch.branch.backbone.conv1.weight"], rtol=0, atol=0)
        # a checkpoint without the branch (e.g. of the radar-only twin) is refused, not loaded half
        model = build_network(cfg.MODEL, num_class=3, dataset=dataset)
        partial = {k: v for k, v in state.items() if not k.startswith(("image_branch.", "module_list.0."))}
        with pytest.raises(MSSFError, match=r"checkpoint: the image branch's weights .* lacks \d+ of its \d+ tensors"):
            model._load_state_dict(partial, strict=False)
    finally:
        expect_trained_checkpoint(False)

    # training from scratch still refuses the frozen branch without its file, before anything runs
    with pytest.raises(MSSFError, match="MODEL.IMAGE_BRANCH.CHECKPOINT: file not found"):
        main(["--pure-torch-nms", "train.py", *CFG, "--epochs", "1", "--wo_gpu_stat", "--extra_tag", "scratch", *CPU])
