"""The shipped mmdet3d configs train and evaluate inside the real mmdetection3d 1.4.0 (mmcv's compiled ops).

Each config, with only the data root (a generated VoD-layout tree, ``.jpg`` images, 4 training frames,
info files written by ``mssf_examples.mmdet3d.infos``), the iteration count (2) and the image scale
overridden, as the entry's ``--data-root``, ``--iters`` and ``--image-scale`` do (batch size 4, 4 workers,
schedule as shipped), goes through ``Runner.from_cfg(cfg).train()``, which validates at its end (the
entry's iteration count puts the validation there: ``val_loop.run()``, what ``Runner.val()`` runs): the box
and semantic losses are present and finite, every fusion-block parameter (MSDFF / SFF, query init, pillar
lifts, semantic head) receives a non-zero gradient, the metric returns the VoD keys. The radar-only
twins are the MSSF models less the fusion, parameter for parameter.
"""

from __future__ import annotations

import math
import re
import sys
from contextlib import contextmanager
from pathlib import Path
from unittest import mock

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
from mmdet3d_vod_tree import CONFIGS, ci_widths, fake_htc_checkpoint, require_mmdet3d, write_tree  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")
MSSF = ["mssf_pointpillars_vod.py", "mssf_second_vod.py", "mssf_centerpoint_vod.py"]
TWINS = {"mssf_pointpillars_vod.py": "pointpillars_vod_radar.py", "mssf_second_vod.py": "second_vod_radar.py",
         "mssf_centerpoint_vod.py": "centerpoint_vod_radar.py"}
SINGLE_SCAN = "mssf_pointpillars_vod_single_scan.py"  # on VoD's single-scan `radar` folder
FUSION_PARAM = re.compile(r"(^|\.)(fusion|fusions|query_init|lifts|seg_head)\.")
IMAGE_SCALE = (160, 100)


@pytest.fixture(scope="module")
def data_root(tmp_path_factory):
    require_mmdet3d()
    return write_tree(tmp_path_factory.mktemp("vod"))


@pytest.fixture(scope="module")
def single_scan_root(tmp_path_factory):
    require_mmdet3d()
    return write_tree(tmp_path_factory.mktemp("vod_radar"), sensor="radar")


def small_cfg(name, data_root, work_dir, iters=2):
    """The shipped config with only the data root, the iteration count and the image scale overridden, as the
    entry's ``--data-root``, ``--iters`` and ``--image-scale`` do (batch size, workers, schedule as shipped), and
    the frozen image branch given its weights as ``--image-checkpoint`` does (a generated HTC-shaped file)."""
    from mssf_examples.mmdet3d.cli import load_config, set_image_checkpoint, set_image_scale, set_iterations

    cfg = load_config(str(CONFIGS / name), str(work_dir), data_root=str(data_root))
    set_image_scale(cfg, IMAGE_SCALE)
    set_iterations(cfg, iters)
    if cfg.model.get("img_backbone") is not None:
        set_image_checkpoint(cfg, fake_htc_checkpoint())
    return cfg


def recorder(model):
    """An mmengine hook recording the losses of every train iteration and, per fusion parameter, whether a
    gradient reached it non-zero and finite (tensor hooks: the optimiser zeroes ``.grad`` after each step)."""
    from mmengine.hooks import Hook

    class Recorder(Hook):
        def __init__(self):
            self.losses, self.batch_sizes, self.validations = [], [], []
            self.nonzero = {}
            for name, p in model.named_parameters():
                if FUSION_PARAM.search(name):
                    self.nonzero[name] = False
                    p.register_hook(self._hook(name))

        def _hook(self, name):
            def hook(grad):
                if bool(torch.any(grad != 0)) and bool(torch.isfinite(grad).all()):
                    self.nonzero[name] = True
            return hook

        def after_train_iter(self, runner, batch_idx, data_batch=None, outputs=None):
            self.losses.append({k: float(v) for k, v in outputs.items()})
            self.batch_sizes.append(len(data_batch["data_samples"]))

        def after_val_epoch(self, runner, metrics=None):
            self.validations.append((runner.iter, dict(metrics or {})))

    return Recorder()


def _unformatted(text, **kwargs):
    return text, False


@contextmanager
def unformatted_config_text():
    """Leave mmengine's config text unformatted (still valid Python): ``Config.pretty_text`` runs yapf over the
    whole config each time the runner logs it, dumps it or saves it in a checkpoint's meta, 5 times in a
    2-iteration run, 13 s of an 83 s cell measured (cProfile, ``centerpoint_vod_radar.py``, loaded machine): the
    set-up cost every cell shares. The tests read no config text; the runner's work is otherwise unchanged."""
    import mmengine.config.config as config_module

    with mock.patch.object(config_module, "FormatCode", _unformatted):
        yield


def run(cfg):
    from mmengine.runner import Runner

    from mssf_examples.mmdet3d.cli import release_workers

    with unformatted_config_text():
        runner = Runner.from_cfg(cfg)
        rec = recorder(runner.model)
        runner.register_hook(rec)
        runner.train()
    release_workers(runner)  # as the entry does (the shipped persistent workers)
    return runner, rec


def recording_runners(monkeypatch):
    """Attach a :func:`recorder` to every runner ``Runner.from_cfg`` builds (the entry's ``main`` included);
    returns the list of ``(runner, recorder)`` it fills."""
    from mmengine.runner import Runner

    import mmengine.config.config as config_module

    monkeypatch.setattr(config_module, "FormatCode", _unformatted)  # as unformatted_config_text()
    built = []
    from_cfg = Runner.from_cfg.__func__

    def recording_from_cfg(cls, cfg):
        runner = from_cfg(cls, cfg)
        rec = recorder(runner.model)
        runner.register_hook(rec)
        built.append((runner, rec))
        return runner

    monkeypatch.setattr(Runner, "from_cfg", classmethod(recording_from_cfg))
    return built


def box_loss_keys(head):
    """The loss keys of the config's box head: ``Anchor3DHead``'s three, or per task of mmdet3d's centre head."""
    if head.type == "CenterHeadWithoutVelocity":
        return {f"task{i}.{k}" for i in range(len(head.tasks)) for k in ("loss_heatmap", "loss_bbox")}
    return {"loss_cls", "loss_bbox", "loss_dir"}


def check_vod_run(runner, rec, fusion):
    """2 iterations of 4 frames (the shipped batch size; the generated tree has 4 training frames), the losses
    present and finite, every fusion parameter with a non-zero gradient, one validation at the end with the
    VoD keys."""
    assert len(rec.losses) == 2 and rec.batch_sizes == [4, 4]
    expected = box_loss_keys(runner.cfg.model.pts_bbox_head) | ({"loss_seg"} if fusion else set())
    for step in rec.losses:
        assert expected <= set(step), step
        assert ("loss_seg" in step) == fusion
        assert all(math.isfinite(v) for v in step.values()), step
    if fusion:
        assert rec.nonzero and all(rec.nonzero.values()), [n for n, ok in rec.nonzero.items() if not ok]
        assert runner.model.pts_middle_encoder.num_fusion_blocks == 2
        assert not any(p.requires_grad for p in runner.model.img_backbone.parameters())  # frozen image branch
    else:
        assert not rec.nonzero  # the twin has no fusion parameters
    # the entry's iteration count validates once, at the end: IterBasedTrainLoop's val_loop.run(), which is
    # what Runner.val() runs (a second call would repeat the same evaluation)
    assert [it for it, _ in rec.validations] == [2]
    metrics = rec.validations[0][1]
    for region in ("entire_area", "driving_corridor"):
        for cls in ("Car", "Pedestrian", "Cyclist", "mAP"):
            for key in ("AP3D_R11", "AP3D_R40", "APBEV_R11", "APBEV_R40"):
                assert f"VoD/{region}/{cls}/{key}" in metrics


# mssf_pointpillars_vod.py: its run is docs/frameworks.md's quick check, run verbatim and checked with
# check_vod_run by test_mmdet3d_docs.py (the same 2 iterations; one run instead of two)
@pytest.mark.parametrize("name", ["mssf_second_vod.py", "mssf_centerpoint_vod.py"] + sorted(TWINS.values()))
def test_config_trains_and_evaluates(name, data_root, tmp_path):
    cfg = small_cfg(name, data_root, tmp_path)
    if "centerpoint" in name:  # the 2D part at CI widths (ci_widths); SECOND's cells keep the shipped ones
        ci_widths(cfg)
    assert cfg.train_dataloader.batch_size == 4 and cfg.train_dataloader.num_workers == 4  # as shipped
    runner, rec = run(cfg)
    check_vod_run(runner, rec, fusion=name in MSSF)


def test_single_scan_config_trains_and_evaluates(single_scan_root, tmp_path):
    """The single-scan example reads VoD's ``radar`` folder (its info files, its metric's ``ann_file``)."""
    assert single_scan_root.name == "radar"
    shipped = small_cfg(SINGLE_SCAN, single_scan_root, tmp_path)
    from mssf_examples.mmdet3d.cli import load_config

    plain = load_config(str(CONFIGS / SINGLE_SCAN), str(tmp_path))
    assert plain.train_dataloader.dataset.data_root == "data/view_of_delft/radar/"
    assert plain.val_evaluator.ann_file == "data/view_of_delft/radar/vod_infos_val.pkl"
    five = load_config(str(CONFIGS / "mssf_pointpillars_vod.py"), str(tmp_path))
    assert plain.model == five.model  # the same detector, only the data differs
    runner, rec = run(shipped)
    check_vod_run(runner, rec, fusion=True)


@pytest.mark.parametrize("name", MSSF)
def test_fusion_removed_is_the_radar_only_twin(name, data_root, tmp_path):
    from mmdet3d.registry import MODELS

    cfg = small_cfg(name, data_root, tmp_path)
    twin = small_cfg(TWINS[name], data_root, tmp_path)
    cfg.model.img_backbone = None
    cfg.model.img_neck = None
    cfg.model.pts_middle_encoder.update(num_fusion_blocks=0, image_channels=None, seg_hidden=None)
    assert cfg.model == twin.model
    torch.manual_seed(0)
    a = MODELS.build(cfg.model).state_dict()
    torch.manual_seed(0)
    b = MODELS.build(twin.model).state_dict()
    assert list(a) == list(b)
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_iteration_count_binds_schedule_validation_checkpoint_and_logging(data_root, tmp_path):
    """``--iters N`` (``set_iterations``): the one-cycle schedule over exactly N iterations, one validation and
    one checkpoint at N, a log line every min(N, 50); a count that is not a positive integer is refused."""
    from mssf_examples.mmdet3d.cli import load_config, set_iterations

    for iters, log_every in ((2, 2), (120, 50)):
        cfg = load_config(str(CONFIGS / "mssf_pointpillars_vod.py"), str(tmp_path), data_root=str(data_root))
        shipped = cfg.param_scheduler[0].copy()
        assert (shipped.by_epoch, shipped.begin, shipped.end) == (True, 0, cfg.train_cfg.max_epochs)
        set_iterations(cfg, iters)
        assert cfg.train_cfg == dict(type="IterBasedTrainLoop", max_iters=iters, val_interval=iters)
        sched = cfg.param_scheduler[0]
        assert (sched.type, sched.by_epoch, sched.begin, sched.end) == ("OneCycleLR", False, 0, iters)
        assert "convert_to_iter_based" not in sched and sched.eta_max == shipped.eta_max
        assert cfg.default_hooks.checkpoint.by_epoch is False and cfg.default_hooks.checkpoint.interval == iters
        assert cfg.default_hooks.logger.interval == log_every and cfg.log_processor.by_epoch is False
        assert cfg.train_dataloader.batch_size == 4 and cfg.train_dataloader.num_workers == 4  # untouched
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="iters: expected a positive integer"):
            set_iterations(cfg, bad)
