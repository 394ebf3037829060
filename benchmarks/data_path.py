"""Measurement: the way one FusionBlock forward takes through the library's files (issue 43's figure).

Not a timing: a count of how often the call moves between the modules of ``src/mssf_blocks/``, so a
layout change can show before and after that the way got shorter. The set-up is the README's drop-in
example (a strided ``SparseConv3d`` + BN + ReLU, one ``SubMConv3d`` residual stage, two samples of 100
points, four 256-channel image levels of a 320 x 512 image, one camera) in six variants: SFF, MSDFF,
MSDFF with ``QueryInit``, each fed a :class:`~mssf_blocks.SparseVoxels` (the block built without the
grid) and a raw spconv ``SparseConvTensor`` (the block built with its ``VoxelGrid``, as in the README;
before issue 43's redesign: with ``voxel_size``, ``point_range_min`` and ``in_stride``). Each variant runs one untraced forward first
(lazy imports and one-time set-up are not the path), then one traced forward, on the CPU, one thread,
``torch.no_grad``, geometry checks at their CPU default (on: they are part of the path).

What is counted (keep it so, or the before/after figures do not compare):

* **frame**: a Python frame whose code file lies under ``src/mssf_blocks/`` (as imported); frames of
  torch, spconv, the standard library, dataclass-generated ``__init__`` s (file ``<string>``) and this
  script are not ours. Events come from ``sys.setprofile`` (``call`` and ``return`` of Python frames;
  a frame left by an exception gives ``return`` too; ``c_call`` events are ignored).
* **current file** (mode ``all``): the file of the innermost *our* frame on the stack. It changes when
  one of our frames is entered (its file) or returns (the file of the nearest our frame below it, or
  none when the traced call is left). Torch or spconv code in between does not change it, so a return
  through them, or a callback from them into our files, is seen as the move between our files it is.
* **current file** (mode ``data``, "followed as data"): the same with only *data frames*: the file of
  the innermost data frame on the stack. A frame is a data frame when, at its ``call`` event, one of its
  arguments (``co_varnames`` up to the positional, keyword-only, ``*args`` and ``**kwargs`` ones,
  ``self`` included) is (a) a voxel holder: a ``SparseVoxels`` or an spconv ``SparseConvTensor``
  (type name ``SparseConvTensor``); (b) a voxel tensor: a tensor that is, by identity, the
  ``features``, ``coords`` or ``indices`` of a voxel holder met earlier in the traced call (the input,
  the downsampled tensor, the fused voxels: each holder registers its tensors when first seen); or
  (c) a list, tuple or dict whose elements / values, or an object whose ``__dict__`` values, include
  (a) or (b), one level deep. Derived tensors (a query built from the features, centroids, sampled
  image features) are not followed: the voxel data is what the holders carry.
* **stay**: a run of consecutive identical current files (none ends a run); **files entered**: the
  distinct files among the stays; **returns**: stays whose file an earlier stay already had
  (= stays - files entered); **visits**: stays per file.

Issue 43 quoted 13 stays in 5 files, 8 returns, for a hand-followed path on an earlier main; its method
was not recorded, so that figure does not compare with these. The numbers measured with this script
are in docs/performance.md ("The data's way through a fusion block").

Usage: ``python benchmarks/data_path.py [--json PATH] [--sequence] [--variants sff-voxels,...]``
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from typing import Any, Callable, Dict, Iterable, List, Optional, Sequence

import torch

__all__ = ["count_stays", "PathTracer", "voxel_tensors", "build_variant", "measure_variant", "VARIANTS"]

VARIANTS = ("sff-voxels", "sff-spconv", "msdff-voxels", "msdff-spconv", "msdff_qi-voxels", "msdff_qi-spconv")


def count_stays(sequence: Iterable[Optional[str]]) -> Dict[str, Any]:
    """Stays, files entered, returns and visits of a sequence of current files (``None``: outside)."""
    stays: List[str] = []
    previous = None
    for name in sequence:
        if name is not None and name != previous:
            stays.append(name)
        previous = name
    visits: Dict[str, int] = {}
    returns = 0
    for name in stays:
        returns += name in visits
        visits[name] = visits.get(name, 0) + 1
    return {"stays": stays, "num_stays": len(stays), "files_entered": len(visits), "returns": returns,
            "visits": visits}


def voxel_tensors(obj: Any) -> Optional[List[Any]]:
    """The tensors a voxel holder carries (``SparseVoxels`` or spconv tensor), or ``None`` for others."""
    from mssf_blocks import SparseVoxels

    if isinstance(obj, SparseVoxels):
        # (``self`` of its own ``__init__`` holds no tensor yet: a holder from the moment it has them)
        return [t for t in (getattr(obj, "features", None), getattr(obj, "coords", None)) if t is not None]
    if type(obj).__name__ == "SparseConvTensor":
        return [obj.features, obj.indices]
    return None


class PathTracer:
    """Records the current file (module docstring) while active, via ``sys.setprofile``.

    ``root``: the package folder whose files count; ``holder``: ``None`` for mode ``all``, else a function
    giving the tensors an argument holds when it is a voxel holder (``None`` otherwise), for mode ``data``.
    ``sequence`` holds the current file (relative to ``root``, ``/``-separated) after each change.
    """

    def __init__(self, root: str, holder: Optional[Callable[[Any], Optional[List[Any]]]] = None) -> None:
        self.root = os.path.realpath(root) + os.sep
        self.holder = holder
        self.sequence: List[Optional[str]] = []
        self._files: Dict[Any, Optional[str]] = {}  # code object -> relative file, None when not ours
        self._data_frames: set = set()  # ids of live data frames (a live frame's id is unique)
        self._registered: Dict[int, Any] = {}  # id -> voxel tensor, kept alive so that no id is reused
        self._current: Optional[str] = None

    def _file(self, code: Any) -> Optional[str]:
        if code not in self._files:
            path = os.path.realpath(code.co_filename)
            self._files[code] = path[len(self.root):].replace(os.sep, "/") if path.startswith(self.root) else None
        return self._files[code]

    def _is_data(self, value: Any, depth: int = 0) -> bool:
        if id(value) in self._registered:
            return True
        held = self.holder(value)
        if held is not None:
            for t in held:
                self._registered.setdefault(id(t), t)
            return True
        if depth:
            return False
        if isinstance(value, (list, tuple)):
            inner = value
        elif isinstance(value, dict):
            inner = list(value.values())
        elif hasattr(value, "__dict__") and not isinstance(value, type):
            inner = list(vars(value).values())
        else:
            return False
        found = False
        for v in inner:  # (all of them, not the first only: every holder registers its tensors)
            found = self._is_data(v, 1) or found
        return found

    def _receives_data(self, frame: Any) -> bool:
        code = frame.f_code
        n = code.co_argcount + code.co_kwonlyargcount + bool(code.co_flags & 0x04) + bool(code.co_flags & 0x08)
        local = frame.f_locals
        found = False
        for name in code.co_varnames[:n]:
            if name in local:
                found = self._is_data(local[name]) or found
        return found

    def _counts(self, frame: Any) -> bool:
        return self.holder is None or id(frame) in self._data_frames

    def _set(self, name: Optional[str]) -> None:
        if name != self._current:
            self._current = name
            self.sequence.append(name)

    def _profile(self, frame: Any, event: str, arg: Any) -> None:
        if event == "call":
            name = self._file(frame.f_code)
            if name is None:
                return
            if self.holder is not None:
                if not self._receives_data(frame):
                    self._data_frames.discard(id(frame))  # (an abandoned generator's id, reused)
                    return
                self._data_frames.add(id(frame))
            self._set(name)
        elif event == "return":
            if self._file(frame.f_code) is None or not self._counts(frame):
                return
            self._data_frames.discard(id(frame))
            below = frame.f_back
            while below is not None and (self._file(below.f_code) is None or not self._counts(below)):
                below = below.f_back
            self._set(None if below is None else self._file(below.f_code))

    def __enter__(self) -> "PathTracer":
        sys.setprofile(self._profile)
        return self

    def __exit__(self, *exc: Any) -> None:
        sys.setprofile(None)
        self._set(None)


# -- the README's set-up ----------------------------------------------------------------------------
GRID = dict(voxel_size=(0.05, 0.05, 0.125), point_range_min=(0.0, -25.6, -3.0))


def build_variant(name: str, seed: int = 0):
    """``(block, x, inputs)`` of the README's drop-in example for one of :data:`VARIANTS`."""
    import spconv.pytorch as spconv
    from torch import nn

    from mssf_blocks import MSDFF, SFF, FusionBlock, FusionInputs, SparseVoxels, VoxelGrid

    fusion_kind, input_kind = name.split("-")
    torch.manual_seed(seed)
    down = spconv.SparseSequential(
        spconv.SparseConv3d(16, 32, 3, stride=2, padding=1, bias=False, indice_key="spconv2"),
        nn.BatchNorm1d(32), nn.ReLU())
    res = spconv.SparseSequential(
        spconv.SubMConv3d(32, 32, 3, padding=1, bias=False, indice_key="subm2"), nn.BatchNorm1d(32), nn.ReLU())
    if fusion_kind == "sff":
        fusion = SFF([256] * 4, 32)
    else:
        fusion = MSDFF(256, 32, num_heads=8, num_levels=4, num_points=4)
    grid = VoxelGrid(GRID["voxel_size"], GRID["point_range_min"] + (51.2, 25.6, 2.0))
    # (the grid is the block's for an spconv input and for its own QueryInit; SparseVoxels carry theirs)
    block = FusionBlock(fusion, grid if input_kind == "spconv" or fusion_kind == "msdff_qi" else None,
                        downsample=down, blocks=res, query_init=fusion_kind == "msdff_qi").eval()

    B, H, W = 2, 320, 512
    xyz = torch.rand(B * 100, 3) * torch.tensor([25.0, 10.0, 3.0]) + torch.tensor([5.0, -5.0, -2.5])
    points = torch.cat([torch.arange(B).repeat_interleave(100)[:, None].float(), xyz], 1)
    cells = ((xyz - torch.tensor(GRID["point_range_min"])) / torch.tensor(GRID["voxel_size"])).floor()
    coords = torch.unique(torch.cat([points[:, :1], cells.flip(1)], 1), dim=0).int()
    features = torch.randn(len(coords), 16)
    if input_kind == "spconv":
        x = spconv.SparseConvTensor(features, coords, [40, 1024, 1024], B)
    else:
        x = SparseVoxels(features, coords, grid.spatial_shape, B, grid=grid)
    fpn = [torch.randn(B, 256, H // s, W // s) for s in (4, 8, 16, 32)]
    k = torch.tensor([[200.0, 0, W / 2], [0, 200, H / 2], [0, 0, 1]])
    lidar2img = (k @ torch.tensor([[0.0, -1, 0, 0], [0, 0, -1, 0], [1, 0, 0, 0]])).expand(B, 1, 3, 4)
    inputs = FusionInputs(image_features=fpn, lidar2img=lidar2img, image_size=(H, W),
                          points=points[:, 1:4], points_batch=points[:, 0].long())
    return block, x, inputs


def measure_variant(name: str, root: Optional[str] = None) -> Dict[str, Dict[str, Any]]:
    """Counts of modes ``all`` and ``data`` for one traced forward of variant ``name`` (after one untraced)."""
    import mssf_blocks

    root = root or os.path.dirname(os.path.abspath(mssf_blocks.__file__))
    block, x, inputs = build_variant(name)
    result = {}
    with torch.no_grad():
        block(x, inputs)
        for mode, holder in (("all", None), ("data", voxel_tensors)):
            with PathTracer(root, holder) as tracer:
                block(x, inputs)
            result[mode] = count_stays(tracer.sequence)
    return result


def _visits(counts: Dict[str, Any]) -> str:
    return ", ".join(f"{f} {n}" for f, n in sorted(counts["visits"].items(), key=lambda kv: (-kv[1], kv[0])))


def main(argv: Optional[Sequence[str]] = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", help="write every count and stay sequence to this file")
    ap.add_argument("--sequence", action="store_true", help="print each variant's stay sequences")
    ap.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated, of {', '.join(VARIANTS)}")
    args = ap.parse_args(argv)
    names = [v for v in args.variants.split(",") if v]
    unknown = sorted(set(names) - set(VARIANTS))
    if unknown:
        ap.error(f"--variants: unknown {unknown}; expected some of {list(VARIANTS)}")
    torch.set_num_threads(1)
    results = {name: measure_variant(name) for name in names}
    print("| variant | mode | files entered | stays | returns | visits per file |")
    print("|---|---|---|---|---|---|")
    for name, modes in results.items():
        for mode, c in modes.items():
            print(f"| {name} | {mode} | {c['files_entered']} | {c['num_stays']} | {c['returns']} | {_visits(c)} |")
    if args.sequence:
        for name, modes in results.items():
            for mode, c in modes.items():
                print(f"\n{name} ({mode}): " + " > ".join(c["stays"]))
    if args.json:
        import spconv

        meta = {"python": sys.version.split()[0], "torch": torch.__version__,
                "spconv": getattr(spconv, "__version__", "?"), "definition": "benchmarks/data_path.py docstring"}
        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump({"meta": meta, "variants": results}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
