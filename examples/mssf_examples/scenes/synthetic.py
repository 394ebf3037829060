"""Deterministic synthetic 4D-radar + camera scenes that reproduce the effects the MSSF paper builds on.

Real 4D-radar data (VoD, TJ4DRadSet) cannot ship with the library, yet the examples need data on which
an image really helps a radar detector. These scenes are built so that it does, for the reasons the
paper gives (Sec. I, IV-C, Fig. 1):

* **Radar alone is ambiguous.** Static clutter (poles, walls, guard rails, car-sized and person-sized
  boxes) returns points with the same point counts, RCS and (zero) Doppler as static cars, pedestrians
  and cyclists; a pole looks like a pedestrian. Pedestrians and cyclists have similar radar
  footprints (a cyclist's returns come mostly from the rider). Moving objects stand out by Doppler, as
  on real radar.
* **The camera disambiguates.** Cars, pedestrians and cyclists render with class-specific colour, shape
  and texture (car bodies with windows, wheels and lamps; people with head, torso and legs; riders on
  two wheels); clutter renders in the desaturated greys of the background.
* **3D-blurred points.** Multipath ghosts behind objects (carrying the object's Doppler), clutter behind
  objects that leaks through occlusion, and noise points project into an object's 2D box without lying
  in its 3D box (paper Fig. 1); ``Scene.blurred_point_mask`` marks them.
* **Lighting** normal / dark / dazzle (TJ4DRadSet analysis, Sec. IV-D) with the paper's shares
  60 / 15 / 25 % by default.

Geometry follows VoD: radar frame ``x`` forward, ``y`` left, ``z`` up, radar behind the bumper at
``radar_height`` above a flat ground, a camera above and behind it with VoD's intrinsics scaled from
1936 x 1216 to a small image, ``multi-scan`` accumulation with ego-motion compensation and a time
index. Points use VoD's channel order ``[x, y, z, RCS, v_r, v_rc, t]``.

Everything is generated with numpy from one integer seed, so a scene is a pure function of
``(seed, config)``. See ``docs/scenes.md`` for pictures and limits.

The generator's parts: :mod:`~mssf_examples.scenes.config` (names, radar signatures,
:class:`SceneConfig`), :mod:`~mssf_examples.scenes.geometry` (box geometry),
:mod:`~mssf_examples.scenes.layout` (object and clutter placement), :mod:`~mssf_examples.scenes.radar`
(radar simulation), :mod:`~mssf_examples.scenes.camera` (image rendering); this module holds
:class:`Scene`, :func:`generate_scene` and :class:`SyntheticDataset` and re-exports the public names.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Optional, Sequence, Tuple

import numpy as np
import torch
from torch import Tensor

from mssf_blocks.errors import MSSFError

from .camera import _render
from .config import CLASS_NAMES, CLUTTER_KINDS, LIGHTING_CONDITIONS, POINT_SOURCES, SceneConfig
from .geometry import box_corners, points_in_box
from .layout import _grey, _hsv, _layout
from .radar import _radar

__all__ = [
    "CLASS_NAMES",
    "CLUTTER_KINDS",
    "LIGHTING_CONDITIONS",
    "POINT_SOURCES",
    "SceneConfig",
    "Scene",
    "generate_scene",
    "scene_seed",
    "SyntheticDataset",
    "box_corners",
    "points_in_box",
]

_SPLITS = {"train": 0, "val": 1, "test": 2}


@dataclass
class Scene:
    """One synthetic radar + camera frame (all tensors on CPU).

    Attributes:
        points: ``(P, 7)`` float32 ``[x, y, z, RCS, v_r, v_rc, t]`` in the sensor frame; ``v_r`` relative
            and ``v_rc`` ego-compensated radial velocity (positive = moving away), ``t`` the scan index
            (``0`` newest, ``-1`` one scan earlier, ...).
        image: ``(3, H, W)`` float32 RGB in ``[0, 1]``.
        lidar2img: ``(3, 4)`` float64 sensor -> pixels, ``(u*d, v*d, d)``, OpenCV pixel centres.
        intrinsics: ``(3, 3)`` float64 camera matrix; sensor_to_camera: ``(4, 4)`` float64.
        gt_boxes: ``(G, 7)`` float32 ``(x, y, z_centre, dx, dy, dz, yaw)`` at the newest scan.
        gt_labels: ``(G,)`` int64, indices into :data:`CLASS_NAMES`.
        gt_boxes_2d: ``(G, 4)`` float32 ``(left, top, right, bottom)``: the box's 8 projected corners'
            extent clipped to ``[0, W - 1] x [0, H - 1]``.
        gt_velocity: ``(G, 2)`` float32 absolute ``(vx, vy)``; gt_moving: ``(G,)`` bool.
        clutter_boxes: ``(K, 7)`` float32; clutter_kinds: ``(K,)`` int64 into :data:`CLUTTER_KINDS`.
        lighting: one of :data:`LIGHTING_CONDITIONS`.
        blurred_point_mask: ``(P,)`` bool, projects (depth > 0) into some GT 2D box but lies in no GT 3D box.
        point_is_clutter: ``(P,)`` bool, returns of clutter items.
        point_source: ``(P,)`` int64 into :data:`POINT_SOURCES` (object surface, multipath ghost, clutter,
            background noise).
        point_object_index: ``(P,)`` int64 GT index of object and ghost points, ``-1`` otherwise.
        instance_map: ``(H, W)`` int64 which item is visible at each pixel: ``-1`` background,
            ``0..G-1`` objects, ``G..G+K-1`` clutter (before lighting).
        ego_velocity: ``(2,)`` float32 ego ``(vx, vy)``.
        seed: the seed the scene was generated from.
    """

    points: Tensor
    image: Tensor
    lidar2img: Tensor
    intrinsics: Tensor
    sensor_to_camera: Tensor
    gt_boxes: Tensor
    gt_labels: Tensor
    gt_boxes_2d: Tensor
    gt_velocity: Tensor
    gt_moving: Tensor
    clutter_boxes: Tensor
    clutter_kinds: Tensor
    lighting: str
    blurred_point_mask: Tensor
    point_is_clutter: Tensor
    point_source: Tensor
    point_object_index: Tensor
    instance_map: Tensor
    ego_velocity: Tensor
    seed: int

    @property
    def image_size(self) -> Tuple[int, int]:
        """``(H, W)``."""
        return int(self.image.shape[1]), int(self.image.shape[2])

    def to_batch(self):
        """A one-sample :class:`mssf_examples.data.batch.RadarCameraBatch` (use :meth:`collate` for several)."""
        return Scene.collate([self])

    @staticmethod
    def collate(scenes: Sequence["Scene"]):
        """Stack scenes into a :class:`mssf_examples.data.batch.RadarCameraBatch` with ``V = 1`` camera."""
        from ..data.batch import RadarCameraBatch  # local: keep scenes importable without the detector code

        if len(scenes) == 0:
            raise MSSFError("scenes: expected at least one Scene, got an empty sequence")
        return RadarCameraBatch(
            points=[s.points for s in scenes],
            lidar2img=torch.stack([s.lidar2img.float() for s in scenes])[:, None],
            images=torch.stack([s.image for s in scenes])[:, None],
            gt_boxes=[s.gt_boxes for s in scenes],
            gt_labels=[s.gt_labels for s in scenes],
        )


def _boxes_2d(boxes: np.ndarray, lidar2img: np.ndarray, image_size: Tuple[int, int]) -> np.ndarray:
    if len(boxes) == 0:
        return np.zeros((0, 4))
    corners = box_corners(boxes)
    hom = np.concatenate([corners, np.ones(corners.shape[:2] + (1,))], -1) @ lidar2img.T
    uv = hom[..., :2] / hom[..., 2:3]
    h, w = image_size
    lo, hi = uv.min(1), uv.max(1)
    return np.stack([np.clip(lo[:, 0], 0, w - 1), np.clip(lo[:, 1], 0, h - 1),
                     np.clip(hi[:, 0], 0, w - 1), np.clip(hi[:, 1], 0, h - 1)], 1)


def _blurred(points: np.ndarray, boxes: np.ndarray, boxes_2d: np.ndarray, lidar2img: np.ndarray) -> np.ndarray:
    if len(points) == 0 or len(boxes) == 0:
        return np.zeros(len(points), dtype=bool)
    hom = np.concatenate([points[:, :3], np.ones((len(points), 1))], 1) @ lidar2img.T
    d = hom[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = hom[:, :2] / d[:, None]
    in2d = ((uv[:, None, 0] >= boxes_2d[None, :, 0]) & (uv[:, None, 0] <= boxes_2d[None, :, 2])
            & (uv[:, None, 1] >= boxes_2d[None, :, 1]) & (uv[:, None, 1] <= boxes_2d[None, :, 3])).any(1) & (d > 0)
    in3d = np.zeros(len(points), dtype=bool)
    for b in boxes:
        in3d |= points_in_box(points, b)
    return in2d & ~in3d


def generate_scene(seed: int, config: Optional[SceneConfig] = None) -> Scene:
    """One synthetic radar + camera frame, a pure function of ``(seed, config)``.

    Args:
        seed: non-negative int seeding a numpy ``default_rng``.
        config: generator settings (default :class:`SceneConfig()`).

    Returns:
        A :class:`Scene`; ``P`` radar points, ``G`` objects, ``K`` clutter items, image ``(3, H, W)``.

    Example:
        >>> s = generate_scene(0)
        >>> s.points.shape[1], tuple(s.image.shape), s.gt_boxes.shape[1]
        (7, (3, 152, 240), 7)
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise MSSFError(f"seed: expected a non-negative int, got {seed!r}")
    cfg = SceneConfig() if config is None else config
    if not isinstance(cfg, SceneConfig):
        raise MSSFError(f"config: expected a SceneConfig, got {type(cfg).__name__}")
    rng = np.random.default_rng(int(seed))
    objects, clutter = _layout(rng, cfg)
    for it in objects:
        it.extra = dict(skin=_hsv(rng.uniform(0.04, 0.09), rng.uniform(0.3, 0.6), rng.uniform(0.45, 0.95)),
                        legs=_grey(rng, 0.1, 0.35), helmet=_hsv(rng.uniform(0, 1), 0.8, 0.9),
                        stripes=rng.integers(0, 2, 1))
    ego_v = np.zeros(2)
    if rng.random() >= cfg.ego_static_prob:
        ego_v[0] = rng.uniform(*cfg.ego_speed)
    lp = np.asarray(cfg.lighting_probs, dtype=np.float64)
    drawn = LIGHTING_CONDITIONS[int(rng.choice(3, p=lp / lp.sum()))]
    lighting = cfg.lighting or drawn
    radar = _radar(rng, cfg, objects, clutter, ego_v)
    image, ids = _render(rng, cfg, objects, clutter, lighting)

    l2i = cfg.lidar2img()
    gt_boxes = np.stack([it.box for it in objects]) if objects else np.zeros((0, 7))
    cl_boxes = np.stack([it.box for it in clutter]) if clutter else np.zeros((0, 7))
    b2d = _boxes_2d(gt_boxes, l2i, cfg.image_size)
    pts = radar["points"]
    f32 = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    i64 = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.int64))  # noqa: E731
    return Scene(
        points=f32(pts.reshape(-1, 7)),
        image=f32(image.transpose(2, 0, 1)),
        lidar2img=torch.from_numpy(l2i),
        intrinsics=torch.from_numpy(cfg.intrinsics()),
        sensor_to_camera=torch.from_numpy(cfg.sensor_to_camera()),
        gt_boxes=f32(gt_boxes.reshape(-1, 7)),
        gt_labels=i64([it.label for it in objects]),
        gt_boxes_2d=f32(b2d.reshape(-1, 4)),
        gt_velocity=f32(np.stack([it.velocity for it in objects]).reshape(-1, 2) if objects else np.zeros((0, 2))),
        gt_moving=torch.tensor([bool(np.any(it.velocity)) for it in objects], dtype=torch.bool),
        clutter_boxes=f32(cl_boxes.reshape(-1, 7)),
        clutter_kinds=i64([it.label for it in clutter]),
        lighting=lighting,
        blurred_point_mask=torch.from_numpy(_blurred(pts, gt_boxes, b2d, l2i)),
        point_is_clutter=torch.from_numpy(radar["source"] == 2),
        point_source=i64(radar["source"]),
        point_object_index=i64(radar["owner"]),
        instance_map=i64(ids),
        ego_velocity=f32(ego_v),
        seed=int(seed),
    )


def scene_seed(seed: int, split: str, index: int) -> int:
    """The seed of scene ``index`` of ``split``: injective in ``(seed, split, index)``, so splits never share a scene."""
    if split not in _SPLITS:
        raise MSSFError(f"split: expected one of {tuple(_SPLITS)}, got {split!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or not (0 <= seed < 2 ** 28):
        raise MSSFError(f"seed: expected an int in [0, 2**28), got {seed!r}")
    if not (0 <= index < 2 ** 32):
        raise MSSFError(f"index: expected an int in [0, 2**32), got {index!r}")
    return (seed << 34) | (_SPLITS[split] << 32) | int(index)


class SyntheticDataset(torch.utils.data.Dataset):
    """``num_scenes`` deterministic scenes of one split; scene ``i`` uses ``scene_seed(seed, split, i)``.

    Args:
        split: ``"train"``, ``"val"`` or ``"test"``.
        num_scenes: dataset length.
        config: generator settings (default :class:`SceneConfig()`).
        seed: base seed shared by the splits of one experiment.
        cache: keep generated scenes in memory (each is ~0.5 MB).

    Example:
        >>> ds = SyntheticDataset("val", 4)
        >>> len(ds), ds.class_names
        (4, ('Car', 'Pedestrian', 'Cyclist'))
    """

    class_names: Tuple[str, ...] = CLASS_NAMES

    def __init__(self, split: str = "train", num_scenes: int = 100, config: Optional[SceneConfig] = None,
                 seed: int = 0, cache: bool = False) -> None:
        scene_seed(seed, split, 0)  # validates split and seed
        if isinstance(num_scenes, bool) or not isinstance(num_scenes, int) or num_scenes < 0:
            raise MSSFError(f"num_scenes: expected a non-negative int, got {num_scenes!r}")
        if config is not None and not isinstance(config, SceneConfig):
            raise MSSFError(f"config: expected a SceneConfig or None, got {type(config).__name__}")
        self.split, self.num_scenes, self.seed = split, num_scenes, seed
        self.config = config or SceneConfig()
        self._cache: Optional[Dict[int, Scene]] = {} if cache else None

    def __len__(self) -> int:
        return self.num_scenes

    def seed_of(self, index: int) -> int:
        """The :func:`generate_scene` seed of scene ``index``."""
        return scene_seed(self.seed, self.split, index)

    def __getitem__(self, index: int) -> Scene:
        if not isinstance(index, (int, np.integer)) or isinstance(index, bool):
            raise MSSFError(f"index: expected an int, got {type(index).__name__}")
        if index < 0:
            index += self.num_scenes
        if not (0 <= index < self.num_scenes):
            raise IndexError(f"index: expected 0 <= index < {self.num_scenes}, got {index}")
        if self._cache is not None and index in self._cache:
            return self._cache[index]
        scene = generate_scene(self.seed_of(int(index)), self.config)
        if self._cache is not None:
            self._cache[int(index)] = scene
        return scene

    @staticmethod
    def collate(scenes: Sequence[Scene]):
        """``DataLoader`` ``collate_fn``: a :class:`mssf_examples.data.batch.RadarCameraBatch`."""
        return Scene.collate(scenes)
