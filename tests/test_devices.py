"""The blocks on every available device against independent float64 references (naive loops on the CPU).

The ``device`` fixture (``tests/conftest.py``) runs each test on the CPU and, where
``torch.cuda.is_available()``, again on CUDA, so the same assertions check a GPU machine
(``benchmarks/gpu_check.py`` runs them there). Per block: the module in float64 on the device equals a
hand-written float64 reference to 1e-10 (outputs and parameter gradients), and in float32 to float32
tolerance; MSDFF's three methods agree on the device. The references are plain loops over voxels,
cameras, heads, levels and points with an explicit bilinear formula (pixel ``i``'s centre at ``i``,
``align_corners=False``, zero padding), so they share no code with the library.

A last test counts host synchronisations with ``torch.cuda.set_sync_debug_mode`` (CUDA only).
"""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

from mssf_blocks.blocks import FusionBlock
from mssf_blocks.samplers import MSDFF, SFF, FusionInputs, QueryInit
from mssf_blocks.geometry import CentroidProjection
from mssf_blocks.heads import SemanticGuidedHead
from mssf_blocks.lift import PillarLift
from mssf_blocks.sparse_voxels import SparseVoxels

TOL32 = dict(rtol=1e-4, atol=1e-4)
TOL64 = dict(rtol=1e-10, atol=1e-10)
EPS = 1e-5  # BatchNorm1d's default eps


# ---------------------------------------------------------------------------------------------------
# references (float64, CPU, loops)
# ---------------------------------------------------------------------------------------------------
def bilinear_ref(img, u, v):
    """``img (C, H, W)`` at normalised ``(u, v)``: pixel coords ``x = u W - 0.5``, zero outside."""
    c, h, w = img.shape
    x, y = u * w - 0.5, v * h - 0.5
    x0, y0 = math.floor(float(x.detach())), math.floor(float(y.detach()))
    out = img.new_zeros(c)
    for yy in (y0, y0 + 1):
        for xx in (x0, x0 + 1):
            if 0 <= xx < w and 0 <= yy < h:
                wx = 1 - abs(x - xx)
                wy = 1 - abs(y - yy)
                out = out + wx * wy * img[:, yy, xx]
    return out


def bn_train_ref(y, weight, bias):
    mean = y.mean(0)
    var = ((y - mean) ** 2).mean(0)
    return (y - mean) / torch.sqrt(var + EPS) * weight + bias


def visible_linear_bn_ref(x, valid, lin_w, lin_b, bn_w, bn_b):
    """Linear + training-mode BatchNorm over the voxels seen by some camera, zeros for the others."""
    vis = valid.any(1)
    out = x.new_zeros(x.shape[0], lin_w.shape[0])
    out[vis] = bn_train_ref(x[vis] @ lin_w.t() + lin_b, bn_w, bn_b)
    return out


def camera_mean_ref(per_cam, valid):
    n = per_cam.shape[0]
    rows = []
    for i in range(n):
        cams = [per_cam[i, k] for k in range(valid.shape[1]) if valid[i, k]]
        rows.append(torch.stack(cams).mean(0) if cams else per_cam.new_zeros(per_cam.shape[2]))
    return torch.stack(rows)


def sff_ref(levels, uv, valid, bidx, p):
    n, v = valid.shape
    per_cam = torch.stack([torch.stack([
        torch.cat([bilinear_ref(lvl[bidx[i], k], uv[i, k, 0], uv[i, k, 1]) for lvl in levels])
        for k in range(v)]) for i in range(n)])
    return visible_linear_bn_ref(camera_mean_ref(per_cam, valid), valid, p["linear.weight"], p["linear.bias"],
                                 p["norm.weight"], p["norm.bias"])


def msdff_ref(query, levels, uv, valid, bidx, p, m, pts):
    """Deformable DETR's formula, project-every-pixel order, one (voxel, camera, head, level, point) at a time."""
    n, v = valid.shape
    e = p["value_proj.weight"].shape[0]  # value_dim, split over the heads
    d = e // m
    nl = len(levels)
    offsets = (query @ p["sampling_offsets.weight"].t() + p["sampling_offsets.bias"]).view(n, m, nl, pts, 2)
    logits = (query @ p["attention_weights.weight"].t() + p["attention_weights.bias"]).view(n, m, nl * pts)
    weights = logits.softmax(-1).view(n, m, nl, pts)
    values = [torch.einsum("bvchw,ec->bvehw", lvl, p["value_proj.weight"]) + p["value_proj.bias"][:, None, None]
              for lvl in levels]
    per_cam = query.new_zeros(n, v, e)
    for i in range(n):
        for k in range(v):
            if not valid[i, k]:
                continue
            heads = []
            for h in range(m):
                acc = query.new_zeros(d)
                for l, val in enumerate(values):
                    hl, wl = val.shape[-2:]
                    for q in range(pts):
                        lu = uv[i, k, 0] + offsets[i, h, l, q, 0] / wl
                        lv = uv[i, k, 1] + offsets[i, h, l, q, 1] / hl
                        acc = acc + weights[i, h, l, q] * bilinear_ref(val[bidx[i], k, h * d:(h + 1) * d], lu, lv)
                heads.append(acc)
            per_cam[i, k] = torch.cat(heads)
    return visible_linear_bn_ref(camera_mean_ref(per_cam, valid), valid, p["output_proj.weight"],
                                 p["output_proj.bias"], p["norm.weight"], p["norm.bias"])


# ---------------------------------------------------------------------------------------------------
# inputs
# ---------------------------------------------------------------------------------------------------
def make_projection(n=9, v=2, b=2, seed=0):
    g = torch.Generator().manual_seed(seed)
    uv = torch.rand(n, v, 2, generator=g, dtype=torch.float64) * 1.2 - 0.1  # some outside the image
    valid = torch.rand(n, v, generator=g) > 0.3
    valid[0] = False  # one voxel seen by no camera
    valid[1] = True
    bidx = torch.randint(0, b, (n,), generator=g)
    return uv, valid, bidx


def make_levels(b=2, v=2, c=4, sizes=((6, 8), (3, 4)), seed=1):
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(b, v, c, h, w, generator=g, dtype=torch.float64) for h, w in sizes]


def projection_on(uv, valid, bidx, device, dtype):
    n = uv.shape[0]
    return CentroidProjection(uv=uv.to(device, dtype), depth=torch.ones(n, uv.shape[1], device=device, dtype=dtype),
                              valid=valid.to(device), centroid=torch.zeros(n, 3, device=device, dtype=dtype),
                              has_points=torch.ones(n, dtype=torch.bool, device=device), batch_index=bidx.to(device))


def randomize(module, seed=2):
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for prm in module.parameters():
            prm.copy_(torch.randn(prm.shape, generator=g, dtype=torch.float64).to(prm) * 0.5)
    return module


def cpu64(params):
    return {k: t.detach().double().cpu().requires_grad_(True) for k, t in params.items()}


def check_grads(module, ref_params, tol):
    for k, prm in module.named_parameters():
        ref = ref_params[k].grad
        assert prm.grad is not None, k
        torch.testing.assert_close(prm.grad.double().cpu(), ref, **tol, msg=k)


# ---------------------------------------------------------------------------------------------------
# tests
# ---------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
def test_sff_matches_the_loop_reference(device, dtype):
    uv, valid, bidx = make_projection()
    levels = make_levels()
    sff = randomize(SFF([4, 4], 5)).to(device, dtype).train()
    ref_p = cpu64(dict(sff.named_parameters()))
    out = sff([l.to(device, dtype) for l in levels], projection_on(uv, valid, bidx, device, dtype))
    ref = sff_ref(levels, uv, valid, bidx, ref_p)
    tol = TOL64 if dtype == torch.float64 else TOL32
    assert out.device.type == device.type
    torch.testing.assert_close(out.double().cpu(), ref, **tol)
    w = torch.randn(ref.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    (out * w.to(device, dtype)).sum().backward()
    (ref * w).sum().backward()
    check_grads(sff, ref_p, tol if dtype == torch.float64 else dict(rtol=1e-3, atol=1e-3))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
def test_msdff_every_method_matches_the_loop_reference(device, dtype):
    uv, valid, bidx = make_projection()
    levels = make_levels()
    m, pts, e = 2, 2, 6
    g = torch.Generator().manual_seed(4)
    query = torch.randn(uv.shape[0], e, generator=g, dtype=torch.float64)
    torch.manual_seed(0)
    base = randomize(MSDFF(4, e, num_heads=m, num_levels=2, num_points=pts))
    ref_p = cpu64(dict(base.named_parameters()))
    ref = msdff_ref(query, levels, uv, valid, bidx, ref_p, m, pts)
    w = torch.randn(ref.shape, dtype=torch.float64, generator=g)
    (ref * w).sum().backward()
    tol = TOL64 if dtype == torch.float64 else TOL32
    for method, order in (("auto", "after_sampling"), ("fast", "after_sampling"), ("reference", "before_sampling")):
        mod = MSDFF(4, e, num_heads=m, num_levels=2, num_points=pts, method=method, value_projection=order)
        mod.load_state_dict(base.state_dict())
        mod = mod.to(device, dtype).train()
        out = mod(query.to(device, dtype), [l.to(device, dtype) for l in levels],
                  projection_on(uv, valid, bidx, device, dtype))
        torch.testing.assert_close(out.double().cpu(), ref, **tol, msg=method)
        assert out[0].abs().max() == 0  # seen by no camera: exact zeros
        (out * w.to(device, dtype)).sum().backward()
        check_grads(mod, ref_p, tol if dtype == torch.float64 else dict(rtol=1e-3, atol=1e-3))


def test_query_init_matches_the_formula(device):
    g = torch.Generator().manual_seed(5)
    n = 7
    f_vox, f_img, centers = (torch.randn(n, c, generator=g, dtype=torch.float64) for c in (3, 4, 3))
    pcr = (0.0, -2.0, -1.0, 4.0, 2.0, 1.0)
    qi = randomize(QueryInit(3, 4, 5, pcr)).to(device, torch.float64).train()
    p = cpu64(dict(qi.named_parameters()))
    pnorm = (centers - torch.tensor(pcr[:3], dtype=torch.float64)) / torch.tensor([4.0, 4.0, 2.0], dtype=torch.float64)
    ref = bn_train_ref(torch.cat([f_vox, f_img, pnorm], 1) @ p["linear.weight"].t() + p["linear.bias"],
                       p["norm.weight"], p["norm.bias"])
    out = qi(f_vox.to(device), f_img.to(device), centers.to(device))
    torch.testing.assert_close(out.cpu(), ref, **TOL64)
    out.pow(2).sum().backward()
    ref.pow(2).sum().backward()
    check_grads(qi, p, TOL64)


def _voxels(device, dtype, seed=6):
    """Voxels on a (D, H, W) = (4, 6, 8) grid of 0.5 m cells from (0, -1.5, -1), two samples."""
    g = torch.Generator().manual_seed(seed)
    coords = torch.unique(torch.cat([torch.randint(0, 2, (30, 1), generator=g), torch.randint(0, 4, (30, 1), generator=g),
                                     torch.randint(0, 6, (30, 1), generator=g), torch.randint(0, 8, (30, 1), generator=g)],
                                    1), dim=0).int()
    feats = torch.randn(coords.shape[0], 6, generator=g, dtype=torch.float64)
    return SparseVoxels(feats.to(device, dtype), coords.to(device), (4, 6, 8), 2, voxel_size=(0.5, 0.5, 0.5), point_range_min=(0.0, -1.5, -1.0))


def test_pillar_lift_matches_the_gather(device):
    vox = _voxels(device, torch.float64)
    lift = randomize(PillarLift(6, 4, stride=2)).to(device, torch.float64)
    bev = torch.randn(2, 6, 3, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(7))
    bev_d = bev.to(device).requires_grad_(True)
    out = lift(bev_d, vox).features
    emb = lift.height_embedding.weight.detach().cpu()
    coords = vox.coords.cpu().long()
    ref = torch.stack([bev[b, :, y // 2, x // 2] + emb[z] for b, z, y, x in coords.tolist()])
    torch.testing.assert_close(out.cpu(), ref, **TOL64)
    # back to BEV: the sum of the voxels of every pillar, by hand
    back = lift.to_bev(vox.replace(features=out))
    ref_bev = torch.zeros(2, 6, 3, 4, dtype=torch.float64)
    for (b, z, y, x), f in zip(coords.tolist(), ref):
        ref_bev[b, :, y // 2, x // 2] += f
    torch.testing.assert_close(back.detach().cpu(), ref_bev, **TOL64)
    back.sum().backward()
    counts = torch.zeros(2, 3, 4, dtype=torch.float64)
    for b, z, y, x in coords.tolist():
        counts[b, y // 2, x // 2] += 1
    torch.testing.assert_close(bev_d.grad.cpu(), counts[:, None].expand(2, 6, 3, 4), **TOL64)


def test_semantic_head_matches_the_formula(device):
    vox = _voxels(device, torch.float64)
    head = randomize(SemanticGuidedHead(6, hidden=(5,))).to(device, torch.float64).train()
    p = cpu64(dict(head.named_parameters()))
    f = vox.features.cpu()
    hid = torch.relu(bn_train_ref(f @ p["mlp.0.weight"].t(), p["mlp.1.weight"], p["mlp.1.bias"]))
    logit = (hid @ p["classifier.weight"].t() + p["classifier.bias"]).squeeze(1)
    score = torch.sigmoid(logit)
    labels = (torch.arange(f.shape[0]) % 3 == 0).double()
    pt = score * labels + (1 - score) * (1 - labels)
    at = 0.25 * labels + 0.75 * (1 - labels)
    ref_loss = (-at * (1 - pt) ** 2 * torch.log(pt)).sum() / labels.sum()
    out, scores, logits = head(vox, return_logits=True)
    torch.testing.assert_close(scores.cpu(), score, **TOL64)
    torch.testing.assert_close(out.features.cpu(), f * score[:, None], **TOL64)
    loss = head.loss(logits, labels.to(device))
    torch.testing.assert_close(loss.cpu(), ref_loss, **TOL64)
    (loss + out.features.sum()).backward()
    (ref_loss + (f * score[:, None]).sum()).backward()
    check_grads(head, p, dict(rtol=1e-9, atol=1e-9))


@pytest.mark.parametrize("kind", ["sff", "msdff"])
def test_fusion_block_adds_the_sampler_output(device, kind):
    """FusionBlock on the device = voxel feature + the sampler's output at the projected centroids, the
    projection worked by hand (pinhole camera looking along +x) and the sampler's loop reference."""
    vox = _voxels(device, torch.float64)
    b = 2
    # u = 8 - 4 y / x, v = 6 - 4 z / x on a 12 x 16 image; the voxels' x in [0, 4] m: in front
    cam = torch.tensor([[8.0, -4, 0, 0], [6, 0, -4, 0], [1, 0, 0, 0]], dtype=torch.float64)
    l2i = cam.expand(b, 1, 3, 4).contiguous()
    levels = make_levels(b=b, v=1, c=6, sizes=((6, 8), (3, 4)))
    pts = torch.zeros(0, 3, dtype=torch.float64)  # no points: every voxel uses its centre
    inputs = FusionInputs([l.to(device) for l in levels], l2i.to(device), (12, 16), pts.to(device),
                          torch.zeros(0, dtype=torch.long, device=device))
    torch.manual_seed(0)
    sampler = SFF([6, 6], 6) if kind == "sff" else MSDFF(6, 6, num_heads=2, num_levels=2, num_points=2)
    block = FusionBlock(randomize(sampler)).to(device, torch.float64).train()
    out = block(vox, inputs)
    centres = vox.voxel_centers().cpu()
    hom = torch.cat([centres, torch.ones(len(centres), 1, dtype=torch.float64)], 1) @ cam.t()
    d = hom[:, 2:]
    uv = torch.cat([(hom[:, :1] / d + 0.5) / 16, (hom[:, 1:2] / d + 0.5) / 12], 1)[:, None]
    # valid: in front of the camera and inside the image (0 <= uv <= 1, the projection's convention)
    valid = (d > 1e-5) & (uv[:, 0] >= 0).all(1, keepdim=True) & (uv[:, 0] <= 1).all(1, keepdim=True)
    assert 0 < int(valid.sum()) < len(valid)  # both kinds present
    bidx = vox.coords[:, 0].long().cpu()
    p = cpu64(dict(block.fusion.named_parameters()))
    if kind == "sff":
        f_img = sff_ref(levels, uv, valid, bidx, p)
    else:
        f_img = msdff_ref(vox.features.cpu(), levels, uv, valid, bidx, p, 2, 2)
    torch.testing.assert_close(out.features.detach().cpu(), vox.features.cpu() + f_img, **TOL64)
    assert torch.equal(out.coords.cpu(), vox.coords.cpu())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="host synchronisations are counted on CUDA only")
@pytest.mark.parametrize("method", ["auto", "fast", "reference"])
def test_msdff_host_syncs_do_not_grow_with_the_voxels_on_cuda(method):  # GPU machines (gpu_check.py)
    """``torch.cuda.set_sync_debug_mode("warn")`` warns on every host synchronisation: MSDFF's forward +
    backward (one camera seeing every voxel) has only the documented, data-dependent ones, a handful,
    the same number for 50 and 5,000 voxels (none per voxel)."""
    import warnings

    dev = torch.device("cuda")

    def count(n):
        uv, valid, bidx = make_projection(n=n, v=1, b=1)
        valid[:] = True
        levels = [lvl.float().to(dev) for lvl in make_levels(b=1, v=1, c=4)]
        mod = MSDFF(4, 8, num_heads=2, num_levels=2, num_points=2, method=method).to(dev).train()
        q = torch.randn(n, 8, device=dev, requires_grad=True)
        proj = projection_on(uv, valid, bidx, dev, torch.float32)
        mod(q, levels, proj).sum().backward()  # warm-up (cuBLAS handles, caches)
        torch.cuda.synchronize()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            torch.cuda.set_sync_debug_mode("warn")
            try:
                mod(q, levels, proj).sum().backward()
            finally:
                torch.cuda.set_sync_debug_mode("default")
        return len([w for w in caught if "synchroniz" in str(w.message).lower()])

    small, large = count(50), count(5000)
    print(f"MSDFF(method={method!r}) host syncs per forward + backward: {small} (N = 50), {large} (N = 5,000)")
    assert large <= small + 2 and small <= 12, (small, large)
