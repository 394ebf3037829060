"""The frozen image branch of the MSSF mmdet3d configs must be given its weights (docs/frameworks.md, "The image
branch's weights"), inside the real mmdetection3d 1.4.0 / mmengine 0.10.

* training a frozen branch that no checkpoint filled is refused: by ``MSSFDetector`` at the first training step
  of mmengine's Runner (what ``tools/train.py`` runs), and by the entry before anything is built, naming
  ``model.freeze_img`` and the ways out; weights from ``init_cfg``, from a checkpoint of the model
  (``load_from``), or ``freeze_img=False`` pass;
* the page's HTC snippet, the config's comment and the ``tools/train.py`` line build as printed and load the
  (generated, HTC-shaped) checkpoint's ``backbone.*`` / ``neck.*`` weights into the image backbone and neck.
"""

from __future__ import annotations

import re
import shlex
import shutil
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from mmdet3d_vod_tree import CONFIGS, fake_htc_checkpoint, require_mmdet3d, write_tree  # noqa: E402
from test_mmdet3d_train import small_cfg  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")
REPO = Path(__file__).resolve().parents[2]
WAYS_OUT = ("model.freeze_img", "init_cfg=dict(type='Pretrained'", "load_from", "model.freeze_img=False")


@pytest.fixture(scope="module")
def data_root(tmp_path_factory):
    require_mmdet3d()
    return write_tree(tmp_path_factory.mktemp("vod"))


def build(model_cfg):
    from mmdet3d.registry import MODELS
    from mmengine.registry import init_default_scope

    import mssf_examples.mmdet3d.plugin  # noqa: F401

    init_default_scope("mmdet3d")
    return MODELS.build(model_cfg)


def htc_state():
    return torch.load(fake_htc_checkpoint(), weights_only=True)["state_dict"]


def assert_htc_loaded(model):
    state = htc_state()
    for part, prefix in (("img_backbone", "backbone."), ("img_neck", "neck.")):
        own = getattr(model, part).state_dict()
        assert own and all(torch.equal(v, state[prefix + k]) for k, v in own.items() if v.is_floating_point())


def test_frozen_unloaded_branch_refused_at_the_first_training_step(data_root, tmp_path):
    from mmengine.runner import Runner

    cfg = small_cfg("mssf_pointpillars_vod.py", data_root, tmp_path)
    for part in ("img_backbone", "img_neck"):
        cfg.model[part].pop("init_cfg")  # the shipped config, nothing loads the image branch
    runner = Runner.from_cfg(cfg)  # building is fine: test / resume runs load the weights after
    with pytest.raises(Exception) as info:
        runner.train()
    from mssf_examples.mmdet3d.cli import release_workers

    release_workers(runner)
    from mssf_blocks.errors import MSSFError

    assert isinstance(info.value, MSSFError), info.value
    msg = str(info.value)
    assert "img_backbone" in msg and "img_neck" in msg and all(w in msg for w in WAYS_OUT), msg
    assert runner.iter == 0  # no optimiser step was taken


def test_entry_refuses_before_building(data_root, tmp_path, monkeypatch):
    from mmengine.runner import Runner

    from mssf_blocks.errors import MSSFError
    from mssf_examples.mmdet3d.cli import main

    def no_build(cls, cfg):
        raise AssertionError("the runner was built")

    monkeypatch.setattr(Runner, "from_cfg", classmethod(no_build))
    args = ["train", str(CONFIGS / "mssf_pointpillars_vod.py"), "--iters", "2", "--data-root", str(data_root),
            "--work-dir", str(tmp_path)]
    with pytest.raises(MSSFError) as info:
        main(args)
    assert all(w in str(info.value) for w in WAYS_OUT) and "--image-checkpoint" in str(info.value)
    for ok in (["--image-checkpoint", "x.pth"], ["--cfg-options", "model.freeze_img=False"], ["--resume"]):
        with pytest.raises(AssertionError, match="the runner was built"):  # passed the check
            main(args + ok)
    with pytest.raises(MSSFError, match="--image-checkpoint: the config's model has no img_backbone"):
        main(["train", str(CONFIGS / "pointpillars_vod_radar.py"), "--image-checkpoint", "x.pth"])


def test_weight_sources_and_freezing(data_root, tmp_path):
    from mmengine.runner import load_checkpoint, save_checkpoint

    from mssf_blocks.errors import MSSFError
    from mssf_examples.mmdet3d.detector import check_image_weights

    cfg = small_cfg("mssf_pointpillars_vod.py", data_root, tmp_path)  # init_cfg: the HTC-shaped file
    model = build(cfg.model)
    model.init_weights()
    assert_htc_loaded(model)
    check_image_weights(model)
    path = str(tmp_path / "model.pth")
    save_checkpoint(model.state_dict(), path)
    bare = cfg.model.copy()
    for part in ("img_backbone", "img_neck"):
        bare[part] = {k: v for k, v in bare[part].items() if k != "init_cfg"}
    fresh = build(bare)
    with pytest.raises(MSSFError, match="img_backbone, img_neck: frozen by model.freeze_img=True"):
        fresh.loss({}, [])  # refused before anything runs
    load_checkpoint(fresh, path)  # what load_from does
    check_image_weights(fresh)
    part = build(bare)
    part.img_backbone.load_state_dict({k[len("backbone."):]: v for k, v in htc_state().items()
                                       if k.startswith("backbone.")})
    with pytest.raises(MSSFError, match=r"^img_neck: .*8 of its 8 frozen weight tensors"):
        check_image_weights(part)  # the neck is still random
    check_image_weights(build(dict(bare, freeze_img=False)))  # the whole branch trains
    # freezing by the modules' own settings (mmdet's frozen_stages) counts too
    own = dict(bare, freeze_img=False, img_backbone=dict(bare["img_backbone"], frozen_stages=4))
    with pytest.raises(MSSFError, match=r"^img_backbone: frozen by the modules' own settings"):
        check_image_weights(build(own))


def _section():
    text = (REPO / "docs" / "frameworks.md").read_text()
    return text[text.index("## mmdetection3d"):text.index("## Conventions that differ")]


def _configs_copy(tmp_path, monkeypatch):
    """``tmp/configs`` = the shipped configs; ``tmp/checkpoints/htc_r50_fpn.pth`` the generated file; cwd tmp."""
    shutil.copytree(CONFIGS, tmp_path / "configs")
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "htc_r50_fpn.pth").symlink_to(fake_htc_checkpoint())
    monkeypatch.chdir(tmp_path)
    return tmp_path / "configs"


def test_documented_htc_snippets_load_the_branch(tmp_path, monkeypatch):
    require_mmdet3d()
    from mmengine.config import Config

    from mssf_examples.mmdet3d.detector import check_image_weights

    configs = _configs_copy(tmp_path, monkeypatch)
    blocks = [b for b in re.findall(r"```text\n(.*?)```", _section(), re.S) if b.startswith("_base_")]
    assert len(blocks) == 1 and 'type="Pretrained"' in blocks[0]
    comment = [ln[2:] for ln in (CONFIGS / "_base_" / "models" / "mssf_pointpillars_vod.py").read_text().splitlines()
               if ln.startswith("#     model = dict(") or ln.startswith("#                  img_neck")]
    assert len(comment) == 2
    from_comment = '_base_ = ["mssf_pointpillars_vod.py"]\nPATH = "checkpoints/htc_r50_fpn.pth"\n' + \
        "\n".join(ln.strip() if i == 0 else ln for i, ln in enumerate(comment)) + "\n"
    for name, text in (("docs.py", blocks[0]), ("comment.py", from_comment)):
        (configs / name).write_text(text)
        cfg = Config.fromfile(str(configs / name))  # as printed: no TypeError asking for _delete_
        model = build(cfg.model)
        model.init_weights()
        assert_htc_loaded(model)
        check_image_weights(model)


def test_tools_train_line_sets_what_the_entry_sets(tmp_path):
    """The page's ``tools/train.py --cfg-options`` line (mmdet3d's own tool, which merges them with mmengine's
    DictAction) gives the config the entry's ``--image-scale 320 200 --image-checkpoint PATH`` give."""
    require_mmdet3d()
    import argparse

    from mmengine.config import DictAction

    from mssf_examples.mmdet3d.cli import load_config, set_image_checkpoint, set_image_scale

    (line,) = [b for b in re.findall(r"```text\n(.*?)```", _section(), re.S) if b.startswith("python tools/train.py")]
    args = shlex.split(line.replace("\\\n", " "))
    assert args[:3] == ["python", "tools/train.py", "examples/configs/mmdet3d/mssf_pointpillars_vod.py"]
    assert args[3] == "--cfg-options"
    ns = argparse.Namespace()
    DictAction(option_strings=["--cfg-options"], dest="cfg_options", nargs="+")(None, ns, args[4:])
    tools = load_config(str(REPO / args[2]))
    tools.merge_from_dict(ns.cfg_options)
    entry = load_config(str(REPO / args[2]))
    set_image_scale(entry, (320, 200))
    set_image_checkpoint(entry, "checkpoints/htc_r50_fpn.pth")
    assert tools.to_dict() == entry.to_dict()
