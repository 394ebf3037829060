"""A whole MSSF-V fusion stage as the authors run it, in float64: their ``x_conv2`` of
``SparseEncoderVoxelNeXtFuse`` with the ablation config ``vx_mm_r50_ablation_n2m4`` (fusion at x_conv1 and
x_conv2, the semantic head at x_conv2).

Their forward of that stage, as we read ``SparseEncoderVoxelNeXtFuse.forward`` (``fuse_after_residual``
False, ``query_voxel_fuse_method='add'``, ``apply_seg_scores_method='mul'``):

1. ``conv2[0]``: ``SparseConv3d(3, stride 2, padding 1)`` + ``BN1d(eps=1e-3)`` + ReLU;
2. the MSDFF fusion block: ``x[inds] += updated_query`` with ``updated_query = msdff(f_vox) + f_vox``;
3. the semantic head on the fused features, ``x[inds] *= sigmoid(logits)``;
4. ``conv2[1]``, ``conv2[2]``: two ``SparseBasicBlock`` s.

The reference is the naive re-implementation (``authors_sparse_reference.py``, the MSDFF and head of
``test_authors_forward.py``); our side is a :class:`FusionBlock` with spconv layers, loaded through the
converter (fusion, head) and by their layer names (convs).
"""

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
pytest.importorskip("spconv")
import spconv.pytorch as spconv  # noqa: E402
from torch import nn  # noqa: E402

from authors_sparse_reference import as_sites, basic_block, bn_eval, conv_module  # noqa: E402
from mssf_blocks.blocks import FusionBlock  # noqa: E402
from mssf_blocks.weights.authors_checkpoint import OFFICIAL_SWITCHES  # noqa: E402
from mssf_blocks.weights import ModuleMap, official_to_ours
from mssf_blocks.samplers import MSDFF  # noqa: E402
from mssf_blocks.geometry import VoxelCentroidProjector  # noqa: E402
from mssf_blocks.heads import SemanticGuidedHead  # noqa: E402
from mssf_examples.models.backbones import SparseBasicBlock  # noqa: E402
from test_authors_forward import (  # noqa: E402
    CI, CV, D64, ENC, IMAGE, LO, VOXEL, L, M, P, linear, random_official, scene, their_msdff,
)

pytestmark = pytest.mark.usefixtures("one_thread")


def their_stage_weights(g):
    sd = random_official(g)

    def r(*shape, scale=0.3):
        return torch.randn(*shape, generator=g, dtype=D64) * scale

    def bn(prefix, c):
        sd.update({f"{prefix}.weight": 1 + r(c, scale=0.2), f"{prefix}.bias": r(c, scale=0.2),
                   f"{prefix}.running_mean": r(c, scale=0.3),
                   f"{prefix}.running_var": 0.5 + torch.rand(c, generator=g, dtype=D64),
                   f"{prefix}.num_batches_tracked": torch.tensor(3)})

    sd[f"{ENC}.conv2.0.0.weight"] = r(CV, 3, 3, 3, CV)
    bn(f"{ENC}.conv2.0.1", CV)
    for j in (1, 2):
        for c in (1, 2):
            sd[f"{ENC}.conv2.{j}.conv{c}.weight"] = r(CV, 3, 3, 3, CV, scale=0.15)
            bn(f"{ENC}.conv2.{j}.bn{c}", CV)
    pre = f"{ENC}.seg_heads.x_conv2.seg_cls_layer"
    sd.update({f"{pre}.0.weight": r(5, CV), f"{pre}.3.weight": r(4, 5), f"{pre}.6.weight": r(1, 4), f"{pre}.6.bias": r(1)})
    bn(f"{pre}.1", 5)
    bn(f"{pre}.4", 4)
    return sd


def centroid_reference_points(coords, inputs, stride):
    """Their voxel_aggregation_utils centroid at ``stride`` (voxel centre when empty), then ``u / W_pad``."""
    size = torch.tensor(VOXEL, dtype=D64) * stride
    lo = torch.tensor(LO, dtype=D64)
    idx = ((inputs.points - lo) / size).floor().long()
    ref = torch.zeros(len(coords), 2, dtype=D64)
    for i, (b, z, y, x) in enumerate(coords):
        mine = (inputs.points_batch == b) & (idx[:, 0] == x) & (idx[:, 1] == y) & (idx[:, 2] == z)
        cent = inputs.points[mine].mean(0) if mine.any() else (torch.tensor([x, y, z], dtype=D64) + 0.5) * size + lo
        cam = inputs.lidar2img[b] @ torch.cat([cent, torch.ones(1, dtype=D64)])
        ref[i] = torch.stack([cam[0] / cam[2] / IMAGE[1], cam[1] / cam[2] / IMAGE[0]])
    return ref


def their_stage(sd, voxels, inputs):
    x = as_sites(voxels.features, voxels.coords)
    x = conv_module(x, sd, f"{ENC}.conv2.0", stride=(2, 2, 2), padding=(1, 1, 1), out_shape=(2, 8, 8))
    coords = sorted(x)
    f_vox = torch.stack([x[c] for c in coords])
    ref = centroid_reference_points(coords, inputs, 2)
    batch = torch.tensor([c[0] for c in coords])
    fused = f_vox + (their_msdff(sd, "x_conv2", f_vox, inputs.image_features, ref, batch) + f_vox)
    pre = f"{ENC}.seg_heads.x_conv2.seg_cls_layer"
    h = torch.relu(bn_eval(linear(fused, sd, f"{pre}.0", bias=False), sd, f"{pre}.1", 1e-5))
    h = torch.relu(bn_eval(linear(h, sd, f"{pre}.3", bias=False), sd, f"{pre}.4", 1e-5))
    logits = linear(h, sd, f"{pre}.6")[:, 0]
    x = {c: fused[i] * torch.sigmoid(logits[i]) for i, c in enumerate(coords)}
    x = basic_block(basic_block(x, sd, f"{ENC}.conv2.1"), sd, f"{ENC}.conv2.2")
    return x, dict(zip(coords, logits))


def our_stage(sd, head_position):
    sw = OFFICIAL_SWITCHES
    down = spconv.SparseSequential(
        spconv.SparseConv3d(CV, CV, 3, stride=2, padding=1, bias=False, indice_key="spconv2"),
        nn.BatchNorm1d(CV, eps=1e-3, momentum=0.01), nn.ReLU())
    blocks = spconv.SparseSequential(SparseBasicBlock(CV, "res2"), SparseBasicBlock(CV, "res2"))
    block = FusionBlock(MSDFF(CI, CV, num_heads=M, num_levels=L, num_points=P, **sw["msdff"]),
                        downsample=down, blocks=blocks, projector=VoxelCentroidProjector(**sw["projector"]),
                        semantic_head=SemanticGuidedHead(CV, hidden=(5, 4)), head_position=head_position)
    block = block.double().eval()
    maps = [ModuleMap("msdff", f"{ENC}.fusion_blocks.x_conv2", "fusion"),
            ModuleMap("semantic_head", f"{ENC}.seg_heads.x_conv2", "semantic_head")]
    theirs = {k: v for k, v in sd.items() if "fusion_blocks.x_conv2" in k or "seg_heads.x_conv2" in k}
    ours = official_to_ours(theirs, maps)
    rename = {"conv2.0.0": "downsample.0", "conv2.0.1": "downsample.1", "conv2.1": "blocks.0", "conv2.2": "blocks.1"}
    for k, v in sd.items():
        for src, dst in rename.items():
            if k.startswith(f"{ENC}.{src}."):
                ours[dst + k[len(ENC) + len(src) + 1:]] = v
    block.load_state_dict(ours, strict=True)
    return block


def test_fusion_stage_with_the_head_where_the_authors_put_it_equals_theirs():
    voxels, inputs, g = scene(11)
    sd = their_stage_weights(g)
    want, want_logits = their_stage(sd, voxels, inputs)
    out, head_voxels, logits = our_stage(sd, "after_fusion")(voxels, inputs, return_logits=True)
    assert out.stride == (2, 2, 2) and len(want) == out.num_voxels > 10
    got = as_sites(out.features, out.coords)
    err = max((got[s] - want[s]).abs().max().item() for s in want)
    assert err <= 1e-9
    got_logits = as_sites(logits[:, None], head_voxels.coords)
    assert max(abs(got_logits[s].item() - want_logits[s].item()) for s in want_logits) <= 1e-9
    # the head after the residual blocks (our former default) is a different network
    other = our_stage(sd, "after_residual")(voxels, inputs)
    other_sites = as_sites(other.features, other.coords)
    assert max((other_sites[s] - want[s]).abs().max().item() for s in want) > 1e-3
