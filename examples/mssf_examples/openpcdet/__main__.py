"""``python -m mssf_examples.openpcdet``: VoD infos, and OpenPCDet's tools with the MSSF classes registered.

    python -m mssf_examples.openpcdet [--cpu] create_vod_infos CFG [--data_path DIR] [--save_path DIR]
        Write vod_infos_{train,val,trainval}.pkl from the dataset config CFG (DATA_PATH unless --data_path).
    python -m mssf_examples.openpcdet [--cpu] create_tj4d_infos CFG [--data_path DIR] [--save_path DIR]
        The same for TJ4DRadSet: tj4d_infos_{train,val,trainval}.pkl.
    python -m mssf_examples.openpcdet [--cpu] [--pure-torch-nms] SCRIPT.py ARGS...
        register() the MSSF classes, then run OpenPCDet's tools/SCRIPT.py (train.py, test.py) with ARGS,
        from the current folder (OpenPCDet's tools/, where its configs' relative paths resolve).

    --pure-torch-nms  the project's pure-torch rotated NMS / IoU instead of OpenPCDet's CUDA extension
    --cpu             a machine without CUDA: pcdet from its clone without setup.py, stand-ins for what was
                      not built, Tensor.cuda() the identity (mssf_examples.openpcdet.cpu); implies --pure-torch-nms
"""

from __future__ import annotations

import argparse
import runpy
import sys
from pathlib import Path

#: the infos commands: name -> (the dataset's default class names, a sample config)
_INFOS = {"create_vod_infos": (("Car", "Pedestrian", "Cyclist"), "cfgs/dataset_configs/vod_radar5_dataset.yaml"),
          "create_tj4d_infos": (("Car", "Pedestrian", "Cyclist", "Truck"), "cfgs/dataset_configs/tj4d_dataset.yaml")}


def _infos(command: str, argv) -> None:
    classes, sample = _INFOS[command]
    parser = argparse.ArgumentParser(prog=f"python -m mssf_examples.openpcdet {command}")
    parser.add_argument("cfg_file", help=f"the dataset config (e.g. {sample})")
    parser.add_argument("--data_path", default=None, help="the release's folder; default: the config's DATA_PATH")
    parser.add_argument("--save_path", default=None, help="where the .pkl files go; default: the data path")
    parser.add_argument("--workers", type=int, default=4)
    args = parser.parse_args(argv)
    from easydict import EasyDict
    from pcdet.config import cfg_from_yaml_file

    from .tj4d_dataset import create_tj4d_infos
    from .vod_dataset import create_vod_infos

    cfg = cfg_from_yaml_file(args.cfg_file, EasyDict())  # OpenPCDet's reading: _BASE_CONFIG_ resolved
    data_path = Path(args.data_path or cfg.DATA_PATH)
    create = create_tj4d_infos if command == "create_tj4d_infos" else create_vod_infos
    create(cfg, cfg.get("CLASS_NAMES", list(classes)), data_path, Path(args.save_path) if args.save_path else data_path,
           workers=args.workers)


def checkpoint_numpy_globals() -> list:
    """What OpenPCDet's checkpoints hold beyond tensors: numpy scalars (the one-cycle learning rate in the
    optimizer state) and their float / int dtypes."""
    import numpy as np

    try:
        from numpy._core.multiarray import scalar
    except ImportError:  # numpy < 2
        from numpy.core.multiarray import scalar
    kinds = [np.float64, np.float32, np.int64, np.int32, np.bool_]
    return [scalar, np.dtype] + [type(np.dtype(k)) for k in kinds]


def allow_numpy_scalars_in_checkpoints() -> None:
    """torch >= 2.6 loads with ``weights_only=True`` by default and refuses OpenPCDet's numpy scalars in
    ``test.py`` / ``--ckpt``: allow-list exactly :func:`checkpoint_numpy_globals`, nothing else (torch < 2.4
    has no allow-list; before 2.6 :func:`main` restricts OpenPCDet's ``torch.load`` to the same list)."""
    from mssf_blocks import torch_versions as _compat

    _compat.add_safe_globals(checkpoint_numpy_globals())


#: what a refused checkpoint was expected to hold, and what to do instead (the error's words)
_HOLDS = "what OpenPCDet's checkpoints hold (numpy scalars)"
_INSTEAD = "Load checkpoints written by OpenPCDet's train.py, or extract their weights from a file you trust"


def _fresh_openpcdet_cfg() -> None:
    """The tools' scripts merge their YAML into the one ``pcdet.config.cfg``: a second run in the same process
    (``main()`` called from Python) would keep the first config's keys (e.g. MSSF-SECOND's ``MAP_TO_BEV`` in an
    MSSF-VoxelNeXt). Back to what ``pcdet.config`` starts with."""
    import pcdet.config as config

    for key in [k for k in config.cfg if k != "ROOT_DIR"]:
        config.cfg.pop(key)  # EasyDict.pop drops the attribute too (clear() would leave it)
    config.cfg.LOCAL_RANK = 0


def main(argv=None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help"):
        print(__doc__)
        return
    flags = set()
    while argv and argv[0] in ("--cpu", "--pure-torch-nms"):
        flags.add(argv.pop(0))
    if not argv:
        raise SystemExit("expected create_vod_infos, create_tj4d_infos or SCRIPT.py after the options "
                         "(python -m mssf_examples.openpcdet -h)")
    cpu = "--cpu" in flags
    pure = cpu or "--pure-torch-nms" in flags
    if argv[0] in _INFOS:
        if cpu:
            from .cpu import prepare_cpu

            prepare_cpu(Path.cwd())
        _infos(argv[0], argv[1:])
        return
    script = Path(argv[0])
    if not script.is_file():
        raise SystemExit(f"SCRIPT: {script} not found (run from OpenPCDet's tools/ folder)")
    if cpu:
        from .cpu import prepare_cpu

        prepare_cpu(script.resolve().parent)
    from ..training.checkpoint_allow_list import restricted_torch_load
    from . import register
    from .image_module import expect_trained_checkpoint

    register(pure_torch_box_ops=pure)
    # test.py evaluates trained checkpoints and train.py --ckpt resumes one: both hold the image branch's
    # weights, so its pre-trained source file (MODEL.IMAGE_BRANCH.CHECKPOINT) is not needed there
    resumes = any(a == "--ckpt" or a.startswith("--ckpt=") for a in argv[1:])
    expect_trained_checkpoint(script.name == "test.py" or (script.name == "train.py" and resumes))
    allow_numpy_scalars_in_checkpoints()
    _fresh_openpcdet_cfg()
    sys.argv = [str(script)] + argv[1:]
    sys.path.insert(0, str(script.resolve().parent))
    try:
        # torch < 2.6 unpickles OpenPCDet's torch.load(filename, map_location) in full: restrict it to tensors
        # and the numpy scalars (later torch refuses by itself, with the allow-list above)
        with restricted_torch_load(checkpoint_numpy_globals(), _HOLDS, _INSTEAD):
            runpy.run_path(str(script), run_name="__main__")
    finally:
        expect_trained_checkpoint(False)  # for what this process builds next (main() called from Python)


if __name__ == "__main__":
    main()
