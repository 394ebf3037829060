"""Strict loading of the MSSF authors' tensors into our modules: every key and shape checked first.

:func:`~mssf_blocks.weights.official_to_ours` renames their tensors; :func:`load_official`
also holds the result against the target module before a single value is copied, so a checkpoint that
does not fit (a missing or extra tensor, another width, a wrong ``voxel_channels`` for the query
initialiser, whose column permutation keeps the shape) fails with the tensor named, never half loaded.
"""

from __future__ import annotations

from typing import List, Mapping, Sequence

import torch
from torch import Tensor, nn

from mssf_blocks.errors import MSSFError
from mssf_blocks.weights.authors_checkpoint import ModuleMap, official_to_ours

__all__ = ["load_official"]


def _under(key: str, prefix: str) -> bool:
    return not prefix or key == prefix or key.startswith(prefix + ".")


def _shown(keys: Sequence[str]) -> str:
    return ", ".join(keys[:12]) + (f", ... ({len(keys)} in all)" if len(keys) > 12 else "")


def load_official(module: nn.Module, state_dict: Mapping[str, Tensor], maps: Sequence[ModuleMap],
                  ignore: Sequence[str] = (), strict: bool = True) -> List[str]:
    """Load their tensors of the mapped modules into ``module``, strictly by default.

    Args:
        module: the model (or block) whose state dict holds every map's ``ours`` prefix.
        state_dict: their state dict.
        maps: the modules to load (:func:`~mssf_blocks.weights.mssf_v_module_maps`).
        ignore: prefixes that may be skipped: of their keys (left out of the conversion) or of ours
            (tensors of a mapped module allowed to keep their initial values).
        strict: ``True`` (default): a tensor of a mapped module missing on either side, or a converted
            tensor the module does not have, is an error. ``False``: only shapes are enforced.

    Returns:
        Our keys that were loaded.

    Raises:
        MSSFError: naming the tensors that are missing or extra, or the tensor whose shape differs
            from the module's (both shapes), or a query-init map whose ``voxel_channels`` is not the
            module's; nothing is copied then.
    """
    if not isinstance(module, nn.Module):
        raise MSSFError(f"module: expected an nn.Module, got {type(module).__name__}")
    ours = official_to_ours(state_dict, maps, ignore, strict=strict)
    target = module.state_dict()
    modules = dict(module.named_modules())
    for m in maps:
        if m.kind != "query_init":
            continue
        sub = modules.get(m.ours)
        have = getattr(sub, "voxel_channels", None)
        if isinstance(have, int) and have != m.voxel_channels:
            raise MSSFError(
                f"maps: the query_init map of {m.theirs!r} has voxel_channels={m.voxel_channels}, but the "
                f"module at {m.ours!r} has voxel_channels={have}: their [f_img | f_vox | p] columns would be "
                "split at the wrong place; pass the module's voxel_channels"
            )
    extra = [k for k in ours if k not in target]
    if extra:
        raise MSSFError(f"state_dict: {len(extra)} converted tensor(s) that the module does not have: "
                        f"{_shown(extra)} (check the maps' ours= prefixes)")
    wrong = [f"{k}: module {tuple(target[k].shape)}, checkpoint {tuple(v.shape)}"
             for k, v in ours.items() if tuple(v.shape) != tuple(target[k].shape)]
    if wrong:
        raise MSSFError(f"state_dict: {len(wrong)} tensor(s) whose shape differs from the module's (nothing "
                        f"was loaded): " + "; ".join(wrong[:12]))
    if strict:
        theirs_of = {}  # our key -> their key, so an ignore= prefix of theirs also covers our tensor
        for m in maps:
            sfx = [k[len(m.theirs) + 1:] for k in state_dict if _under(k, m.theirs) and k != m.theirs]
            for t_sfx, o_sfx in m.rules(sfx):
                theirs_of[f"{m.ours}.{o_sfx}" if m.ours else o_sfx] = f"{m.theirs}.{t_sfx}"
        missing = [k for k in target if any(_under(k, m.ours) for m in maps) and k not in ours
                   and not k.endswith("num_batches_tracked")
                   and not any(_under(k, p) or _under(theirs_of.get(k, ""), p) for p in ignore)]
        if missing:
            raise MSSFError(
                f"state_dict: {len(missing)} tensor(s) of the mapped modules would keep their initial "
                f"values: {_shown(missing)}; pass their prefix in ignore=(...) to allow it"
            )
    with torch.no_grad():
        for k, v in ours.items():
            target[k].copy_(v)
    return list(ours)
