"""Issue 13, items 1-7: autocast-proof projection, input validation that used to pass silently, NaN
pixels that no voxel reads, and the library's one dtype rule (``docs/conventions.md``, "Dtypes").

References: a numpy float64 projection (never the code under test), hand-chosen out-of-grid coordinates,
the same computation with the unread pixel set to zero (an unread pixel cannot change anything), and
the same module fed the explicitly converted input.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from mssf_blocks import MSSFError, SparseVoxels, VoxelCentroidProjector, torch_versions as _compat
from mssf_blocks.blocks import FusionBlock
from mssf_blocks.functional.deform import touched
from mssf_blocks.functional.geometry import project_points, voxel_centroids, voxel_centroids_reference
from mssf_blocks.samplers import MSDFF, SFF, FusionInputs, QueryInit
from mssf_blocks.geometry import CentroidProjection
from mssf_blocks.heads import SemanticGuidedHead
from mssf_blocks.lift import PillarLift

pytestmark = pytest.mark.usefixtures("one_thread")

# float16 CPU autocast needs a newer torch than the library's floor (mssf_blocks.torch_versions); skipped there
_NO_CPU_F16 = _compat.missing("cpu_float16_autocast")
AMP = [torch.bfloat16, pytest.param(torch.float16, marks=pytest.mark.skipif(_NO_CPU_F16 is not None,
                                                                            reason=str(_NO_CPU_F16)))]
VOD_HW = (1216, 1936)


# ---------------------------------------------------------------------------------------------------
# 1. projection precision under autocast
# ---------------------------------------------------------------------------------------------------
def vod_like_lidar2img() -> np.ndarray:
    """VoD's intrinsics (README of the real frames) and a radar ~1.5 m below / 2.5 m behind the camera:
    camera (right, down, forward) = (-y, -z, x)."""
    k = np.array([[1495.468642, 0.0, 961.272442], [0.0, 1495.468642, 624.89592], [0.0, 0.0, 1.0]])
    rt = np.array([[0.0, -1.0, 0.0, 0.05], [0.0, 0.0, -1.0, 1.5], [1.0, 0.0, 0.0, 2.5]])
    return k @ rt


def pixels64(xyz: np.ndarray, l2i: np.ndarray, image_hw=VOD_HW):
    cam = np.concatenate([xyz, np.ones((len(xyz), 1))], 1) @ l2i.T
    d = cam[:, 2]
    uv = cam[:, :2] / np.where(d > 1e-5, d, 1.0)[:, None]
    valid = (d > 1e-5) & np.all(uv >= -0.5, 1) & (uv[:, 0] <= image_hw[1] - 0.5) & (uv[:, 1] <= image_hw[0] - 0.5)
    return uv, valid


def max_pixel_error(xyz32: torch.Tensor, l2i64: np.ndarray, l2i: torch.Tensor, amp, image_hw=VOD_HW) -> float:
    ref, valid = pixels64(xyz32.double().numpy(), l2i64, image_hw)
    assert valid.sum() > 10
    pb = torch.zeros(len(xyz32), dtype=torch.long)
    with torch.autocast("cpu", dtype=amp):
        got = project_points(xyz32, pb, l2i[None], image_hw)
    assert got.pixel.dtype == got.uv.dtype == torch.float32
    return float(np.abs(got.pixel[:, 0].double().numpy() - ref)[valid].max())


def vod_range_points(n=4000, seed=0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.tensor([0.0, -25.6, -3.0]), torch.tensor([51.2, 25.6, 2.0])
    return lo + torch.rand(n, 3, generator=g) * (hi - lo)


@pytest.mark.parametrize("amp", AMP)
@pytest.mark.parametrize("l2i_dtype", [torch.float64, torch.float32])
def test_projection_under_autocast_matches_float64_at_vod_ranges(amp, l2i_dtype):
    l2i = vod_like_lidar2img()
    err = max_pixel_error(vod_range_points(), l2i, torch.from_numpy(l2i).to(l2i_dtype), amp)
    assert err < 1e-3, err  # bfloat16 autocast used to be off by pixels


def kitti_lidar2img(calib: Path) -> np.ndarray:
    """``P2 @ R0_rect @ Tr_velo_to_cam`` (3 x 4, float64) of a KITTI-format calibration file, read here."""
    m = {}
    for line in calib.read_text().splitlines():
        key, _, vals = line.partition(":")
        if vals.split():
            m[key] = np.array(vals.split(), dtype=np.float64)
    r0, tr = np.eye(4), np.eye(4)
    r0[:3, :3] = m["R0_rect"].reshape(3, 3)
    tr[:3] = m["Tr_velo_to_cam"].reshape(3, 4)
    return m["P2"].reshape(3, 4) @ r0 @ tr


def read_vod(root: Path, fid: str):
    pts = np.fromfile(root / "radar/velodyne" / f"{fid}.bin", dtype="<f4").reshape(-1, 7)
    return torch.from_numpy(pts[:, :3].copy()), kitti_lidar2img(root / "radar/calib" / f"{fid}.txt")


@pytest.mark.realdata
@pytest.mark.parametrize("fid", ["00549", "01047"])
@pytest.mark.parametrize("amp", AMP)
def test_projection_under_autocast_on_real_vod_frames(realdata_root, fid, amp):
    root = realdata_root / "vod"
    if not root.is_dir():
        pytest.skip(f"VoD frames not found at {root}")
    xyz, l2i = read_vod(root, fid)
    for l2i_t in (torch.from_numpy(l2i), torch.from_numpy(l2i).float()):
        err = max_pixel_error(xyz, l2i, l2i_t, amp)
        assert err < 1e-3, (fid, l2i_t.dtype, err)  # was a median 2.1 px / max 11 px (bf16)


@pytest.mark.realdata
@pytest.mark.parametrize("amp", AMP)
def test_projection_under_autocast_on_the_real_kitti_frame(realdata_root, amp):
    root = realdata_root / "kitti"
    if not root.is_dir():
        pytest.skip(f"KITTI frame not found at {root}")
    pts = np.fromfile(root / "velodyne/000000.bin", dtype="<f4").reshape(-1, 4)
    l2i = kitti_lidar2img(root / "calib/000000.txt")
    xyz = torch.from_numpy(pts[:, :3].copy())
    for l2i_t in (torch.from_numpy(l2i), torch.from_numpy(l2i).float()):
        err = max_pixel_error(xyz, l2i, l2i_t, amp, image_hw=(375, 1242))
        assert err < 1e-3, (l2i_t.dtype, err)


class RecordingProjector(VoxelCentroidProjector):
    def forward(self, *args, **kwargs):
        self.last = super().forward(*args, **kwargs)
        return self.last


@pytest.mark.parametrize("amp", AMP)
def test_fusion_block_samples_at_float64_exact_spots_under_autocast(amp):
    """The projection inside FusionBlock under autocast, against numpy float64 of the same centroids."""
    l2i = vod_like_lidar2img()
    pts = vod_range_points(3000, seed=1)
    pts = pts[torch.from_numpy(pixels64(pts.double().numpy(), l2i)[1])]
    voxel, lo = (0.4, 0.4, 0.5), (0.0, -25.6, -3.0)
    coords = torch.unique(torch.cat([torch.zeros(len(pts), 1), ((pts - torch.tensor(lo)) / torch.tensor(voxel))
                                     .floor()[:, [2, 1, 0]]], 1).int(), dim=0)
    vox = SparseVoxels(torch.randn(len(coords), 8), coords, (10, 128, 128), 1, voxel_size=voxel, point_range_min=lo)
    levels = [torch.randn(1, 6, VOD_HW[0] // s, VOD_HW[1] // s) for s in (16, 32)]
    inputs = FusionInputs(levels, torch.from_numpy(l2i)[None], VOD_HW, pts, torch.zeros(len(pts), dtype=torch.long))
    block = FusionBlock(MSDFF(6, 8, num_heads=2, num_levels=2, num_points=2),
                        query_init=QueryInit(8, 6, 8, lo + (51.2, 25.6, 2.0)), projector=RecordingProjector()).eval()
    with torch.autocast("cpu", dtype=amp):
        block(vox, inputs)
    proj = block.projector.last
    ref, valid = pixels64(proj.centroid.double().numpy(), l2i)
    uv_ref = (ref + 0.5) / np.array([VOD_HW[1], VOD_HW[0]])
    err_px = np.abs(proj.uv[:, 0].double().numpy() - uv_ref)[valid] * np.array([VOD_HW[1], VOD_HW[0]])
    assert valid.sum() > 100 and err_px.max() < 1e-3, err_px.max()


# ---------------------------------------------------------------------------------------------------
# 2. voxel_centroids validates coords
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("fn", [voxel_centroids, voxel_centroids_reference])
@pytest.mark.parametrize("row, pattern", [
    ([0, 0, 0, 4], r"coords\[:, 3\] \(x index\): expected values in \[0, 4\) \(spatial_shape\[2\]=4\)"),
    ([0, 0, 0, -1], r"coords\[:, 3\] \(x index\).*got values in \[-1, 1\]"),
    ([0, 0, 3, 0], r"coords\[:, 2\] \(y index\): expected values in \[0, 3\) \(spatial_shape\[1\]=3\)"),
    ([0, 2, 0, 0], r"coords\[:, 1\] \(z index\): expected values in \[0, 2\) \(spatial_shape\[0\]=2\)"),
    ([1, 0, 0, 0], r"coords\[:, 0\] \(batch index\): expected values in \[0, 1\) \(batch_size=1\)"),
])
def test_voxel_centroids_refuse_coords_outside_the_grid(fn, row, pattern):
    # x == W used to alias voxel (y + 1, x = 0); x == -1 collected the out-of-range points.
    coords = torch.tensor([[0, 0, 0, 1], row], dtype=torch.int32)
    pts = torch.tensor([[1.5, 0.5, 0.5], [0.5, 1.5, 0.5], [-3.0, 0.5, 0.5]])
    with pytest.raises(MSSFError, match=pattern):
        fn(pts, torch.zeros(3, dtype=torch.long), coords, (2, 3, 4), 1, (1.0, 1.0, 1.0), (0.0, 0.0, 0.0))


# ---------------------------------------------------------------------------------------------------
# 3. a NaN pixel that no voxel reads reaches no output and no gradient
# ---------------------------------------------------------------------------------------------------
def run_touched(plan, value, loc, wt, w, b):
    leaves = [t.detach().clone().requires_grad_() for t in (value, loc, wt, w, b)]
    out = touched.sample_project([leaves[0]], torch.zeros(loc.shape[0], dtype=torch.long),
                                            *leaves[1:], plan)
    (out * torch.linspace(-1, 1, out.numel()).view(out.shape)).sum().backward()
    return [out.detach()] + [t.grad for t in leaves]


@pytest.mark.parametrize("plan", ["dense", "project", "sample", "direct", None])
@pytest.mark.parametrize("pixel", [(0, 0), (-1, -1)])
def test_unread_nan_pixel_changes_nothing(plan, pixel):
    g = torch.Generator().manual_seed(0)
    q, m, p, c, d = 40, 2, 2, 6, 3
    value = torch.randn(1, 1, c, 10, 12, generator=g)
    if plan == "direct":  # the in-place plan reads channels-last maps only
        value = value[:, 0].contiguous(memory_format=torch.channels_last)[:, None]
    loc = 0.3 + 0.4 * torch.rand(q, m, 1, p, 2, generator=g)
    loc[:4] = 1.5  # some corners outside the map (they used to read a clamped row with weight 0)
    wt = torch.rand(q, m, 1, p, generator=g)
    w, b = torch.randn(m, d, c, generator=g), torch.randn(m, d, generator=g)
    bad, zero = value.clone(), value.clone()
    bad[0, 0, :, pixel[0], pixel[1]] = float("nan")
    zero[0, 0, :, pixel[0], pixel[1]] = 0.0
    got, ref = run_touched(plan, bad, loc, wt, w, b), run_touched(plan, zero, loc, wt, w, b)
    # (equal up to summation order: the NaN case may leave out-of-map corners out of their bags)
    for name, a, r in zip(("out", "value", "loc", "wt", "weight", "bias"), got, ref):
        torch.testing.assert_close(a, r, rtol=1e-5, atol=1e-6, msg=name)
    assert not got[1][0, 0, :, pixel[0], pixel[1]].any()  # the NaN pixel's own gradient: zero, as any unread


def test_msdff_auto_nan_in_unread_pixel_keeps_value_proj_grad_finite():
    g = torch.Generator().manual_seed(1)
    n = 400
    feats = [torch.randn(1, 16, 24, 32, generator=g), torch.randn(1, 16, 12, 16, generator=g)]
    feats[0][0, :, 0, 0] = float("nan")  # a corner of the image no voxel reads
    uv = (0.3 + 0.4 * torch.rand(n, 1, 2, generator=g))
    proj = CentroidProjection(uv=uv, depth=torch.ones(n, 1), valid=torch.ones(n, 1, dtype=torch.bool),
                              centroid=torch.zeros(n, 3), has_points=torch.ones(n, dtype=torch.bool),
                              batch_index=torch.zeros(n, dtype=torch.long))
    msdff = MSDFF(16, 16, num_heads=2, num_levels=2, num_points=2)
    msdff(torch.randn(n, 16, generator=g), feats, proj).sum().backward()
    assert torch.isfinite(msdff.value_proj.weight.grad).all()  # the "dense" plan made it NaN


# ---------------------------------------------------------------------------------------------------
# 4, 5, 7. points, image_size and the names in the messages
# ---------------------------------------------------------------------------------------------------
def small_scene(c_img=6, levels_hw=((12, 16), (6, 8)), image_size=(48, 64), dtype=torch.float32, seed=0):
    g = torch.Generator().manual_seed(seed)
    pts = torch.rand(30, 3, generator=g) * torch.tensor([8.0, 6, 1.5]) + torch.tensor([1.0, -3, -0.5])
    pb = torch.zeros(30, dtype=torch.long)
    idx = ((pts - torch.tensor([0.0, -4, -1])) / 0.5).floor().long()
    coords = torch.unique(torch.cat([pb[:, None], idx[:, [2, 1, 0]]], 1), dim=0).int()
    vox = SparseVoxels(torch.randn(len(coords), 8, generator=g, dtype=dtype), coords, (4, 16, 20), 1, voxel_size=(0.5,) * 3,
                       point_range_min=(0.0, -4.0, -1.0))
    l2i = torch.tensor([[[32.0, -40, 0, 0], [24, 0, -40, 0], [1, 0, 0, 0]]])
    levels = [torch.randn(1, c_img, h, w, generator=g) for h, w in levels_hw]
    return vox, levels, l2i, image_size, pts, pb


def test_openpcdet_points_are_refused_with_how_to_slice_them():
    vox, levels, l2i, size, pts, pb = small_scene()
    pcdet = torch.cat([pb[:, None].float(), pts, torch.randn(len(pts), 2)], 1)  # (b, x, y, z, i, t)
    with pytest.raises(MSSFError, match=r"points: expected shape \(P, 3\), got shape \(30, 6\).*pts\[:, 1:4\]"):
        FusionInputs(levels, l2i, size, pcdet, pb)
    with pytest.raises(MSSFError, match=r"points: expected shape \(P, 3\).*points_batch=pts\[:, 0\]\.long\(\)"):
        VoxelCentroidProjector()(vox, pcdet, pb, l2i, size)
    FusionInputs(levels, l2i, size, pcdet[:, 1:4], pcdet[:, 0].long())  # sliced as told: accepted


@pytest.mark.parametrize("where", ["inputs", "projector", "centroids"])
def test_transposed_points_blame_points(where):
    vox, levels, l2i, size, pts, pb = small_scene()
    with pytest.raises(MSSFError, match=r"^points: .*got shape \(3, 30\); transposed\?"):
        if where == "inputs":
            FusionInputs(levels, l2i, size, pts.T, pb)
        elif where == "projector":
            VoxelCentroidProjector()(vox, pts.T, pb, l2i, size)
        else:
            voxel_centroids(pts.T, pb, vox.coords, vox.spatial_shape, 1, vox.voxel_size, vox.point_range_min)


@pytest.mark.parametrize("levels_hw, size", [
    (((304, 484), (152, 242)), (1216, 1936)),  # VoD, strides 4 and 8
    (((38, 61),), (1216, 1936)),  # stride 32, ceil rounding
    (((94, 311), (47, 156)), (375, 1242)),  # KITTI, ceil(375 / 4), ceil(1242 / 4)
    (((11, 38),), (375, 1242)),  # stride 32, floor rounding
])
def test_image_size_with_the_levels_aspect_is_accepted(levels_hw, size):
    _, _, l2i, _, pts, pb = small_scene()
    FusionInputs([torch.zeros(1, 2, h, w) for h, w in levels_hw], l2i, size, pts, pb)


@pytest.mark.parametrize("levels_hw, size", [(((152, 242),), (1936, 1216)), (((94, 311),), (1242, 375)),
                                             (((12, 16),), (64, 48))])
def test_swapped_image_size_is_refused(levels_hw, size):
    _, _, l2i, _, pts, pb = small_scene()
    with pytest.raises(MSSFError, match=r"image_size: expected \(H, W\) with the aspect of image_features\[0\].*swapped\?"):
        FusionInputs([torch.zeros(1, 2, h, w) for h, w in levels_hw], l2i, size, pts, pb)


def test_wrong_level_channels_in_msdff_block_name_the_image_level():
    vox, levels, l2i, size, pts, pb = small_scene(c_img=256)
    block = FusionBlock(MSDFF(64, 8, num_heads=2, num_levels=2, num_points=2),
                        query_init=QueryInit(8, 64, 8, (0, -4, -1, 10, 4, 1))).eval()
    with pytest.raises(MSSFError, match=r"^inputs\.image_features\[0\]: expected shape \(B=1, 64, \*, \*\)") as info:
        block(vox, FusionInputs(levels, l2i, size, pts, pb))
    assert "f_img0" not in str(info.value)


# ---------------------------------------------------------------------------------------------------
# 6. one dtype rule for every module
# ---------------------------------------------------------------------------------------------------
def _proj(n, dtype=torch.float32):
    g = torch.Generator().manual_seed(2)
    return CentroidProjection(uv=torch.rand(n, 1, 2, generator=g).to(dtype), depth=torch.ones(n, 1),
                              valid=torch.ones(n, 1, dtype=torch.bool), centroid=torch.zeros(n, 3),
                              has_points=torch.ones(n, dtype=torch.bool), batch_index=torch.zeros(n, dtype=torch.long))


def _case(name):
    """(module, call(module, x), x, argument name): ``x`` is the floating input the rule applies to."""
    g = torch.Generator().manual_seed(3)
    if name == "SFF":
        # (level 1 follows x's dtype: values exact in bfloat16, so only the dtype differs between calls)
        levels = [torch.randn(1, 6, 12, 16, generator=g), torch.randn(1, 6, 6, 8, generator=g).bfloat16().float()]
        return SFF([6, 6], 8).eval(), lambda mod, x: mod([x, levels[1].to(x.dtype)], _proj(20)), levels[0], \
            r"image_features\[0\]"
    if name == "MSDFF":
        levels = [torch.randn(1, 6, 12, 16, generator=g), torch.randn(1, 6, 6, 8, generator=g)]
        mod = MSDFF(6, 8, num_heads=2, num_levels=2, num_points=2).eval()
        return mod, lambda mod, x: mod(x, levels, _proj(20)), torch.randn(20, 8, generator=g), "query"
    if name == "QueryInit":
        f_img0, centers = torch.randn(20, 6, generator=g), torch.rand(20, 3, generator=g) * 4
        mod = QueryInit(8, 6, 8, (0, 0, 0, 4, 4, 4)).eval()
        return mod, lambda mod, x: mod(x, f_img0, centers), torch.randn(20, 8, generator=g), "f_vox"
    if name.startswith("FusionBlock"):
        vox, levels, l2i, size, pts, pb = small_scene()
        inputs = FusionInputs(levels, l2i, size, pts, pb)
        fusion = SFF([6, 6], 8) if name == "FusionBlock-SFF" else MSDFF(6, 8, num_heads=2, num_levels=2, num_points=2)
        qi = QueryInit(8, 6, 8, (0, -4, -1, 10, 4, 1)) if name == "FusionBlock-MSDFF" else None
        mod = FusionBlock(fusion, query_init=qi).eval()
        return mod, lambda mod, x: mod(vox.replace(features=x), inputs).features, vox.features, r"x\.features"
    if name == "SemanticGuidedHead":
        vox, *_ = small_scene()
        return SemanticGuidedHead(8, hidden=(4,)).eval(), \
            lambda mod, x: mod(vox.replace(features=x))[0].features, vox.features, r"voxels\.features"
    if name == "PillarLift":
        vox, *_ = small_scene()
        mod = PillarLift(5, 4, stride=2)
        with torch.no_grad():
            mod.height_embedding.weight.normal_(generator=g)
        return mod, lambda mod, x: mod(x, vox).features, torch.randn(1, 5, 8, 10, generator=g), "bev"
    raise AssertionError(name)


MODULES = ["SFF", "MSDFF", "QueryInit", "FusionBlock-SFF", "FusionBlock-MSDFF", "FusionBlock-MSDFF-plain",
           "SemanticGuidedHead", "PillarLift"]


@pytest.mark.parametrize("name", MODULES)
def test_float64_input_into_float32_module_is_refused(name):
    mod, call, x, arg = _case(name)
    with pytest.raises(MSSFError, match=rf"{arg}: expected dtype torch.float32 or lower precision.*float64.*\.double\(\)"):
        call(mod, x.double())


@pytest.mark.parametrize("name", MODULES)
def test_float32_input_into_float64_module_is_read_as_float64(name):
    mod, call, x, _ = _case(name)
    mod = mod.double()
    out = call(mod, x)
    assert out.dtype == torch.float64
    assert torch.equal(out, call(mod, x.double()))  # float32 -> float64 is exact: the same numbers


@pytest.mark.parametrize("name", MODULES)
def test_bfloat16_input_into_float32_module_is_read_as_float32(name):
    mod, call, x, _ = _case(name)
    x16 = x.bfloat16()
    out = call(mod, x16)
    assert out.dtype == torch.float32
    assert torch.equal(out, call(mod, x16.float()))


@pytest.mark.parametrize("dtype, expected", [(torch.float64, torch.float64), (torch.float32, torch.float32),
                                             (torch.bfloat16, torch.float32), (torch.float16, torch.float32)])
def test_projector_geometry_is_float32_or_better(dtype, expected):
    vox, levels, l2i, size, pts, pb = small_scene()
    got = VoxelCentroidProjector()(vox, pts.to(dtype), pb, l2i, size)
    assert got.uv.dtype == got.centroid.dtype == got.depth.dtype == expected
    ref = VoxelCentroidProjector()(vox, pts.to(dtype).double(), pb, l2i.double(), size)
    torch.testing.assert_close(got.centroid.double(), ref.centroid, rtol=0, atol=1e-6)
    centroid, _ = voxel_centroids(pts.to(dtype), pb, vox.coords, vox.spatial_shape, 1, vox.voxel_size,
                                  vox.point_range_min)
    assert centroid.dtype == expected


def test_check_finite_sum_shortcut_is_exact():
    # finite entries whose sum overflows to inf are still finite (the exact test decides); one NaN or
    # inf anywhere is refused, named, and counted
    from mssf_blocks.checks.tensors import check_finite

    big = torch.full((4,), 3e38)
    assert not bool(torch.isfinite(big.sum()))
    assert check_finite(big, "x") is big
    for bad, count in ((float("nan"), 1), (float("inf"), 1), (-float("inf"), 1)):
        x = torch.ones(1000)
        x[123] = bad
        with pytest.raises(MSSFError, match=rf"x: expected finite values, got {count} NaN/inf"):
            check_finite(x, "x")
    x = torch.ones(10)
    x[2], x[7] = float("inf"), -float("inf")  # inf + -inf = NaN in the sum
    with pytest.raises(MSSFError, match="got 2 NaN/inf"):
        check_finite(x, "x")
