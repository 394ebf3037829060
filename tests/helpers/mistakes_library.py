"""Cases of the "Common mistakes" table (tests/docs/test_docs_mistakes_table.py): spconv inputs, BatchNorm,
batch sizes and widths (test_foreign_errors' helpers), the converter, ``testing.assert_close``,
``evaluate`` and the triton version (test_triton_version's stand-in for an old triton on a GPU).

Each case runs every mistake its row lists; where a row also says what keeps working, the case asserts it.
"""

from __future__ import annotations

import importlib.util
import sys
import warnings
from pathlib import Path

import pytest
import torch

from mistakes_registry import Outcome, case, outcome

TESTS = Path(__file__).resolve().parents[1]


def _helpers(name: str, folder: str = ""):
    """Another test module's helpers (imported as a plain module; its own tests are not collected here)."""
    path = str(TESTS / folder)
    if path not in sys.path:
        sys.path.append(path)
    return __import__(name)


def _foreign():
    pytest.importorskip("spconv.pytorch")
    return _helpers("test_foreign_errors", "checks")


@case("integer features, int64 indices or zero voxels into spconv")
def _():
    fe = _foreign()
    from mssf_blocks import SparseVoxels
    from mssf_blocks.blocks import FusionBlock
    from mssf_blocks.samplers import SFF
    from mssf_blocks.integrations import _backbones
    from torch import nn

    spconv = fe.spconv
    runs = [lambda make=make: fe.block(SFF([4], 8)).eval()(make(), fe.inputs())  # the six of test_foreign_errors
            for make, _ in fe.SPCONV_CASES.values()]
    bare = FusionBlock(SFF([4], 4), grid=fe.VOXEL_GRID).eval()  # no downsample: the same checks
    biased = spconv.SparseSequential(spconv.SparseConv3d(4, 8, 3, stride=2, padding=1), nn.BatchNorm1d(8))
    net = _backbones.build("VoxelBackBone8x", 4, [0, -25.6, -3, 51.2, 25.6, 2], [0.8, 0.8, 0.125], num_fusion_blocks=0)
    coords = torch.tensor([[0, 1, 2, 3], [0, 2, 3, 4]], dtype=torch.int32)
    runs += [
        lambda: bare(fe._int64_indices(), fe.inputs()),
        lambda: SparseVoxels(torch.ones(0, 4), torch.zeros(0, 4, dtype=torch.int32), (4, 8, 8), 1,
                             **fe.GRID).to_spconv(),
        lambda: fe.block(SFF([4], 8)).eval()(SparseVoxels.from_spconv(fe.sparse(torch.randn(20, 6)), **fe.GRID),
                                             fe.inputs()),  # what a FusionBlock hands its downsample
        lambda: fe.block(SFF([4], 8), blocks=fe.residual(6)).eval()(fe.sparse(torch.randn(20, 4)), fe.inputs()),
        lambda: FusionBlock(SFF([4], 8, norm_layer=None), downsample=biased, grid=fe.VOXEL_GRID).eval()(fe.sparse(torch.randn(20, 4)), fe.inputs()),
        lambda: _backbones.run_dense_layout(net, torch.randn(2, 4, dtype=torch.float64), coords, 1, None),
        lambda: _backbones.run_dense_layout(net, torch.randn(2, 5), coords, 1, None),
    ]
    return outcome(*runs)


@case("one in-image voxel in training mode")
def _():
    fe = _foreign()
    from mssf_blocks import SparseVoxels
    from mssf_blocks.blocks import FusionBlock
    from mssf_blocks.samplers import SFF, QueryInit
    from mssf_blocks.heads import SemanticGuidedHead
    from torch import nn

    one = SparseVoxels(torch.randn(1, 4), torch.tensor([[0, 0, 1, 1]], dtype=torch.int32), (4, 8, 8), 1, **fe.GRID)
    # "a LayerNorm head takes one voxel": accepted
    assert SemanticGuidedHead(4, hidden=(8,), norm_layer=nn.LayerNorm).train()(one)[1].shape == (1,)
    qi = QueryInit(8, 4, 8, (0, 0, 0, 1, 1, 1)).train()
    v8 = SparseVoxels(torch.randn(1, 8), torch.tensor([[0, 0, 2, 2]], dtype=torch.int32), (4, 8, 8), 1, **fe.GRID)
    from mssf_blocks.static_path import static_path

    def static_sff():  # the static path (no row gather), where data checks run (here: the CPU)
        with static_path():
            SFF([4], 6).train()([torch.randn(1, 4, 8, 8)], fe.projection(5, [2]))

    runs = [lambda: SFF([4], 6).train()([torch.randn(1, 4, 8, 8)], fe.projection(5, [2])), static_sff]
    runs += [lambda m=m: fe.msdff(method=m).train()(torch.randn(5, 8), [torch.randn(1, 4, 8, 8)], fe.projection(5, [2]))
             for m in ("auto", "reference", "fast", "grid")]
    runs += [lambda: qi(torch.randn(1, 8), torch.randn(1, 4), torch.rand(1, 3)),
             lambda: FusionBlock(fe.msdff(), query_init=qi, grid=fe.VOXEL_GRID).train()(v8, fe.inputs()),
             lambda: SemanticGuidedHead(4, hidden=(8,)).train()(one)]
    return outcome(*runs)


@case("camera inputs of different batch sizes")
def _():
    fe = _foreign()
    from mssf_blocks.samplers import SFF, FusionInputs

    runs = [lambda: fe.inputs(batch=2, l2i=fe.L2I),
            lambda: fe.inputs(batch=1, l2i=fe.L2I.expand(2, 3, 4), points_to_sensor=torch.eye(4).expand(2, 4, 4)),
            lambda: fe.inputs(batch=2, points_to_sensor=torch.eye(4).expand(3, 4, 4)),
            lambda: fe.inputs(batch=2, levels=[torch.randn(2, 4, 8, 8), torch.randn(3, 4, 4, 4)]),
            lambda: fe.block(SFF([4], 8)).eval()(fe.sparse(torch.randn(20, 4), batch_size=2), fe.inputs(batch=1)),
            lambda: FusionInputs([torch.zeros(2, 4, 8, 8)], fe.L2I.expand(2, 3, 4), [(8, 8), (8, 8)],
                                 torch.zeros(0, 3), torch.zeros(0, dtype=torch.long))]
    if importlib.util.find_spec("mmengine") is not None:  # the mmdet3d encoder's short per-sample lists
        from mssf_blocks.integrations import mmdet3d_plugin

        enc = mmdet3d_plugin.MSSFSparseEncoder(4, [41, 64, 64], [0, -25.6, -3, 51.2, 25.6, 2], [0.8, 0.8, 0.125],
                                               image_channels=[4], msdff_heads=2, msdff_points=1)
        meta = {"lidar2img": torch.eye(4).numpy(), "img_shape": (8, 8), "pad_shape": (8, 8),
                "batch_input_shape": (8, 8)}
        runs.append(lambda: enc(torch.randn(2, 4), torch.tensor([[0, 1, 2, 3], [1, 2, 3, 4]], dtype=torch.int32), 2,
                                points=[torch.rand(3, 4)], img_features=[torch.randn(2, 4, 8, 8)],
                                batch_input_metas=[meta, meta]))
    return outcome(*runs)


@case("a width that differs between a module and its inputs")
def _():
    fe = _foreign()
    from mssf_blocks import SparseVoxels
    from mssf_blocks.blocks import FusionBlock
    from mssf_blocks.samplers import MSDFF, SFF, QueryInit
    from mssf_blocks.heads import SemanticGuidedHead
    from mssf_blocks.lift import PillarLift

    v = SparseVoxels(torch.randn(3, 4), fe.indices(3), (4, 8, 8), 1, **fe.GRID)
    levels = [torch.randn(1, 4, 8, 8), torch.randn(1, 4, 4, 4)]
    qi = QueryInit(8, 4, 8, (0, 0, 0, 1, 1, 1))
    return outcome(
        lambda: fe.block(fe.msdff(embed_dim=16)).eval()(fe.sparse(torch.randn(20, 4)), fe.inputs()),
        lambda: FusionBlock(SFF([4], 6), grid=fe.VOXEL_GRID).eval()(v, fe.inputs()),
        lambda: SFF([4, 6], 8).eval()(levels, fe.projection(3, [0, 1])),
        lambda: MSDFF(6, 8, num_heads=2, num_levels=2, num_points=1).eval()(torch.randn(3, 8), levels,
                                                                           fe.projection(3, [0, 1])),
        lambda: fe.msdff().eval()(torch.randn(3, 4), [torch.randn(1, 4, 8, 8)], fe.projection(3, [0, 1])),
        lambda: qi(torch.randn(3, 6), torch.randn(3, 4), torch.rand(3, 3)),
        lambda: qi(torch.randn(3, 8), torch.randn(3, 5), torch.rand(3, 3)),
        lambda: SemanticGuidedHead(6, hidden=(8,))(v),
        lambda: PillarLift(4, 4)(torch.zeros(1, 5, 8, 8), v),
        lambda: PillarLift(4, 4, raw_channels=3)(torch.zeros(1, 4, 8, 8), v))


@case("converter: a missing tensor")
def _():
    ol = _helpers("test_load_authors_checkpoint", "weights")
    from mssf_blocks.weights import ModuleMap, load_official, official_to_ours
    from mssf_blocks.samplers import QueryInit

    maps = [ModuleMap("query_init", f"{ol.ENC}.query_proj", "", voxel_channels=4)]
    missing = ol._theirs_query_init(4, 6, 4)
    del missing[f"{ol.ENC}.query_proj.1.running_var"]
    qi = QueryInit(4, 6, 4, ol.PCR)
    before = ol._params(qi)
    result = outcome(
        lambda: official_to_ours(missing, maps),
        lambda: load_official(qi, missing, maps),
        lambda: load_official(QueryInit(4, 7, 4, ol.PCR), ol._theirs_query_init(4, 6, 4), maps),  # another width
        lambda: load_official(qi, ol._theirs_query_init(4, 6, 4),
                              [ModuleMap("query_init", f"{ol.ENC}.query_proj", "", voxel_channels=2)]))
    assert all(torch.equal(before[k], t) for k, t in qi.state_dict().items()), "copied before refusing"
    return result


@case("`testing.assert_close` on int / bool tensors")
def _():
    from mssf_blocks.testing import assert_close

    a, m = torch.tensor([1, 2, 3], dtype=torch.int32), torch.tensor([True, False])
    x64 = torch.ones(3, dtype=torch.float64)
    failures = []

    def fails(actual, expected):
        try:
            assert_close(actual, expected)
        except AssertionError as exc:
            failures.append(str(exc))
        else:
            raise AssertionError(f"assert_close accepted {actual} against {expected}")

    def run():
        assert_close(a, a.long())  # the same values in another integer dtype: accepted
        assert_close(m, m.clone())
        assert_close((x64 + 3e-6).float(), x64)  # float32's tolerance, whichever side it is on
        assert_close(x64, (x64 + 3e-6).float())
        fails(a, torch.tensor([1, 2, 4], dtype=torch.int32))  # exact: one off is a failure
        fails(x64, (x64 + 1e-3).float())
    result = outcome(run)
    return Outcome(result.kind, result.messages + failures)


@case("1-based prediction labels")
def _():
    from mssf_examples.evaluation.metrics import evaluate

    boxes = torch.tensor([[10.0, 0, 0, 4, 2, 1.5, 0], [5.0, 2, 0, 1, 1, 1.7, 0]], dtype=torch.float64)
    gt = {"boxes": boxes, "labels": torch.tensor([0, 1])}
    pred = {"boxes": boxes, "scores": torch.tensor([0.9, 0.8]), "labels": torch.tensor([1, 2])}
    return outcome(lambda: evaluate([pred], [gt], ["Car", "Pedestrian"], protocol="exact"))


@case("`KittiObjects` into `evaluate")
def _():
    me = _helpers("test_misuse_eval_cli", "examples/cli")

    def run():
        res = me.evaluate([me.parse_labels(me.LABELS)], [me.parse_labels(me.LABELS)], ["Car", "Pedestrian"],
                          protocol="exact", regions={"entire_area": None})["entire_area"]
        assert res["mAP"]["AP3D_R40"] == pytest.approx(100.0), res["mAP"]  # the boxes matched themselves
    return outcome(run)


def _old_triton(mp):
    """An old triton (2.1) on a device whose table entry is "triton" (test_triton_version's stand-in)."""
    from mssf_blocks.functional.deform import op

    tv = _helpers("test_triton_version", "functional")
    tv.triton_on_a_device(mp)
    mp.setattr(op, "_TRITON_VERSION", (2, 1))
    return tv, op


@case("a GPU with triton older than 3.0")
def _():
    from mssf_blocks.functional.deform import grid

    def run():
        with pytest.MonkeyPatch.context() as mp, warnings.catch_warnings():
            tv, op = _old_triton(mp)
            warnings.simplefilter("error")  # the failure-then-fallback warning (any warning) fails the case
            args = tv._inputs()
            assert torch.equal(op.deform_sample_project(*args, backend="auto"), grid.sample_project(*args))
            assert op._TRITON_FAILURE == [], "the kernels were tried"
    return outcome(run)


@case("forcing `backend=\"triton\"` with a triton older than 3.0")
def _():
    def run():
        with pytest.MonkeyPatch.context() as mp:
            _, op = _old_triton(mp)
            op.resolve_backend("triton", "cpu", torch.float32, 32)
    return outcome(run)
