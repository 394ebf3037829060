"""Pillar networks (paper Sec. III-G): :class:`PillarLift` (BEV -> voxels and back) and
:class:`HeightEmbedding`; the pure functions are in :mod:`mssf_blocks.functional.lift`."""

from mssf_blocks.lift.height_embedding import HeightEmbedding
from mssf_blocks.lift.pillar_lift import PillarLift

__all__ = ["PillarLift", "HeightEmbedding"]
