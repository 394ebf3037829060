"""SparseVoxels: validation, functional updates, voxel centres and spconv round trip."""

import pytest
import torch

from mssf_blocks import MSSFError, SparseVoxels


def make(n=3, **kw):
    args = dict(
        features=torch.randn(n, 4),
        coords=torch.tensor([[0, 0, 1, 2], [1, 3, 0, 0], [0, 1, 7, 7]][:n], dtype=torch.int32),
        spatial_shape=(4, 8, 8),
        batch_size=2,
        voxel_size=(0.1, 0.2, 0.5),
        point_range_min=(0.0, -0.8, -1.0),
    )
    args.update(kw)
    return SparseVoxels(**args)


def test_voxel_centers_hand_worked():
    # voxel (b=0, z=0, y=1, x=2) at stride 1: x = 2.5*0.1 = 0.25, y = 1.5*0.2 - 0.8 = -0.5, z = 0.5*0.5 - 1 = -0.75
    v = make()
    c = v.voxel_centers(dtype=torch.float64)
    torch.testing.assert_close(c[0], torch.tensor([0.25, -0.5, -0.75], dtype=torch.float64))
    # stride (sz, sy, sx) = (1, 2, 4): voxel (z=3, y=0, x=0): x = 0.5*0.4, y = 0.5*0.4 - 0.8, z = 3.5*0.5 - 1
    v2 = make(stride=(1, 2, 4))
    c2 = v2.voxel_centers(dtype=torch.float64)
    torch.testing.assert_close(c2[1], torch.tensor([0.2, -0.6, 0.75], dtype=torch.float64))


def test_point_range_max_and_metric_size():
    v = make(stride=(2, 2, 2), spatial_shape=(2, 4, 4), coords=torch.zeros(1, 4, dtype=torch.int32), features=torch.zeros(1, 4))
    assert v.metric_voxel_size == pytest.approx((0.2, 0.4, 1.0))
    assert v.point_range_max == pytest.approx((0.8, 0.8, 1.0))


@pytest.mark.parametrize(
    "kwargs, pattern",
    [
        (dict(coords=torch.zeros(3, 4, dtype=torch.int64)), r"coords: expected dtype torch.int32"),
        (dict(coords=torch.zeros(3, 3, dtype=torch.int32)), r"coords: expected shape \(N=3, 4\)|coords: expected shape"),
        (dict(coords=torch.tensor([[0, 0, 0, 8]] * 3, dtype=torch.int32)), r"coords\[:, 3\] \(x index\).*\[0, 8\)"),
        (dict(coords=torch.tensor([[0, 4, 0, 0]] * 3, dtype=torch.int32)), r"coords\[:, 1\] \(z index\)"),
        (dict(coords=torch.tensor([[2, 0, 0, 0]] * 3, dtype=torch.int32)), r"batch index.*batch_size=2"),
        (dict(coords=torch.tensor([[-1, 0, 0, 0]] * 3, dtype=torch.int32)), r"batch index"),
        (dict(features=torch.zeros(2, 4)), r"features: expected shape \(3, \*\), got shape \(2, 4\)"),
        (dict(features=torch.zeros(3, 4, dtype=torch.int32)), r"features: expected a floating-point"),
        (dict(voxel_size=(0.1, float("nan"), 0.1)), r"voxel_size: expected finite"),
        (dict(voxel_size=(0.1, -0.1, 0.1)), r"voxel_size: expected positive"),
        (dict(point_range_min=(0.0, float("inf"), 0.0)), r"point_range_min: expected finite"),
        (dict(spatial_shape=(4, 8)), r"spatial_shape: expected 3 values"),
        (dict(stride=(1, 0, 1)), r"stride: expected positive"),
        (dict(batch_size=0), r"batch_size: expected a positive int"),
    ],
)
def test_validation_errors(kwargs, pattern):
    with pytest.raises(MSSFError, match=pattern):
        make(**kwargs)


def test_error_is_value_error():
    assert issubclass(MSSFError, ValueError)


def test_replace_features_keeps_everything_else():
    v = make()
    f = torch.randn(3, 7)
    w = v.replace(features=f)
    assert w.features is f and w.coords is v.coords and w.stride == v.stride
    assert v.features.shape == (3, 4)  # original untouched
    with pytest.raises(MSSFError, match="features: expected shape"):
        v.replace(features=torch.randn(4, 7))
    with pytest.raises(MSSFError, match="unknown field"):
        v.replace(colour=1)
    with pytest.raises(MSSFError, match="coords"):
        v.replace(coords=torch.tensor([[0, 0, 0, 99]] * 3, dtype=torch.int32))


def test_frozen():
    v = make()
    with pytest.raises(Exception):
        v.features = torch.zeros(3, 4)


spconv = pytest.importorskip("spconv.pytorch")


def test_spconv_round_trip_keeps_index_cache():
    torch.manual_seed(0)
    coords = torch.tensor([[0, 0, 0, 0], [0, 1, 1, 1], [0, 2, 2, 2], [1, 0, 1, 0], [1, 3, 3, 3]], dtype=torch.int32)
    x = spconv.SparseConvTensor(torch.randn(5, 4), coords, [4, 4, 4], 2)
    subm = spconv.SubMConv3d(4, 4, 3, indice_key="subm1", bias=False)
    y = subm(x)  # populates indice_dict["subm1"]
    v = SparseVoxels.from_spconv(y, voxel_size=(0.1, 0.1, 0.2), point_range_min=(0, 0, 0))
    assert torch.equal(v.coords, coords) and v.spatial_shape == (4, 4, 4) and v.batch_size == 2
    v2 = v.replace(features=v.features * 2)
    z = v2.to_spconv()
    assert torch.equal(z.features, y.features * 2)
    assert torch.equal(z.indices, y.indices)
    assert list(z.spatial_shape) == [4, 4, 4] and z.batch_size == 2
    assert "subm1" in z.indice_dict and z.indice_dict["subm1"] is y.indice_dict["subm1"]
    # A later conv with the same key reuses the cached indices and agrees with a fresh computation.
    subm2 = spconv.SubMConv3d(4, 3, 3, indice_key="subm1", bias=False)
    out_cached = subm2(z).features
    fresh = spconv.SparseConvTensor(z.features, z.indices, [4, 4, 4], 2)
    out_fresh = spconv.SubMConv3d(4, 3, 3, bias=False)
    out_fresh.load_state_dict(subm2.state_dict())
    torch.testing.assert_close(out_cached, out_fresh(fresh).features)


def test_to_spconv_without_source_and_coords_change_drops_cache():
    coords = torch.tensor([[0, 0, 0, 0], [0, 1, 1, 1]], dtype=torch.int32)
    x = spconv.SparseConvTensor(torch.randn(2, 4), coords, [2, 2, 2], 1)
    v = SparseVoxels.from_spconv(x, voxel_size=(1, 1, 1), point_range_min=(0, 0, 0))
    moved = v.replace(coords=torch.tensor([[0, 1, 0, 0], [0, 1, 1, 1]], dtype=torch.int32))
    assert moved.spconv_source is None
    t = moved.to_spconv()
    assert torch.equal(t.indices, moved.coords) and t.indice_dict == {}


def test_from_spconv_rejects_other_objects():
    with pytest.raises(MSSFError, match="tensor: expected an spconv SparseConvTensor"):
        SparseVoxels.from_spconv(torch.zeros(3), voxel_size=(1, 1, 1), point_range_min=(0, 0, 0))
