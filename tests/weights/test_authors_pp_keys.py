"""The authors' two MSSF-PP fusion stages (``PointPillarsScatterFuse`` and ``SECONDFuse`` of
``EricLiuhhh/MSSF``) against :class:`PillarFusionStage` configured by ``OFFICIAL_SWITCHES``, in float64.

Their forward of one stage, as we read it (``fuse_bev=True`` in ``SECONDFuse``, the MSSF-PP config):

1. ``x = conv_input(radar voxels)``: a bias-free 3x3x3 submanifold convolution, no norm, no activation;
   ``SECONDFuse`` adds ``BEV[b, :, y, x] + height_embeddings(z)`` (the voxel grid at the map's x/y cells);
2. ``q = query_proj(cat(grid_sample(level0, align_corners=True), x, p))``; ``SECONDFuse`` adds
   ``BEV[b, :, y, x]`` to it;
3. ``x += msdff(q) + q`` (their attention's residual), then ``x *= sigmoid(seg_head(x))``;
4. the voxels summed per ``(b, y, x)`` into a dense map (zeros elsewhere), concatenated after the map
   the stage started from.

The reference is written from that reading with loops (``authors_sparse_reference.py`` for the
convolution, ``test_authors_forward.py`` for the MSDFF); weights are random tensors under their keys,
loaded through the converter only.
"""

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).parent))
pytest.importorskip("spconv")

from authors_sparse_reference import as_sites, bn_eval, subm_conv  # noqa: E402
from mssf_blocks.blocks import FusionBlock  # noqa: E402
from mssf_blocks.weights.authors_checkpoint import OFFICIAL_SWITCHES  # noqa: E402
from mssf_blocks.weights import official_to_ours
from mssf_blocks.weights.authors_pp_keys import mssf_pp_stage_maps  # noqa: E402
from mssf_blocks.errors import MSSFError  # noqa: E402
from mssf_blocks.samplers import MSDFF, QueryInit  # noqa: E402
from mssf_blocks.geometry import VoxelCentroidProjector  # noqa: E402
from mssf_blocks.heads import SemanticGuidedHead  # noqa: E402
from mssf_blocks.lift import PillarLift  # noqa: E402
from mssf_blocks.blocks.pillar_fusion_stage import PillarFusionStage  # noqa: E402
from test_authors_forward import (  # noqa: E402
    CI, CV, D64, ENC, L, M, P, PCR, grid_at, linear, random_official, scene, their_msdff, their_reference_points,
)

pytestmark = pytest.mark.usefixtures("one_thread")
CR, NZ = 3, 4  # raw point-feature channels, z cells of the lift grid (scene(): spatial (4, 16, 16))


def their_weights(g):
    sd = random_official(g)
    sd[f"{ENC}.conv_input.0.weight"] = torch.randn(CV, 3, 3, 3, CR, generator=g, dtype=D64) * 0.3
    sd[f"{ENC}.height_embeddings.weight"] = torch.randn(NZ, CV, generator=g, dtype=D64)
    for k in [k for k in sd if ".seg_heads.x_conv3." in k]:
        sd[k.replace("x_conv3", "x_conv1")] = sd.pop(k)
    return sd


def their_stage(sd, stage, voxels, raw, bev, inputs):
    coords = [tuple(int(v) for v in c) for c in voxels.coords]
    conv = subm_conv(as_sites(raw, voxels.coords), sd[f"{ENC}.conv_input.0.weight"])
    x = torch.stack([conv[c] for c in coords])
    b, z, y, xx = voxels.coords.long().T
    at_bev = bev[b, :, y, xx]
    if stage == "backbone":
        x = x + at_bev + sd[f"{ENC}.height_embeddings.weight"][z]
    cent, ref = their_reference_points(voxels, inputs)
    img0 = torch.stack([grid_at(inputs.image_features[0][b[i]], ref[i:i + 1], True)[0] for i in range(len(b))])
    lo, hi = torch.tensor(PCR[:3], dtype=D64), torch.tensor(PCR[3:], dtype=D64)
    q = bn_eval(linear(torch.cat([img0, x, (cent - lo) / (hi - lo)], 1), sd, f"{ENC}.query_proj.0"), sd,
                f"{ENC}.query_proj.1", 1e-5)
    if stage == "backbone":
        q = q + at_bev
    x = x + their_msdff(sd, "x_conv1", q, inputs.image_features, ref, b) + q
    pre = f"{ENC}.seg_heads.x_conv1.seg_cls_layer"
    h = torch.relu(bn_eval(linear(x, sd, f"{pre}.0", bias=False), sd, f"{pre}.1", 1e-5))
    h = torch.relu(bn_eval(linear(h, sd, f"{pre}.3", bias=False), sd, f"{pre}.4", 1e-5))
    logits = linear(h, sd, f"{pre}.6")[:, 0]
    x = x * torch.sigmoid(logits)[:, None]
    summed = torch.zeros_like(bev)
    for i in range(len(coords)):
        summed[b[i], :, y[i], xx[i]] += x[i]
    return torch.cat([bev, summed], 1), logits


def our_stage(sd, stage, merge=None):
    sw = OFFICIAL_SWITCHES
    lift_sw = sw["pillar_lift" if stage == "backbone" else "pillar_scatter_lift"]
    stage_sw = dict(sw["pillar_stage" if stage == "backbone" else "pillar_scatter_stage"])
    if merge is not None:
        stage_sw["merge"] = merge
    lift = PillarLift(CV, NZ, raw_channels=CR, dtype=D64, **lift_sw)
    block = FusionBlock(MSDFF(CI, CV, num_heads=M, num_levels=L, num_points=P, dtype=D64, **sw["msdff"]),
                        query_init=QueryInit(CV, CI, CV, PCR, dtype=D64, **sw["query_init"]),
                        projector=VoxelCentroidProjector(**sw["projector"]),
                        semantic_head=SemanticGuidedHead(CV, hidden=(5, 4), dtype=D64), **sw["fusion_block"])
    ours = PillarFusionStage(lift, block, **stage_sw).eval()
    enc = "middle_encoder" if stage == "scatter" else "backbone"
    theirs = {k.replace(ENC, enc): v for k, v in sd.items()
              if not any(s in k for s in ("x_conv2", "x_conv3", "height_embeddings" if stage == "scatter" else "@"))}
    maps, ignore = mssf_pp_stage_maps(stage, "", CV)
    ours.load_state_dict(official_to_ours(theirs, maps, ignore), strict=True)
    return ours


@pytest.mark.parametrize("stage", ["scatter", "backbone"])
def test_mssf_pp_stage_equals_theirs(stage):
    voxels, inputs, g = scene(21 if stage == "scatter" else 22)
    sd = their_weights(g)
    raw = torch.randn(voxels.num_voxels, CR, generator=g, dtype=D64)
    bev = torch.randn(2, CV, 16, 16, generator=g, dtype=D64)
    want, want_logits = their_stage(sd, stage, voxels, raw, bev, inputs)
    model = our_stage(sd, stage)
    got, head_voxels, logits = model(bev, voxels.replace(features=raw), inputs, return_logits=True)
    assert got.shape == (2, 2 * CV, 16, 16)
    assert (got - want).abs().max() <= 1e-9
    assert torch.equal(head_voxels.coords, voxels.coords) and (logits - want_logits).abs().max() <= 1e-9
    # the paper's merge (fused pillars replace the map's) is a different map
    paper = our_stage(sd, stage, merge="replace")(bev, voxels.replace(features=raw), inputs)
    assert paper.shape == bev.shape and (paper - want[:, CV:]).abs().max() > 1e-3


def test_pillar_stage_arguments_are_checked():
    lift = PillarLift(CV, NZ)
    block = FusionBlock(MSDFF(CI, CV, num_heads=M, num_levels=L, num_points=P))
    with pytest.raises(MSSFError, match="merge"):
        PillarFusionStage(lift, block, merge="sum")
    with pytest.raises(MSSFError, match="lift.channels"):
        PillarFusionStage(PillarLift(CV + 1, NZ), block)
    with pytest.raises(MSSFError, match="use_bev"):
        PillarLift(CV, NZ, use_bev=False)
    with pytest.raises(MSSFError, match="raw_channels"):
        PillarLift(CV, NZ, raw_channels=0)
    with pytest.raises(MSSFError, match="stage"):
        mssf_pp_stage_maps("neck", "", CV)
    voxels, inputs, _ = scene(23)
    with pytest.raises(MSSFError, match=r"raw voxel features \(N, 3\)"):
        PillarLift(CV, NZ, raw_channels=CR)(torch.zeros(2, CV, 16, 16), voxels)
