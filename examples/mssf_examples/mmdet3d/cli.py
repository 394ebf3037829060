"""``python -m mssf_examples.mmdet3d infos|train|test``: mmdet3d training without the repository's ``tools/``.

* ``infos --root DATA --sensor radar_5frames [--splits train val]``: the View-of-Delft info files, and
  ``infos --dataset tj4d --root DATA``: TJ4DRadSet's (:mod:`.infos`);
* ``train CONFIG [--work-dir DIR] [--data-root DIR] [--image-scale W H] [--iters N] [--resume [CKPT]]
  [--image-checkpoint PATH] [--cfg-options k=v ...]``: ``Runner.from_cfg(cfg).train()``; ``--iters N``
  (:func:`set_iterations`) trains N iterations instead of the config's epochs, with the schedule, validation,
  checkpoint and logging bound to them; ``--image-checkpoint`` (:func:`set_image_checkpoint`) loads the image
  branch from an mmdet checkpoint (the paper's HTC R-50-FPN); a frozen image branch that nothing loads is
  refused before anything is built (:func:`check_image_weights_given`);
* ``test CONFIG CHECKPOINT [same options less --resume, --iters and --image-checkpoint]``: ``Runner.test()``;
* ``convert-authors THEIR_CHECKPOINT --config CONFIG --out FILE``: the MSSF authors' MSSF-PP checkpoint into the
  config's model configured as theirs (:mod:`.authors_checkpoint`), with the mapped / ignored / missing report.

Checkpoints are unpickled weights-only with exactly what mmengine 0.10's checkpoints hold allowed
(:mod:`.checkpoints`): a file holding anything else is refused. What mmdet3d's ``tools/train.py`` /
``tools/test.py`` (in mmdet3d's repository, not in its package) do on one machine, less launchers and AMP.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import List, Optional

from mssf_blocks.errors import MSSFError


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m mssf_examples.mmdet3d", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True)
    i = sub.add_parser("infos", help="write vod_infos_<split>.pkl (tj4d_infos_<split>.pkl) from the release")
    i.add_argument("--dataset", choices=("vod", "tj4d"), default="vod",
                   help="vod: View-of-Delft (default); tj4d: TJ4DRadSet (root holding training/ and ImageSets/)")
    i.add_argument("--root", required=True, help="the release root (VoD: holding radar, radar_5frames, lidar)")
    i.add_argument("--sensor", default="radar_5frames", help="VoD's radar folder (default radar_5frames)")
    i.add_argument("--splits", nargs="+", default=["train", "val"], help="split files (default train val)")
    i.add_argument("--out-dir", default=None, help="default <root>/<sensor> (VoD), <root> (TJ4DRadSet)")
    a = sub.add_parser("convert-authors",
                       help="the MSSF authors' MSSF-PP checkpoint into an mmdet3d config built as theirs")
    a.add_argument("checkpoint", help="their .pth (EricLiuhhh/MSSF, MSSF-PP)")
    a.add_argument("--config", required=True, help="a config configured as theirs (mssf_pointpillars_vod_authors.py)")
    a.add_argument("--out", required=True, help="the converted checkpoint to write (read by test / load_from)")
    for name in ("train", "test"):
        s = sub.add_parser(name, help=f"{name} a config with mmengine's Runner")
        s.add_argument("config")
        if name == "test":
            s.add_argument("checkpoint")
        s.add_argument("--work-dir", default=None, help="default work_dirs/<config name>")
        if name == "train":
            s.add_argument("--resume", nargs="?", const="auto", default=None,
                           help="resume from the latest checkpoint of the work dir, or from the given one")
        s.add_argument("--data-root", default=None, help="the dataset folder holding the info files (overrides the config's)")
        s.add_argument("--image-scale", nargs=2, type=int, default=None, metavar=("W", "H"),
                       help="the network's image size (every pipeline's Resize; default the config's)")
        if name == "train":
            s.add_argument("--image-checkpoint", default=None, metavar="PATH",
                           help="load the image branch from an mmdet checkpoint with backbone.* / neck.* weights "
                                "(the paper's HTC R-50-FPN): both modules' init_cfg")
            s.add_argument("--iters", type=int, default=None, metavar="N",
                           help="train N iterations instead of the config's epochs: the learning-rate schedule "
                                "compressed into them, validation and a checkpoint (iter_N.pth) at the end, a log "
                                "line every min(N, the config's interval) iterations")
        s.add_argument("--cfg-options", nargs="+", default=None, metavar="KEY=VALUE",
                       help="override config values (mmengine DictAction syntax)")
    return p


def set_data_root(cfg, data_root: str) -> None:
    """Point every dataloader and the evaluators' ``ann_file`` (``VoDMetric``, ``TJ4DMetric``) at ``data_root``
    (the folder holding the info files)."""
    root = str(data_root).rstrip("/") + "/"
    for key in ("train_dataloader", "val_dataloader", "test_dataloader"):
        if cfg.get(key) is not None:
            cfg[key].dataset.data_root = root
    for key in ("val_evaluator", "test_evaluator"):
        ev = cfg.get(key)
        if ev is not None and ev.get("ann_file") is not None:
            ev.ann_file = root + Path(ev.ann_file).name


def set_image_scale(cfg, scale) -> None:
    """Set the ``Resize`` scale of every pipeline (the network's image size)."""
    for key in ("train_dataloader", "val_dataloader", "test_dataloader"):
        if cfg.get(key) is not None:
            for step in cfg[key].dataset.pipeline:
                if step.get("type") == "Resize":
                    step.scale = tuple(scale)


def set_image_checkpoint(cfg, path: str) -> None:
    """``--image-checkpoint``: ``init_cfg=dict(type="Pretrained", checkpoint=path, prefix=...)`` of the image
    backbone (``backbone.``) and neck (``neck.``), the key names of mmdet's HTC / Faster R-CNN checkpoints."""
    model = cfg.model
    missing = [k for k in ("img_backbone", "img_neck") if model.get(k) is None]
    if missing:
        raise MSSFError(f"--image-checkpoint: the config's model has no {' / '.join(missing)} (a radar-only model?)")
    model.img_backbone.init_cfg = dict(type="Pretrained", checkpoint=str(path), prefix="backbone.")
    model.img_neck.init_cfg = dict(type="Pretrained", checkpoint=str(path), prefix="neck.")


def _pretrained(init_cfg) -> bool:
    cfgs = init_cfg if isinstance(init_cfg, (list, tuple)) else [init_cfg]
    return any(isinstance(c, dict) and c.get("type") == "Pretrained" for c in cfgs)


def check_image_weights_given(cfg) -> None:
    """Before anything is built: an ``MSSFDetector`` whose image branch is frozen (``freeze_img``, default True)
    and that no ``init_cfg`` (the modules' or the model's), ``load_from`` or ``resume`` would load is refused,
    with the error the model itself raises at its first training step (``check_image_weights``)."""
    model = cfg.model
    if model.get("type") != "MSSFDetector" or not model.get("freeze_img", True):
        return
    if cfg.get("load_from") or cfg.get("resume") or _pretrained(model.get("init_cfg")):
        return  # the model's own check at the first step says whether the image weights were in there
    parts = {k: "no init_cfg=dict(type='Pretrained', ...), no load_from" for k in ("img_backbone", "img_neck")
             if model.get(k) is not None and not _pretrained(model[k].get("init_cfg"))}
    if parts:
        from .detector import frozen_image_message

        raise MSSFError(frozen_image_message(parts, True))


def set_iterations(cfg, iters: int) -> None:
    """Bound training to ``iters`` iterations (``--iters``): what "the iteration count" of a run means.

    * ``train_cfg``: ``IterBasedTrainLoop(max_iters=iters, val_interval=iters)``: one validation, at the end;
    * ``param_scheduler``: each epoch-based scheduler's ``[begin, end)`` mapped from ``[0, max_epochs]`` onto
      ``[0, iters]`` iterations (the one-cycle schedule runs whole, compressed); iteration-based ones unchanged;
    * ``default_hooks.checkpoint``: by iteration, every ``iters`` (``iter_<iters>.pth``, what ``test`` and
      ``--resume`` read); ``default_hooks.logger.interval`` and ``log_processor.window_size`` at most ``iters``
      (one line per iteration for short runs), ``log_processor.by_epoch=False``.

    Batch size, workers, the model and the data pipeline stay as the config has them.
    """
    if not isinstance(iters, int) or isinstance(iters, bool) or iters < 1:
        raise ValueError(f"iters: expected a positive integer, got {iters!r}")
    max_epochs = cfg.train_cfg.get("max_epochs")
    cfg.train_cfg = dict(type="IterBasedTrainLoop", max_iters=iters, val_interval=iters)
    schedulers = cfg.get("param_scheduler") or []
    for sched in (schedulers if isinstance(schedulers, list) else [schedulers]):
        if not sched.get("by_epoch", True):
            continue
        if not max_epochs:
            raise ValueError("iters: the config's param_scheduler is by epoch but train_cfg has no max_epochs "
                             "to map it from")
        begin, end = sched.get("begin", 0), min(sched.get("end", max_epochs), max_epochs)
        sched.begin = round(begin * iters / max_epochs)
        sched.end = max(round(end * iters / max_epochs), sched.begin + 1)
        sched.by_epoch = False
        sched.pop("convert_to_iter_based", None)
    hooks = cfg.default_hooks
    hooks.checkpoint = dict(hooks.get("checkpoint", {}), by_epoch=False, interval=iters)
    if hooks.get("logger") is not None:
        hooks.logger.interval = min(int(hooks.logger.get("interval", 50)), iters)
    cfg.log_processor = dict(cfg.get("log_processor", {}), by_epoch=False,
                             window_size=min(int(cfg.get("log_processor", {}).get("window_size", 10)), iters))


def release_workers(runner) -> None:
    """Stop the data loaders' worker processes of ``runner``'s loops now.

    The shipped configs keep their workers (``persistent_workers=True``); left to garbage collection (or to
    interpreter exit) torch's loader waits up to 5 s per worker for them to stop: 7 to 27 s measured after a
    2-iteration run on a loaded 2-core machine, against 0.5 s when stopped here (after the run, nothing lost).
    """
    for name in ("_train_loop", "_val_loop", "_test_loop"):
        loop = getattr(runner, name, None)
        loader = getattr(loop, "dataloader", None)
        it = getattr(loader, "_iterator", None)
        if it is not None and hasattr(it, "_shutdown_workers"):
            it._shutdown_workers()
            loader._iterator = None


def load_config(config: str, work_dir: Optional[str] = None, cfg_options: Optional[List[str]] = None,
                data_root: Optional[str] = None):
    from mmengine.config import Config, DictAction

    cfg = Config.fromfile(config)
    if cfg_options:
        ns = argparse.Namespace()
        DictAction(option_strings=["--cfg-options"], dest="cfg_options")(None, ns, cfg_options)
        cfg.merge_from_dict(ns.cfg_options)
    if data_root is not None:
        set_data_root(cfg, data_root)
    cfg.work_dir = work_dir or cfg.get("work_dir") or str(Path("work_dirs") / Path(config).stem)
    return cfg


def main(argv: Optional[List[str]] = None) -> int:
    args = _parser().parse_args(argv)
    if args.command == "infos":
        from .infos import create_tj4d_infos, create_vod_infos

        written = create_tj4d_infos(args.root, args.splits, args.out_dir) if args.dataset == "tj4d" else \
            create_vod_infos(args.root, args.sensor, args.splits, args.out_dir)
        for split, path in written.items():
            print(f"{split}: {path}")
        return 0
    if args.command == "convert-authors":
        from .authors_checkpoint import run

        return run(args.checkpoint, args.config, args.out)
    from mmengine.registry import init_default_scope
    from mmengine.runner import Runner

    cfg = load_config(args.config, args.work_dir, args.cfg_options, args.data_root)
    if args.image_scale is not None:
        set_image_scale(cfg, args.image_scale)
    if getattr(args, "iters", None) is not None:
        set_iterations(cfg, args.iters)
    init_default_scope(cfg.get("default_scope", "mmdet3d"))
    from .checkpoints import weights_only_checkpoints

    if args.command == "train":
        if args.image_checkpoint is not None:
            set_image_checkpoint(cfg, args.image_checkpoint)
        if args.resume == "auto":
            cfg.resume, cfg.load_from = True, None
        elif args.resume is not None:
            cfg.resume, cfg.load_from = True, args.resume
        check_image_weights_given(cfg)
        runner = Runner.from_cfg(cfg)
        with weights_only_checkpoints():
            runner.train()
    else:
        cfg.load_from = args.checkpoint
        runner = Runner.from_cfg(cfg)
        with weights_only_checkpoints():
            runner.test()
    release_workers(runner)
    return 0
