"""``MODEL.IMAGE_BRANCH.IMAGE_SIZE`` of the examples' OpenPCDet image branch: the levels are those of the resized
image, and the resize is recorded so that the fusion projects into it (no OpenPCDet import needed)."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F

from mssf_blocks import MSSFError
from mssf_examples.openpcdet.image_module import OpenPCDetImageBranch

CFG = dict(DEPTH=18, BASE_CHANNELS=4, FPN_CHANNELS=8, NUM_OUTS=4, FROZEN=False, MEAN=[0.4, 0.5, 0.6],
           STD=[0.2, 0.25, 0.3])


def test_levels_are_those_of_the_resized_image_and_the_resize_is_recorded():
    torch.manual_seed(0)
    module = OpenPCDetImageBranch({**CFG, "IMAGE_SIZE": [32, 48]}).eval()
    images = torch.rand(2, 3, 128, 200)
    batch = {"images": images.clone(), "batch_size": 2}
    with torch.no_grad():
        out = module(batch)
        resized = F.interpolate(images, size=(32, 48), mode="bilinear", align_corners=False, antialias=True)
        mean, std = torch.tensor(CFG["MEAN"]).view(1, 3, 1, 1), torch.tensor(CFG["STD"]).view(1, 3, 1, 1)
        ref = module.branch(((resized - mean) / std).unsqueeze(1))
    assert [tuple(lvl.shape) for lvl in out["image_fpn"]] == [(2, 8, 8, 12), (2, 8, 4, 6), (2, 8, 2, 3), (2, 8, 1, 2)]
    for got, want in zip(out["image_fpn"], ref):
        torch.testing.assert_close(got, want[:, 0])
    assert tuple(out["images"].shape) == (2, 3, 32, 48)  # the image the levels (and the fusion's size) come from
    m = out["img_aug_matrix"]
    assert tuple(m.shape) == (2, 1, 4, 4) and m.dtype == torch.float64
    # hand-worked: the image's outer corner (-0.5, -0.5) stays, its centre goes to the new centre
    for (u, v), (u2, v2) in (((-0.5, -0.5), (-0.5, -0.5)), ((99.5, 63.5), (23.5, 15.5)), ((199.5, 127.5), (47.5, 31.5))):
        p = m[1, 0] @ torch.tensor([u, v, 1.0, 1.0], dtype=torch.float64)
        torch.testing.assert_close(p[:2], torch.tensor([u2, v2], dtype=torch.float64))


def test_images_already_at_the_size_pass_unchanged():
    module = OpenPCDetImageBranch({**CFG, "IMAGE_SIZE": [32, 48]}).eval()
    batch = {"images": torch.rand(1, 3, 32, 48), "batch_size": 1}
    with torch.no_grad():
        module(batch)
    assert "img_aug_matrix" not in batch


@pytest.mark.parametrize("bad", [[32], [0, 48], "32x48"])
def test_bad_image_size_names_the_key(bad):
    with pytest.raises(MSSFError, match="MODEL.IMAGE_BRANCH.IMAGE_SIZE"):
        OpenPCDetImageBranch({**CFG, "IMAGE_SIZE": bad})
