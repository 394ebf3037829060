"""mmdetection3d's half of ``framework_gap.py``: the shipped MSSF-PointPillars config and its radar-only twin,
sized as the demo's model, trained by mmengine's ``Runner`` and evaluated by the VoD metric at its end.

What changes against the shipped files is what makes them the demo's model on the demo's data, nothing else:
the range (the scenes' 25.6 m), the widths (``demo_preset``: 0.32 m pillars, ResNet-18 of 8 base channels with a
16-channel FPN, 2 heads x 2 points, one fusion block as the demo's ``n = 1``), images scaled to [0, 1] as the demo's
image branch was trained on, the demo's image size, no augmentation (the demo's default), and the demo's budget
(steps, batch size, peak learning rate of the one-cycle schedule).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Dict

CONFIGS = Path(__file__).resolve().parents[1] / "examples" / "configs" / "mmdet3d"
MODELS = {"MSSF-PP": "mssf_pointpillars_vod.py", "PointPillars (radar only)": "pointpillars_vod_radar.py"}
AUGMENTATIONS = ("RandomFlip3D", "GlobalRotScaleTrans")


def _retarget(node: Any, old, new) -> Any:
    """Every ``[x0, y0, z0, x1, y1, z1]`` of ``node`` whose x / y extent is ``old``'s gets ``new``'s (the ranges of
    the grid, the filters and the anchors; the anchors keep their heights)."""
    if isinstance(node, dict):
        for k in list(node):
            node[k] = _retarget(node[k], old, new)
        return node
    if isinstance(node, (list, tuple)):
        if len(node) == 6 and all(isinstance(v, (int, float)) for v in node):
            if [float(node[i]) for i in (0, 1, 3, 4)] == [float(old[i]) for i in (0, 1, 3, 4)]:
                out = list(node)
                for i in (0, 1, 3, 4):
                    out[i] = float(new[i])
                if [float(node[i]) for i in (2, 5)] == [float(old[i]) for i in (2, 5)]:
                    out[2], out[5] = float(new[2]), float(new[5])
                return type(node)(out) if isinstance(node, tuple) else out
            return node
        return type(node)(_retarget(v, old, new) for v in node)
    return node


def demo_sized_config(name: str, data_root: Path, work_dir: Path, preset, budget: Dict[str, Any], image_ckpt: Path):
    """The shipped config ``name`` as the demo's model at the demo's budget (see the module's doc)."""
    from mssf_examples.mmdet3d.cli import load_config, set_image_checkpoint, set_image_scale, set_iterations

    cfg = load_config(str(CONFIGS / name), str(work_dir), data_root=str(data_root))
    old = list(cfg.model.pts_middle_encoder.point_cloud_range)
    _retarget(cfg._cfg_dict, old, preset.pillar_range)
    enc = cfg.model.pts_middle_encoder
    fuses = enc.num_fusion_blocks > 0
    enc.update(voxel_size=[*preset.pillar_size, preset.pillar_range[5] - preset.pillar_range[2]],
               pfn_channels=preset.pfn_channels, layer_nums=list(preset.pillar_layer_nums),
               num_filters=list(preset.pillar_filters), num_upsample_filters=list(preset.pillar_upsample_filters),
               lift_z_size=preset.lift_z_size, msdff_heads=preset.msdff_heads, msdff_points=preset.msdff_points,
               msdff_value_projection=preset.msdff_value_projection)
    head = cfg.model.pts_bbox_head
    head.in_channels = head.feat_channels = sum(preset.pillar_upsample_filters)
    # the demo's images are RGB in [0, 1]: mmcv loads BGR 0..255, so flip the channels and divide
    cfg.model.data_preprocessor.update(mean=[0.0, 0.0, 0.0], std=[255.0, 255.0, 255.0], bgr_to_rgb=True)
    if fuses:
        enc.update(num_fusion_blocks=budget["fusion_blocks"], image_channels=[preset.fpn_channels] * 4,
                   seg_hidden=list(preset.seg_hidden))
        cfg.model.img_backbone.update(depth=preset.image_depth, base_channels=preset.image_base_channels)
        base = preset.image_base_channels
        cfg.model.img_neck.update(in_channels=[base, 2 * base, 4 * base, 8 * base], out_channels=preset.fpn_channels)
        set_image_checkpoint(cfg, str(image_ckpt))
    for key in ("train_dataloader", "val_dataloader", "test_dataloader"):
        cfg[key].num_workers = budget["workers"]
        cfg[key].persistent_workers = budget["workers"] > 0
    pipeline = cfg.train_dataloader.dataset.pipeline
    pipeline[:] = [step for step in pipeline if step.type not in AUGMENTATIONS]
    h, w = budget["image_size"]
    set_image_scale(cfg, (w, h))
    cfg.train_dataloader.batch_size = budget["batch_size"]
    cfg.optim_wrapper.optimizer.lr = budget["lr"]
    for sched in cfg.param_scheduler:
        if "eta_max" in sched:
            sched.eta_max = budget["lr"]
    set_iterations(cfg, budget["steps"])
    cfg.default_hooks.logger.interval = max(1, min(50, budget["steps"]))
    cfg.randomness = dict(seed=budget["seed"])
    return cfg


def train_and_evaluate(cfg) -> Dict[str, float]:
    """``Runner.from_cfg(cfg).train()`` (which validates at its end); the VoD metric's values."""
    from mmengine.hooks import Hook
    from mmengine.registry import init_default_scope
    from mmengine.runner import Runner

    from mssf_examples.mmdet3d.checkpoints import weights_only_checkpoints
    from mssf_examples.mmdet3d.cli import check_image_weights_given, release_workers

    class Metrics(Hook):
        def __init__(self):
            self.values = {}

        def after_val_epoch(self, runner, metrics=None):
            self.values = dict(metrics or {})

    init_default_scope(cfg.get("default_scope", "mmdet3d"))
    check_image_weights_given(cfg)
    runner = Runner.from_cfg(cfg)
    hook = Metrics()
    runner.register_hook(hook)
    with weights_only_checkpoints():
        runner.train()
    release_workers(runner)
    return {k: float(v) for k, v in hook.values.items()}
