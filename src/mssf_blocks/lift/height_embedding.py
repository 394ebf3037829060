"""``HeightEmbedding``: a learnable vector per z index, the ``HeightEmb(z)`` of ``f_vox = BEV(x, y) +
HeightEmb(z)`` (paper Sec. III-G, "Extend to Pillar"; used by :class:`~mssf_blocks.lift.PillarLift`)."""

from __future__ import annotations


import torch
from torch import Tensor, nn

from mssf_blocks.checks.tensors import check_index_range, check_shape
from mssf_blocks.checks.arguments import check_positive_int
from mssf_blocks.errors import MSSFError

__all__ = ["HeightEmbedding"]


class HeightEmbedding(nn.Module):
    """A learnable vector per z index, zero-initialised (so lifting starts as a plain copy of the BEV).

    Args:
        num_z: number of z indices ``Z`` (the voxel grid's ``D``).
        channels: ``C``.

    Shapes:
        - z: ``(N,)`` integer indices in ``[0, Z)``.
        - output: ``(N, C)``.
    """

    def __init__(self, num_z: int, channels: int, device=None, dtype=None) -> None:
        super().__init__()
        self.num_z = check_positive_int(num_z, "num_z")
        self.channels = check_positive_int(channels, "channels")
        self.weight = nn.Parameter(torch.zeros(num_z, channels, device=device, dtype=dtype))

    def forward(self, z: Tensor) -> Tensor:
        check_shape(z, "z", ("N",))
        if z.dtype not in (torch.int32, torch.int64):
            raise MSSFError(f"z: expected an integer tensor of z indices, got dtype {z.dtype}")
        check_index_range(z, "z", self.num_z, "num_z")
        return self.weight[z.long()]

    def extra_repr(self) -> str:
        return f"num_z={self.num_z}, channels={self.channels}"
