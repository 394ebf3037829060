"""``mssf_blocks.weights.authors_checkpoint``: the authors' state-dict layout and forward, reproduced exactly.

The reference below re-creates the forward of the authors' code (``EricLiuhhh/MSSF``) from its
description, with plain loops and ``F.grid_sample``; the weights are random tensors under *their* key
names, loaded into our modules only through the converter. Their forward, as we read it:

* reference point of a voxel: its centroid (mean of its points; the voxel centre when it holds none)
  projected with ``lidar2img``, ``(u / W_pad, v / H_pad)``, no in-image test;
* query initialiser: ``BN(Linear(cat(grid_sample(level0, align_corners=True), f_vox, p)))``, ``p`` the
  centroid normalised by the point-cloud range;
* MSDFF (``MSDeformableAttention``): ``value_proj`` on every pixel, heads of ``value_dim / M``
  channels, locations ``ref + offset / (W_l, H_l)``, ``grid_sample(align_corners=False)``, softmax
  over ``L * P``, ``output_proj``, then ``dropout(.) + query``; the block adds the voxel feature;
* SFF (``SimpleVoxelFusionBlock``): ``BN_{eps=1e-3}(Linear(cat_l grid_sample(level_l, align_corners=True)))``;
* semantic head: ``seg_cls_layer`` = (Linear without bias, BN, ReLU) per hidden width, Linear.
"""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from mssf_blocks.blocks import FusionBlock
from mssf_blocks.weights.authors_checkpoint import OFFICIAL_SWITCHES
from mssf_blocks.weights import ModuleMap, mssf_v_module_maps, official_to_ours, ours_to_official
from mssf_blocks.errors import MSSFError
from mssf_blocks.samplers import MSDFF, SFF, FusionInputs, QueryInit
from mssf_blocks.geometry import VoxelCentroidProjector
from mssf_blocks.heads import SemanticGuidedHead
from mssf_blocks.lift import HeightEmbedding
from mssf_blocks.sparse_voxels import SparseVoxels

D64 = torch.float64
ENC = "pts_middle_encoder"
VOXEL = (0.5, 0.5, 0.5)
LO = (0.0, -4.0, -1.0)
PCR = (0.0, -4.0, -1.0, 8.0, 4.0, 1.0)
IMAGE = (24, 40)  # (H, W), their padded input shape
CV, CI, DV, M, L, P = 6, 8, 8, 2, 2, 3  # voxel channels, image channels, value_dim, heads, levels, points


def scene(seed=0):
    """Two samples, a forward camera (u = 20 - 30 y / x, v = 12 - 30 z / x), voxels with 1-3 points each,
    one voxel without points, some voxels projecting outside the image (all in front of the camera)."""
    g = torch.Generator().manual_seed(seed)
    coords, pts, pb = [], [], []
    for b in range(2):
        cells = {(int(z), int(y), int(x)) for z, y, x in zip(torch.randint(0, 4, (9,), generator=g),
                                                           torch.randint(0, 16, (9,), generator=g),
                                                           torch.randint(2, 16, (9,), generator=g))}
        for k, (z, y, x) in enumerate(sorted(cells)):
            coords.append([b, z, y, x])
            if k == 0:
                continue  # no points: its centroid is its centre
            for _ in range(1 + k % 3):
                xyz = (torch.tensor([x, y, z], dtype=D64) + torch.rand(3, generator=g, dtype=D64)) * 0.5
                pts.append(xyz + torch.tensor(LO, dtype=D64))
                pb.append(b)
    coords = torch.tensor(coords, dtype=torch.int32)
    n = coords.shape[0]
    voxels = SparseVoxels(torch.randn(n, CV, generator=g, dtype=D64), coords, (4, 16, 16), 2, voxel_size=VOXEL, point_range_min=LO)
    cam = torch.tensor([[20.0, -30, 0, 0], [12, 0, -30, 0], [1, 0, 0, 0]], dtype=D64)
    levels = [torch.randn(2, CI, IMAGE[0] // s, IMAGE[1] // s, generator=g, dtype=D64) for s in (4, 8)]
    inputs = FusionInputs(levels, cam.expand(2, 3, 4).contiguous(), IMAGE, torch.stack(pts),
                          torch.tensor(pb))
    return voxels, inputs, g


def their_reference_points(voxels, inputs):
    """Centroid (their voxel_aggregation_utils: mean of the voxel's points, else the centre) and u / W_pad."""
    n = voxels.num_voxels
    cent = torch.zeros(n, 3, dtype=D64)
    for i in range(n):
        b, z, y, x = voxels.coords[i].tolist()
        idx = ((inputs.points - torch.tensor(LO, dtype=D64)) / torch.tensor(VOXEL, dtype=D64)).floor().long()
        mine = (inputs.points_batch == b) & (idx[:, 0] == x) & (idx[:, 1] == y) & (idx[:, 2] == z)
        if mine.any():
            cent[i] = inputs.points[mine].mean(0)
        else:
            cent[i] = (torch.tensor([x, y, z], dtype=D64) + 0.5) * torch.tensor(VOXEL, dtype=D64) + torch.tensor(LO, dtype=D64)
    ref = torch.zeros(n, 2, dtype=D64)
    for i in range(n):
        cam = inputs.lidar2img[voxels.coords[i, 0]] @ torch.cat([cent[i], torch.ones(1, dtype=D64)])
        ref[i] = torch.stack([cam[0] / cam[2] / IMAGE[1], cam[1] / cam[2] / IMAGE[0]])
    return cent, ref


def grid_at(img, ref, align_corners):
    """``img (C, H, W)`` at normalised ``ref (K, 2)`` -> ``(K, C)``, zero padding."""
    grid = (2 * ref - 1).view(1, 1, -1, 2)
    return F.grid_sample(img[None], grid, mode="bilinear", padding_mode="zeros", align_corners=align_corners)[0, :, 0].T


def bn_eval(x, sd, prefix, eps):
    return (x - sd[f"{prefix}.running_mean"]) / torch.sqrt(sd[f"{prefix}.running_var"] + eps) * sd[
        f"{prefix}.weight"] + sd[f"{prefix}.bias"]


def linear(x, sd, prefix, bias=True):
    return x @ sd[f"{prefix}.weight"].T + (sd[f"{prefix}.bias"] if bias else 0)


def random_official(g):
    """Random tensors in their layout: an MSDFF block at x_conv1 and x_conv2, an SFF block, query_proj, seg head."""
    def r(*shape, scale=0.5):
        return torch.randn(*shape, generator=g, dtype=D64) * scale

    def bn(prefix, c):
        return {f"{prefix}.weight": 1 + r(c, scale=0.2), f"{prefix}.bias": r(c, scale=0.2),
                f"{prefix}.running_mean": r(c, scale=0.3), f"{prefix}.running_var": 0.5 + torch.rand(c, generator=g, dtype=D64),
                f"{prefix}.num_batches_tracked": torch.tensor(7)}

    sd = {}
    for loc in ("x_conv1", "x_conv2"):
        pre = f"{ENC}.fusion_blocks.{loc}.img_cross_att.deformable_attention"
        sd.update({f"{pre}.sampling_offsets.weight": r(M * L * P * 2, CV), f"{pre}.sampling_offsets.bias": r(M * L * P * 2, scale=3),
                   f"{pre}.attention_weights.weight": r(M * L * P, CV), f"{pre}.attention_weights.bias": r(M * L * P),
                   f"{pre}.value_proj.weight": r(DV, CI), f"{pre}.value_proj.bias": r(DV),
                   f"{pre}.output_proj.weight": r(CV, DV), f"{pre}.output_proj.bias": r(CV)})
    sd.update({f"{ENC}.fusion_blocks.x_conv3.img_transform.0.weight": r(CV, CI * L),
               f"{ENC}.fusion_blocks.x_conv3.img_transform.0.bias": r(CV)})
    sd.update(bn(f"{ENC}.fusion_blocks.x_conv3.img_transform.1", CV))
    sd.update({f"{ENC}.query_proj.0.weight": r(CV, CI + CV + 3), f"{ENC}.query_proj.0.bias": r(CV)})
    sd.update(bn(f"{ENC}.query_proj.1", CV))
    sd.update({f"{ENC}.seg_heads.x_conv3.seg_cls_layer.0.weight": r(5, CV), f"{ENC}.seg_heads.x_conv3.seg_cls_layer.3.weight": r(4, 5),
               f"{ENC}.seg_heads.x_conv3.seg_cls_layer.6.weight": r(1, 4), f"{ENC}.seg_heads.x_conv3.seg_cls_layer.6.bias": r(1)})
    sd.update(bn(f"{ENC}.seg_heads.x_conv3.seg_cls_layer.1", 5))
    sd.update(bn(f"{ENC}.seg_heads.x_conv3.seg_cls_layer.4", 4))
    # their query initialiser's VoxelFusion builds an img_transform it never calls (dead weights)
    sd.update({f"{ENC}.voxel_fuse.img_transform.0.weight": r(CI, CI), f"{ENC}.voxel_fuse.img_transform.0.bias": r(CI)})
    return sd


def their_msdff(sd, loc, query, levels, ref, batch):
    pre = f"{ENC}.fusion_blocks.{loc}.img_cross_att.deformable_attention"
    n, d = query.shape[0], DV // M
    off = linear(query, sd, f"{pre}.sampling_offsets").view(n, M, L, P, 2)
    att = linear(query, sd, f"{pre}.attention_weights").view(n, M, L * P).softmax(-1).view(n, M, L, P)
    out = torch.zeros(n, DV, dtype=D64)
    for i in range(n):
        for lv in range(L):
            img = levels[lv][batch[i]]  # (C, H_l, W_l)
            h, w = img.shape[-2:]
            value = (img.permute(1, 2, 0) @ sd[f"{pre}.value_proj.weight"].T + sd[f"{pre}.value_proj.bias"]).permute(2, 0, 1)
            for m in range(M):
                loc_ = ref[i] + off[i, m, lv] / torch.tensor([w, h], dtype=D64)
                s = grid_at(value[m * d:(m + 1) * d], loc_, align_corners=False)  # (P, d)
                out[i, m * d:(m + 1) * d] += (att[i, m, lv][:, None] * s).sum(0)
    return linear(out, sd, f"{pre}.output_proj")


def build_ours(converted, first=True):
    sw = OFFICIAL_SWITCHES
    msdff = MSDFF(CI, CV, num_heads=M, num_levels=L, num_points=P, dtype=D64, **sw["msdff"])
    qi = QueryInit(CV, CI, CV, PCR, dtype=D64, **sw["query_init"]) if first else None
    block = FusionBlock(msdff, query_init=qi, projector=VoxelCentroidProjector(**sw["projector"])).eval()
    return block


def test_first_msdff_block_with_query_init_equals_their_forward():
    voxels, inputs, g = scene()
    theirs = random_official(g)
    maps, ignore = mssf_v_module_maps({"x_conv1": "fusion"}, query_init="query_init", voxel_channels=CV)
    ignore += [f"{ENC}.fusion_blocks.x_conv2", f"{ENC}.fusion_blocks.x_conv3", f"{ENC}.seg_heads"]
    block = build_ours(None)
    block.load_state_dict(official_to_ours(theirs, maps, ignore), strict=True)
    got = block(voxels, inputs).features

    cent, ref = their_reference_points(voxels, inputs)
    assert ((ref < 0) | (ref > 1)).any(dim=1).any() and ((ref > 0) & (ref < 1)).all(dim=1).any()
    batch = voxels.coords[:, 0].long()
    img0 = torch.stack([grid_at(inputs.image_features[0][batch[i]], ref[i:i + 1], True)[0] for i in range(len(batch))])
    pos = (cent - torch.tensor(PCR[:3], dtype=D64)) / (torch.tensor(PCR[3:], dtype=D64) - torch.tensor(PCR[:3], dtype=D64))
    f_vox = voxels.features
    q = bn_eval(linear(torch.cat([img0, f_vox, pos], 1), theirs, f"{ENC}.query_proj.0"), theirs, f"{ENC}.query_proj.1", 1e-5)
    updated = their_msdff(theirs, "x_conv1", q, inputs.image_features, ref, batch) + q  # dropout: eval
    want = f_vox + updated
    assert (got - want).abs().max() <= 1e-10
    # the switches matter: the library's defaults give a different forward
    plain = FusionBlock(MSDFF(CI, CV, num_heads=M, num_levels=L, num_points=P, dtype=D64),
                        query_init=QueryInit(CV, CI, CV, PCR, dtype=D64)).eval()
    plain.load_state_dict(official_to_ours(theirs, maps, ignore), strict=False)
    assert (plain(voxels, inputs).features - want).abs().max() > 1e-3


def test_later_msdff_block_computes_two_f_vox_plus_f_img():
    voxels, inputs, g = scene(1)
    theirs = random_official(g)
    maps = [ModuleMap("msdff", f"{ENC}.fusion_blocks.x_conv2", "fusion")]
    block = build_ours(None, first=False)
    block.load_state_dict(official_to_ours(theirs, maps, ignore=[f"{ENC}.{k}" for k in (
        "fusion_blocks.x_conv1", "fusion_blocks.x_conv3", "query_proj", "seg_heads", "voxel_fuse")]), strict=True)
    _, ref = their_reference_points(voxels, inputs)
    batch = voxels.coords[:, 0].long()
    f_vox = voxels.features
    want = 2 * f_vox + their_msdff(theirs, "x_conv2", f_vox, inputs.image_features, ref, batch)
    assert (block(voxels, inputs).features - want).abs().max() <= 1e-10
    # training mode: dropout 0.1 on the image feature, before the query is added back (same RNG draw)
    block.train()
    torch.manual_seed(3)
    got = block(voxels, inputs).features
    torch.manual_seed(3)
    f_img = F.dropout(their_msdff(theirs, "x_conv2", f_vox, inputs.image_features, ref, batch), 0.1, True)
    assert (got - (2 * f_vox + f_img)).abs().max() <= 1e-10
    assert (f_img == 0).any()


def test_sff_block_equals_their_forward():
    voxels, inputs, g = scene(2)
    theirs = random_official(g)
    maps, ignore = mssf_v_module_maps({"x_conv3": "fusion"}, fusion="sff")
    ignore += [f"{ENC}.{k}" for k in ("fusion_blocks.x_conv1", "fusion_blocks.x_conv2", "query_proj", "seg_heads")]
    sff = SFF([CI] * L, CV, dtype=D64, **OFFICIAL_SWITCHES["sff"])
    block = FusionBlock(sff, projector=VoxelCentroidProjector(**OFFICIAL_SWITCHES["projector"])).eval()
    block.load_state_dict(official_to_ours(theirs, maps, ignore), strict=True)
    _, ref = their_reference_points(voxels, inputs)
    batch = voxels.coords[:, 0].long()
    sampled = torch.stack([torch.cat([grid_at(lvl[batch[i]], ref[i:i + 1], True)[0] for lvl in inputs.image_features])
                           for i in range(len(batch))])
    pre = f"{ENC}.fusion_blocks.x_conv3.img_transform"
    want = voxels.features + bn_eval(linear(sampled, theirs, f"{pre}.0"), theirs, f"{pre}.1", 1e-3)
    assert (block(voxels, inputs).features - want).abs().max() <= 1e-10


def test_semantic_head_and_height_embedding_equal_theirs():
    _, _, g = scene(3)
    theirs = random_official(g)
    head = SemanticGuidedHead(CV, hidden=(5, 4)).double().eval()
    maps = [ModuleMap("semantic_head", f"{ENC}.seg_heads.x_conv3", "")]
    head.load_state_dict(official_to_ours(theirs, maps, ignore=[f"{ENC}.fusion_blocks", f"{ENC}.query_proj",
                                                                f"{ENC}.voxel_fuse"]), strict=True)
    x = torch.randn(9, CV, generator=g, dtype=D64)
    pre = f"{ENC}.seg_heads.x_conv3.seg_cls_layer"
    h = torch.relu(bn_eval(linear(x, theirs, f"{pre}.0", bias=False), theirs, f"{pre}.1", 1e-5))
    h = torch.relu(bn_eval(linear(h, theirs, f"{pre}.3", bias=False), theirs, f"{pre}.4", 1e-5))
    assert (head.logits(x) - linear(h, theirs, f"{pre}.6")[:, 0]).abs().max() <= 1e-10
    # MSSF-PP: nn.Embedding(D, C) of the BEV channels, looked up by the voxel's z index
    emb = {"pts_backbone.height_embeddings.weight": torch.randn(5, 3, generator=g, dtype=D64)}
    ours = HeightEmbedding(5, 3, dtype=D64)
    ours.load_state_dict(official_to_ours(emb, [ModuleMap("height_embedding", "pts_backbone.height_embeddings", "")]))
    z = torch.tensor([0, 4, 2, 2])
    assert torch.equal(ours(z), emb["pts_backbone.height_embeddings.weight"][z])


def test_round_trip_ours_theirs_ours_is_exact():
    g = torch.Generator().manual_seed(4)
    sw = OFFICIAL_SWITCHES
    ours = torch.nn.ModuleDict({
        "b1": FusionBlock(MSDFF(CI, CV, num_heads=M, num_levels=L, num_points=P, **sw["msdff"]),
                          query_init=QueryInit(CV, CI, CV, PCR, **sw["query_init"])),
        "b3": FusionBlock(SFF([CI] * L, CV, **sw["sff"])),
        "seg": SemanticGuidedHead(CV, hidden=(5, 4)),
    })
    with torch.no_grad():
        for t in ours.state_dict().values():
            if t.is_floating_point():
                t.copy_(torch.randn(t.shape, generator=g))
    sd = ours.state_dict()
    maps, _ = mssf_v_module_maps({"x_conv1": "b1.fusion", "x_conv3": "b3.fusion"}, query_init="b1.query_init",
                                 voxel_channels=CV, semantic_heads={"x_conv3": "seg"})
    maps[1] = ModuleMap("sff", maps[1].theirs, maps[1].ours)
    theirs = ours_to_official(sd, maps)
    assert theirs[f"{ENC}.query_proj.0.weight"].shape == (CV, CI + CV + 3)
    # their column order: image, voxel, position
    w = sd["b1.query_init.linear.weight"]
    assert torch.equal(theirs[f"{ENC}.query_proj.0.weight"], torch.cat([w[:, CV:CV + CI], w[:, :CV], w[:, -3:]], 1))
    assert f"{ENC}.seg_heads.x_conv3.seg_cls_layer.6.bias" in theirs
    back = official_to_ours(theirs, maps)
    assert back.keys() == sd.keys()
    assert all(torch.equal(back[k], sd[k]) for k in sd)


def test_unmappable_keys_raise_naming_them():
    g = torch.Generator().manual_seed(5)
    theirs = random_official(g)
    maps, ignore = mssf_v_module_maps({"x_conv1": "f1", "x_conv2": "f2"}, query_init="qi", voxel_channels=CV,
                                      semantic_heads={"x_conv3": "seg"})
    maps.append(ModuleMap("sff", f"{ENC}.fusion_blocks.x_conv3", "f3"))
    official_to_ours(theirs, maps, ignore)  # everything maps, the dead img_transform is ignored
    with pytest.raises(MSSFError, match=r"voxel_fuse\.img_transform\.0\.weight"):
        official_to_ours(theirs, maps)  # the dead weights are not dropped silently
    extra = dict(theirs)
    extra[f"{ENC}.fusion_blocks.x_conv1.img_cross_att.deformable_attention.level_embeds"] = torch.zeros(2)
    extra["pts_backbone.blocks.0.0.weight"] = torch.zeros(1)
    with pytest.raises(MSSFError, match=r"2 key\(s\).*level_embeds.*pts_backbone\.blocks\.0\.0\.weight.*ignore="):
        official_to_ours(extra, maps, ignore)
    # ours -> theirs: an MSDFF built with our norm has tensors their module does not
    normed = {f"f.{k}": v for k, v in MSDFF(CI, CV, num_heads=M, num_levels=L, num_points=P).state_dict().items()}
    with pytest.raises(MSSFError, match=r"f\.norm\.running_mean"):
        ours_to_official(normed, [ModuleMap("msdff", "x", "f")])
    with pytest.raises(MSSFError, match="voxel_channels"):
        ModuleMap("query_init", "a", "b")
    with pytest.raises(MSSFError, match="kind"):
        ModuleMap("lateral_conv", "a", "b")
    with pytest.raises(MSSFError, match=r"query_proj\.0\.weight"):
        official_to_ours({f"{ENC}.query_proj.0.weight": torch.zeros(4, 5)},
                         [ModuleMap("query_init", f"{ENC}.query_proj", "qi", voxel_channels=CV)])


def test_switch_arguments_are_checked():
    with pytest.raises(MSSFError, match="add_query"):
        MSDFF(8, 8, add_query=1)
    with pytest.raises(MSSFError, match="output_dropout"):
        MSDFF(8, 8, output_dropout=1.0)
    with pytest.raises(MSSFError, match="position"):
        QueryInit(2, 2, 2, PCR, position="centre")
    with pytest.raises(MSSFError, match="align_corners"):
        SFF([2], 2, align_corners="yes")
    with pytest.raises(MSSFError, match="half_pixel"):
        VoxelCentroidProjector(half_pixel=0)


def test_corner_origin_image_augmentation_is_their_apply_img_aug():
    from mssf_blocks.geometry import image_augmentation_matrix

    # their apply_img_aug: pts * scale_factor - crop_offset, then u -> W_img - u (img_shape before padding)
    g = torch.Generator().manual_seed(6)
    uv = torch.rand(20, 2, generator=g, dtype=D64) * torch.tensor([1936.0, 1216.0], dtype=D64)
    scale = torch.tensor([1333 / 1936, 800 / 1216], dtype=D64)
    want = uv * scale - torch.tensor([7.0, 3.0], dtype=D64)
    want[:, 0] = 1300 - want[:, 0]
    a, size = image_augmentation_matrix((1216, 1936), resize=(800, 1333), crop=(3, 7, 790, 1300), flip=True,
                                        corner_origin=True)
    got = (torch.cat([uv, torch.ones(20, 1, dtype=D64)], 1) @ a.T)[:, :2]
    assert size == (790, 1300) and (got - want).abs().max() <= 1e-9
    # ours (pixel centres): the flip differs by exactly one pixel, the resize by 0.5 (s - 1)
    ours, _ = image_augmentation_matrix((1216, 1936), flip=True)
    theirs, _ = image_augmentation_matrix((1216, 1936), flip=True, corner_origin=True)
    assert torch.equal(theirs - ours, torch.tensor([[0, 0, 1.0], [0, 0, 0], [0, 0, 0]], dtype=D64))
    with pytest.raises(MSSFError, match="corner_origin"):
        image_augmentation_matrix((4, 4), corner_origin=1)
