"""Strict loading of the authors' tensors: missing / extra tensors and wrong shapes are errors, checked
before anything is copied (issue 33)."""

from __future__ import annotations

import pytest
import torch

from mssf_blocks.weights.authors_checkpoint import OFFICIAL_SWITCHES
from mssf_blocks.weights import ModuleMap, load_official, official_to_ours
from mssf_blocks.errors import MSSFError
from mssf_blocks.samplers import MSDFF, QueryInit

ENC = "pts_middle_encoder"
PCR = (0.0, -4.0, -1.0, 8.0, 4.0, 1.0)


def _theirs_query_init(c_vox, c_img, c_out, seed=0):
    g = torch.Generator().manual_seed(seed)
    pre = f"{ENC}.query_proj"
    return {f"{pre}.0.weight": torch.randn(c_out, c_img + c_vox + 3, generator=g),
            f"{pre}.0.bias": torch.randn(c_out, generator=g),
            f"{pre}.1.weight": torch.rand(c_out, generator=g) + 0.5, f"{pre}.1.bias": torch.randn(c_out, generator=g),
            f"{pre}.1.running_mean": torch.randn(c_out, generator=g),
            f"{pre}.1.running_var": torch.rand(c_out, generator=g) + 0.5,
            f"{pre}.1.num_batches_tracked": torch.tensor(3)}


def _params(module):
    return {k: v.clone() for k, v in module.state_dict().items()}


def test_load_official_loads_and_permutes_exactly():
    theirs = _theirs_query_init(4, 6, 4)
    qi = QueryInit(4, 6, 4, PCR, **OFFICIAL_SWITCHES["query_init"])
    loaded = load_official(qi, theirs, [ModuleMap("query_init", f"{ENC}.query_proj", "", voxel_channels=4)])
    w = theirs[f"{ENC}.query_proj.0.weight"]  # [f_img (6) | f_vox (4) | p (3)] -> ours [f_vox | f_img | p]
    assert torch.equal(qi.linear.weight.detach(), torch.cat([w[:, 6:10], w[:, :6], w[:, 10:]], 1))
    assert torch.equal(qi.norm.running_var, theirs[f"{ENC}.query_proj.1.running_var"])
    assert "linear.weight" in loaded


def test_wrong_voxel_channels_is_refused_before_copying():
    # their query_proj for C_vox = 4 (C_in = 6 + 4 + 3 = 13); a map that says 8 would permute the
    # columns at the wrong place while every shape still fits
    theirs = _theirs_query_init(4, 6, 4)
    qi = QueryInit(4, 6, 4, PCR)
    before = _params(qi)
    with pytest.raises(MSSFError, match=r"voxel_channels=2.*voxel_channels=4"):
        load_official(qi, theirs, [ModuleMap("query_init", f"{ENC}.query_proj", "", voxel_channels=2)])
    assert all(torch.equal(before[k], v) for k, v in qi.state_dict().items())


def test_shape_mismatch_names_tensor_and_both_shapes_nothing_copied():
    theirs = _theirs_query_init(4, 6, 4)
    qi = QueryInit(4, 7, 4, PCR)  # another image width: weight (4, 14) against their (4, 13)
    before = _params(qi)
    with pytest.raises(MSSFError, match=r"linear\.weight: module \(4, 14\), checkpoint \(4, 13\)"):
        load_official(qi, theirs, [ModuleMap("query_init", f"{ENC}.query_proj", "", voxel_channels=4)])
    assert all(torch.equal(before[k], v) for k, v in qi.state_dict().items())


def test_missing_tensor_is_an_error_unless_ignored():
    theirs = _theirs_query_init(4, 6, 4)
    del theirs[f"{ENC}.query_proj.1.running_var"]
    maps = [ModuleMap("query_init", f"{ENC}.query_proj", "", voxel_channels=4)]
    with pytest.raises(MSSFError, match=r"query_proj\.1\.running_var"):
        official_to_ours(theirs, maps)
    qi = QueryInit(4, 6, 4, PCR)
    with pytest.raises(MSSFError, match=r"running_var"):
        load_official(qi, theirs, maps)
    # named in ignore: skipped on purpose, the module keeps its own running_var
    load_official(qi, theirs, maps, ignore=[f"{ENC}.query_proj.1.running_var"])
    assert torch.equal(qi.norm.running_var, torch.ones(4))
    assert torch.equal(qi.norm.running_mean, theirs[f"{ENC}.query_proj.1.running_mean"])


def test_extra_converted_tensor_is_an_error():
    m = MSDFF(6, 4, num_heads=2, num_levels=1, num_points=1, **OFFICIAL_SWITCHES["msdff"])
    sd = {f"x.img_cross_att.deformable_attention.{k}": v for k, v in m.state_dict().items()}
    # mapped to a prefix the module does not have
    with pytest.raises(MSSFError, match=r"does not have: wrong\.sampling_offsets\.weight"):
        load_official(m, sd, [ModuleMap("msdff", "x", "wrong")])
    # an MSDFF with our norm: their checkpoint has no norm tensors -> missing, named
    normed = MSDFF(6, 4, num_heads=2, num_levels=1, num_points=1)
    with pytest.raises(MSSFError, match=r"norm\.weight"):
        load_official(normed, sd, [ModuleMap("msdff", "x", "")])
    load_official(normed, sd, [ModuleMap("msdff", "x", "")], ignore=["norm"])
    assert torch.equal(normed.value_proj.weight, m.value_proj.weight)
