"""Deployment helpers: the static-shape path switch (``torch.compile`` / ``torch.export`` / ONNX).

See ``docs/deployment.md``. While a graph is captured the blocks take their static-shape path on their
own; :func:`static_path` forces it in eager mode.
"""

from __future__ import annotations

from ._static import static_path, use_static_path

__all__ = ["static_path", "use_static_path", "PYTREE_FIELDS"]


# ---------------------------------------------------------------------------------------------------
# pytree registration: SparseVoxels, FusionInputs and CentroidProjection as export inputs / outputs
# ---------------------------------------------------------------------------------------------------
# torch.export and the dynamo ONNX exporter flatten their inputs and outputs with torch's pytree: the
# tensors of these dataclasses become graph inputs (in the order of the field lists below), the other
# fields (grid, sizes) become part of the graph's input spec, fixed at export time.
from typing import Any, List, Tuple  # noqa: E402

from . import _compat  # noqa: E402
from .fusion import FusionInputs  # noqa: E402
from .geometry import CentroidProjection  # noqa: E402
from .sparse import SparseVoxels  # noqa: E402

#: graph-input tensors of each dataclass, in pytree order; the remaining fields are static context
PYTREE_FIELDS = {
    SparseVoxels: ("features", "coords"),
    FusionInputs: ("image_features", "lidar2img", "points", "points_batch", "points_to_sensor"),
    CentroidProjection: ("uv", "depth", "valid", "centroid", "has_points", "batch_index"),
}
_STATIC_FIELDS = {
    SparseVoxels: ("spatial_shape", "batch_size", "voxel_size", "point_range_min", "stride"),
    FusionInputs: ("image_size",),
    CentroidProjection: (),
}


def _register(cls: type) -> None:
    children, static = PYTREE_FIELDS[cls], _STATIC_FIELDS[cls]

    def get(obj: Any, f: str) -> Any:
        # sequences as lists (FusionInputs stores its levels as a tuple): the ONNX exporter turns the
        # tuples of a dynamic_shapes spec into lists before matching it against the inputs
        value = getattr(obj, f)
        return list(value) if isinstance(value, tuple) else value

    def flatten(obj: Any) -> Tuple[List[Any], Tuple[Any, ...]]:
        return [get(obj, f) for f in children], tuple(getattr(obj, f) for f in static)

    def flatten_with_keys(obj: Any):
        # MappingKey (obj['points']), not GetAttrKey (obj.points): torch 2.13's export guard code substitutes
        # paths as text, and obj.points is a prefix of obj.points_batch (a SyntaxError in ep.module()).
        return [(_compat.mapping_key(f), get(obj, f)) for f in children], tuple(getattr(obj, f) for f in static)

    def unflatten(values: List[Any], context: Tuple[Any, ...]) -> Any:
        kwargs = dict(zip(children, values))
        kwargs.update(zip(static, context))
        return cls(**kwargs)

    def to_dumpable(context: Tuple[Any, ...]) -> str:
        import json

        return json.dumps([list(c) if isinstance(c, tuple) else c for c in context])

    def from_dumpable(text: str) -> Tuple[Any, ...]:
        import json

        return tuple(tuple(c) if isinstance(c, list) else c for c in json.loads(text))

    _compat.register_pytree_node(
        cls, flatten, unflatten, serialized_type_name=f"mssf_blocks.{cls.__name__}",
        flatten_with_keys=flatten_with_keys, to_dumpable=to_dumpable, from_dumpable=from_dumpable,
    )


for _cls in PYTREE_FIELDS:
    _register(_cls)
