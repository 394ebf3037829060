"""The image samplers of a fusion block: :class:`SFF` (paper eq. 6-7), :class:`MSDFF` (eq. 9-10) with its
query :class:`QueryInit` (eq. 8), and :class:`FusionInputs`, the camera side they read. One per file,
named after it; ``_layers.py`` and ``_msdff_pairs.py`` are their private helpers."""

from mssf_blocks.samplers.fusion_inputs import FusionInputs
from mssf_blocks.samplers.msdff import MSDFF
from mssf_blocks.samplers.query_init import QueryInit
from mssf_blocks.samplers.sff import SFF, sample_at_projection

__all__ = ["FusionInputs", "SFF", "MSDFF", "QueryInit", "sample_at_projection"]
