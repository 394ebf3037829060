"""The MSSF authors' checkpoints: key maps and conversion (``authors_checkpoint.py``, ``authors_pp_keys.py``
for the pillar stage) and strict loading (``load_authors_checkpoint.py``); ``docs/differences.md``."""

from mssf_blocks.weights.authors_checkpoint import ModuleMap, mssf_v_module_maps, official_to_ours, ours_to_official
from mssf_blocks.weights.authors_pp_keys import mssf_pp_stage_maps
from mssf_blocks.weights.load_authors_checkpoint import load_official

__all__ = ["ModuleMap", "official_to_ours", "ours_to_official", "mssf_v_module_maps", "mssf_pp_stage_maps",
           "load_official"]
