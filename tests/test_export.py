"""``torch.export`` of the fusion modules (voxel count a dynamic dimension) and ONNX of a fusion block,
checked on three voxel counts against the eager modules (the default CPU plans: an independent path).

The whole MSSF-PointPillars detector goes through ONNX in tests/examples/models/test_export_onnx.py.
"""

import pytest
import torch

from mssf_blocks import torch_versions as _compat
from mssf_blocks import (
    MSDFF,
    SFF,
    FusionBlock,
    FusionInputs,
    PillarLift,
    QueryInit,
    SemanticGuidedHead,
    SparseVoxels,
)
from mssf_blocks.functional.deform import bag as deform_bag
from mssf_blocks.geometry import CentroidProjection

pytestmark = pytest.mark.usefixtures("one_thread")

RANGE = (0.0, -4.0, -1.0, 8.0, 4.0, 1.0)
L2I = torch.tensor([[[0.0, -8.0, 0.0, 32.0], [0.0, 0.0, -8.0, 16.0], [1.0, 0.0, 0.0, 1.0]]])
FEATS = [torch.randn(1, 8, 24, 32, generator=torch.Generator().manual_seed(0)),
         torch.randn(1, 8, 12, 16, generator=torch.Generator().manual_seed(1))]
BEV = torch.randn(1, 16, 16, 16, generator=torch.Generator().manual_seed(2))
COUNTS = (30, 12, 77)  # the first one is the example input of the export


def _scene(n, seed):
    g = torch.Generator().manual_seed(seed)
    idx = torch.randperm(4 * 16 * 16, generator=g)[:n]
    coords = torch.stack([torch.zeros(n, dtype=torch.long), idx // 256, idx // 16 % 16, idx % 16], 1).int()
    vox = SparseVoxels(torch.randn(n, 16, generator=g), coords, (4, 16, 16), 1, voxel_size=(0.5, 0.5, 0.5), point_range_min=RANGE[:3])
    pts = torch.rand(3 * n, 3, generator=g) * torch.tensor([8.5, 8.0, 2.0]) + torch.tensor(RANGE[:3])
    uv = torch.rand(n, 1, 2, generator=g) * 1.2 - 0.1
    valid = (uv >= 0).all(-1) & (uv <= 1).all(-1)
    proj = CentroidProjection(uv, valid.float(), valid, torch.zeros(n, 3), valid[:, 0], vox.batch_index)
    return vox, FusionInputs(FEATS, L2I, (48, 64), pts, torch.zeros(3 * n, dtype=torch.long)), proj


# torch.export with dynamic shapes needs a newer torch than the library's floor (mssf_blocks.torch_versions)
NO_EXPORT = _compat.missing("export_dynamic_shapes")
NO_ONNX_DYNAMO = NO_EXPORT or _compat.missing("onnx_dynamo")
if NO_EXPORT is None:
    from torch.export import Dim

    N, P = Dim("N", min=2), Dim("P", min=2)
else:
    N = P = None
VOXELS = [{0: N}, {0: N}]  # SparseVoxels: features, coords (SparseVoxels.PYTREE_FIELDS)
INPUTS = [[None, None], None, {0: P}, {0: P}, None]  # FusionInputs: levels, lidar2img, points, points_batch, p2s
PROJ = [{0: N}] * 6  # CentroidProjection: uv, depth, valid, centroid, has_points, batch_index


def _case(name):
    torch.manual_seed(0)
    if name == "SFF":
        return SFF([8, 8], 16), lambda v, i, p: (FEATS, p), ([None, None], PROJ)
    if name == "MSDFF":
        return (MSDFF(8, 16, num_heads=2, num_levels=2, num_points=2), lambda v, i, p: (v.features, FEATS, p),
                ({0: N}, [None, None], PROJ))
    if name == "QueryInit":
        return (QueryInit(16, 8, 16, RANGE), lambda v, i, p: (v.features, v.features[:, :8].clone(), v.voxel_centers()),
                ({0: N}, {0: N}, {0: N}))
    if name == "FusionBlock":
        block = FusionBlock(MSDFF(8, 16, num_heads=2, num_levels=2, num_points=2), query_init=QueryInit(16, 8, 16, RANGE))
        return block, lambda v, i, p: (v, i), (VOXELS, INPUTS)
    if name == "SemanticGuidedHead":
        return SemanticGuidedHead(16, hidden=(8,)), lambda v, i, p: (v,), (VOXELS,)
    if name == "PillarLift":
        return PillarLift(16, 4), lambda v, i, p: (BEV, v), (None, VOXELS)
    raise KeyError(name)


def _leaves(out):
    return [t for t in torch.utils._pytree.tree_leaves(out) if isinstance(t, torch.Tensor)]


@pytest.mark.skipif(NO_EXPORT is not None, reason=str(NO_EXPORT))
@pytest.mark.parametrize("name", ["SFF", "MSDFF", "MSDFF_blocks", "QueryInit", "FusionBlock", "SemanticGuidedHead",
                                  "PillarLift"])
def test_torch_export_with_dynamic_voxel_count(name, monkeypatch):
    """Every block exported once with a symbolic voxel count, then run at other counts; "MSDFF_blocks": MSDFF's
    static sampling planned in 4 blocks of queries (its block size made small), which must hold for any count,
    the smallest (2) included."""
    counts = COUNTS
    if name == "MSDFF_blocks":
        name, counts = "MSDFF", COUNTS + (2, 3)
        # (a symbolic count is planned as bag.STATIC_PLAN_QUERIES queries of M = 2 x C = 8 float32 samples)
        monkeypatch.setattr(deform_bag, "_STATIC_BLOCK_BYTES", deform_bag.STATIC_PLAN_QUERIES * 2 * 8 * 4 // 4)
        assert deform_bag.static_blocks(deform_bag.STATIC_PLAN_QUERIES, 2, 8, 4) == 4
    mod, make_args, dynamic = _case(name)
    mod.eval()
    example = make_args(*_scene(COUNTS[0], 0))
    ep = torch.export.export(mod, example, dynamic_shapes=dynamic)
    if counts is not COUNTS:  # one bag per level and block
        bags = [nd for nd in ep.graph.nodes if nd.op == "call_function" and "embedding_bag" in str(nd.target)]
        assert len(bags) == 4 * 2
    exported = ep.module()
    for n in counts:
        args = make_args(*_scene(n, n))
        got, want = _leaves(exported(*args)), _leaves(mod(*args))
        assert len(got) == len(want) and got[0].shape[0] == n
        for a, e in zip(got, want):
            torch.testing.assert_close(a, e, atol=1e-5, rtol=1e-5)


def test_sparse_voxels_round_trip_through_pytree():
    vox = _scene(5, 0)[0]
    leaves, spec = torch.utils._pytree.tree_flatten(vox)
    assert [id(t) for t in leaves] == [id(vox.features), id(vox.coords)]
    back = torch.utils._pytree.tree_unflatten(leaves, spec)
    assert isinstance(back, SparseVoxels) and back.spatial_shape == vox.spatial_shape and back.stride == vox.stride
    assert SparseVoxels.PYTREE_FIELDS == ("features", "coords")


@pytest.mark.skipif(NO_ONNX_DYNAMO is not None, reason=str(NO_ONNX_DYNAMO))
def test_onnx_export_of_fusion_block_runs_in_onnxruntime(tmp_path):
    ort = pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    block = FusionBlock(SFF([8, 8], 16)).eval()
    vox, inputs, _ = _scene(COUNTS[0], 0)
    # the names docs/deployment.md passes (2 levels here): without them the exporter's are unstable
    input_names = ["voxel_features", "voxel_coords", "image_level_0", "image_level_1", "lidar2img", "points",
                   "points_batch"]
    program = torch.onnx.export(block, (vox, inputs), dynamic_shapes=(VOXELS, INPUTS), dynamo=True,
                                opset_version=18, verbose=False, input_names=input_names,
                                output_names=["fused_features", "fused_coords"])
    path = tmp_path / "block.onnx"
    program.save(str(path))
    import onnx

    model = onnx.load(str(path))

    def dims(v):
        return [d.dim_param or d.dim_value for d in v.type.tensor_type.shape.dim]

    assert [(v.name, dims(v)) for v in model.graph.input] == [
        ("voxel_features", ["N", 16]), ("voxel_coords", ["N", 4]), ("image_level_0", [1, 8, 24, 32]),
        ("image_level_1", [1, 8, 12, 16]), ("lidar2img", [1, 3, 4]), ("points", ["P", 3]), ("points_batch", ["P"])]
    assert [(v.name, dims(v)) for v in model.graph.output] == [("fused_features", ["N", 16]), ("fused_coords", ["N", 4])]
    assert "GridSample" in {node.op_type for node in model.graph.node}  # what TensorRT needs (opset >= 16)
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    names = [i.name for i in session.get_inputs()]
    for n in COUNTS:
        v, i, _ = _scene(n, n)
        flat = [v.features, v.coords, *i.image_features, i.lidar2img, i.points, i.points_batch]
        out = session.run(None, {k: t.numpy() for k, t in zip(names, flat)})
        want = block(v, i).features.detach()
        assert out[0].shape == (n, 16)
        assert float((torch.from_numpy(out[0]) - want).abs().max()) <= 1e-4


# Operators of the TensorRT ONNX parser (onnx-tensorrt's operator support list) that the static-shape path
# may emit; no Loop / Sequence ops, no custom domains.
TENSORRT_OPS = {
    "Abs", "Add", "And", "ArgMax", "BatchNormalization", "Cast", "Clip", "Concat", "Constant", "ConstantOfShape",
    "Conv", "CumSum", "Div", "Einsum", "Equal", "Exp", "Expand", "Floor", "Gather", "GatherElements", "GatherND",
    "Gemm", "Greater", "GreaterOrEqual", "GridSample", "Identity", "Less", "LessOrEqual", "MatMul", "Max", "Min",
    "Mul", "Neg", "Not", "Or", "Pow", "Range", "Reciprocal", "ReduceMax", "ReduceMean", "ReduceSum", "Relu",
    "ReduceMin", "Reshape", "ScatterElements", "ScatterND", "Shape", "Sigmoid", "Slice", "Softmax", "Split", "Sqrt", "Squeeze",
    "Sub", "Tile", "TopK", "Transpose", "Unsqueeze", "Where",
}


@pytest.mark.skipif(NO_ONNX_DYNAMO is not None, reason=str(NO_ONNX_DYNAMO))
@pytest.mark.parametrize("name,opset,form", [("MSDFF", 17, "planned"), ("MSDFF", 18, "planned"),
                                            ("FusionBlock", 17, "planned"), ("FusionBlock", 18, "planned"),
                                            ("MSDFF", 18, "raw"), ("MSDFF", 17, "mixed")])
def test_onnx_export_of_msdff_has_tensorrt_operators_and_matches_onnxruntime(name, opset, form, tmp_path, monkeypatch):
    # The static-shape MSDFF under ONNX (grid.sample_project_onnx: per level a 1 x 1 Conv and GridSample per
    # head, or a GridSample of the raw level projected after with a MatMul; no embedding_bag Loop), the voxel
    # count a dynamic axis, checked in onnxruntime at two other counts against the eager module (the default
    # CPU plans, an independent path). "planned": the plan's choice at these sizes; "raw": every level
    # sample-first; "mixed": the finer level sample-first, the coarser project-first.
    ort = pytest.importorskip("onnxruntime")
    pytest.importorskip("onnxscript")
    import onnx

    from mssf_blocks.functional.deform import grid as deform_grid

    if form != "planned":
        widths = {lvl.shape[-1] for lvl in _scene(COUNTS[0], 0)[1].image_features}
        monkeypatch.setattr(deform_grid, "_raw_pays",
                            lambda level, *a: form == "raw" or level.shape[-1] == max(widths))

    mod, make_args, dynamic = _case(name)
    mod.eval()
    with torch.no_grad():
        for sub in mod.modules():  # (value_proj's bias starts at zero: a bias term dropped would go unseen)
            if isinstance(sub, MSDFF):
                sub.value_proj.bias.normal_(generator=torch.Generator().manual_seed(5))
        program = torch.onnx.export(mod, make_args(*_scene(COUNTS[0], 0)), dynamic_shapes=dynamic, dynamo=True,
                                    opset_version=opset, verbose=False)
    path = tmp_path / f"{name}.onnx"
    program.save(str(path))
    model = onnx.load(str(path))
    assert model.opset_import[0].version == opset
    ops = {node.op_type for node in model.graph.node}
    assert ops <= TENSORRT_OPS, sorted(ops - TENSORRT_OPS)
    assert "GridSample" in ops and not model.functions
    assert ("Conv" in ops) is (form != "raw")  # (the planned form at these sizes: every level project-first)
    assert all(node.domain in ("", "ai.onnx") for node in model.graph.node)
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    names = [i.name for i in session.get_inputs()]
    for n in COUNTS[1:]:
        args = make_args(*_scene(n, n))
        flat = _leaves(args)
        assert len(flat) == len(names)
        out = session.run(None, {k: t.numpy() for k, t in zip(names, flat)})
        with torch.no_grad():
            want = _leaves(mod(*args))[0]
        assert out[0].shape[0] == n
        assert float((torch.from_numpy(out[0]) - want).abs().max()) <= 1e-4
