"""Camera rendering of the synthetic scenes: background, depth-tested boxes and people, lighting."""

from __future__ import annotations

import math
from typing import List, Tuple

import numpy as np

from .config import SceneConfig
from .geometry import box_corners
from .layout import _grey, _Item


def _smooth_noise(rng: np.random.Generator, h: int, w: int, cell: int) -> np.ndarray:
    """``(h, w)`` value noise in about ``[-1, 1]``: a coarse random grid, bilinearly upsampled."""
    gh, gw = h // cell + 2, w // cell + 2
    grid = rng.uniform(-1, 1, (gh, gw))
    y = np.arange(h) / cell
    x = np.arange(w) / cell
    y0, x0 = y.astype(int), x.astype(int)
    fy, fx = (y - y0)[:, None], (x - x0)[None]
    g00, g01 = grid[y0][:, x0], grid[y0][:, x0 + 1]
    g10, g11 = grid[y0 + 1][:, x0], grid[y0 + 1][:, x0 + 1]
    return (g00 * (1 - fx) + g01 * fx) * (1 - fy) + (g10 * (1 - fx) + g11 * fx) * fy


class _Canvas:
    """RGB image with a depth buffer; every primitive writes where it is nearer than what is there."""

    def __init__(self, cfg: SceneConfig, rgb: np.ndarray, texture: np.ndarray) -> None:
        self.h, self.w = cfg.image_size
        self.k = cfg.intrinsics()
        self.s2c = cfg.sensor_to_camera()
        self.camera = np.asarray(cfg.camera_position, dtype=np.float64)
        self.rgb = rgb
        self.texture = texture
        self.depth = np.full((self.h, self.w), np.inf)
        self.ids = np.full((self.h, self.w), -1, dtype=np.int64)
        u = np.arange(self.w, dtype=np.float64)
        v = np.arange(self.h, dtype=np.float64)
        self.ray_x = (u - self.k[0, 2]) / self.k[0, 0]
        self.ray_y = (v - self.k[1, 2]) / self.k[1, 1]

    def to_cam(self, p: np.ndarray) -> np.ndarray:
        return p @ self.s2c[:3, :3].T + self.s2c[:3, 3]

    def project(self, p: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        c = self.to_cam(p)
        return c[:, :2] / c[:, 2:3] * self.k[[0, 1], [0, 1]] + self.k[:2, 2], c[:, 2]

    def window(self, uv: np.ndarray):
        l, t = np.floor(uv.min(0)).astype(int)
        r, b = np.ceil(uv.max(0)).astype(int)
        l, t, r, b = max(l, 0), max(t, 0), min(r, self.w - 1), min(b, self.h - 1)
        if l > r or t > b:
            return None
        return slice(t, b + 1), slice(l, r + 1)

    def quad(self, corners: np.ndarray, colour: np.ndarray, item: int, texture_amp: float = 0.05) -> None:
        """Fill a planar convex quad ``(4, 3)`` (sensor frame) with per-pixel depth from its plane."""
        cam = self.to_cam(corners)
        normal = np.cross(cam[1] - cam[0], cam[2] - cam[0])
        offset = normal @ cam[0]
        if abs(offset) < 1e-9:
            return  # seen edge-on
        uv = cam[:, :2] / cam[:, 2:3] * self.k[[0, 1], [0, 1]] + self.k[:2, 2]
        win = self.window(uv)
        if win is None:
            return
        ys, xs = win
        px = np.arange(xs.start, xs.stop, dtype=np.float64)[None]
        py = np.arange(ys.start, ys.stop, dtype=np.float64)[:, None]
        nxt = uv[[1, 2, 3, 0]]
        sign = 1.0 if np.sum(uv[:, 0] * nxt[:, 1] - nxt[:, 0] * uv[:, 1]) >= 0 else -1.0
        inside = np.ones((len(py), px.shape[1]), dtype=bool)
        for (x0, y0), (x1, y1) in zip(uv.tolist(), nxt.tolist()):
            inside &= (((x1 - x0) * sign) * (py - y0) - ((y1 - y0) * sign) * (px - x0)) >= 0
        rx, ry = self.ray_x[xs][None], self.ray_y[ys][:, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            z = offset / (normal[0] * rx + normal[1] * ry + normal[2])
        self._write(win, inside & (z > 0), z, colour, item, texture_amp)

    def sprite(self, win, mask: np.ndarray, colours: np.ndarray, depth: float, item: int, texture_amp=0.05):
        """Paint a flat cut-out at constant ``depth`` (thin objects: people, bicycles)."""
        self._write(win, mask, np.full(mask.shape, depth), colours, item, texture_amp)

    def _write(self, win, mask, z, colour, item, texture_amp):
        front = mask & (z < self.depth[win])
        if not front.any():
            return
        col = np.broadcast_to(np.asarray(colour, dtype=np.float64), front.shape + (3,))
        tex = 1.0 + texture_amp * self.texture[win][..., None]
        region = self.rgb[win]
        region[front] = np.clip(col[front] * tex[front], 0, 1)
        self.depth[win][front] = z[front]
        self.ids[win][front] = item


# Faces of a unit box: (centre, axis-a, axis-b) in local half-extent units; b is "up" on vertical faces.
_FACES = {
    "front": ((1, 0, 0), (0, 1, 0), (0, 0, 1)), "back": ((-1, 0, 0), (0, -1, 0), (0, 0, 1)),
    "left": ((0, 1, 0), (-1, 0, 0), (0, 0, 1)), "right": ((0, -1, 0), (1, 0, 0), (0, 0, 1)),
    "top": ((0, 0, 1), (1, 0, 0), (0, 1, 0)), "bottom": ((0, 0, -1), (0, 1, 0), (1, 0, 0)),
}
_SHADE = {"front": 0.85, "back": 0.8, "left": 0.95, "right": 0.7, "top": 1.1, "bottom": 0.4}


def _face_quad(box: np.ndarray, face: str, a=(-1.0, 1.0), b=(-1.0, 1.0), lift: float = 0.0) -> np.ndarray:
    """``(4, 3)`` sensor-frame corners of the sub-rectangle ``a x b`` (in [-1, 1]) of a box face."""
    c0, ua, ub = (np.asarray(v, dtype=np.float64) for v in _FACES[face])
    half = box[3:6] / 2
    loc = [c0 * half * (1 + lift / np.maximum(half, 1e-9)) + ua * half * aa + ub * half * bb
           for aa, bb in ((a[0], b[0]), (a[1], b[0]), (a[1], b[1]), (a[0], b[1]))]
    loc = np.asarray(loc)
    cy, sy = math.cos(box[6]), math.sin(box[6])
    x = cy * loc[:, 0] - sy * loc[:, 1]
    y = sy * loc[:, 0] + cy * loc[:, 1]
    return np.stack([x, y, loc[:, 2]], 1) + box[:3]


def _facing(box: np.ndarray, face: str, camera: np.ndarray) -> bool:
    """Whether the outward normal of ``face`` points towards the camera (back faces are skipped)."""
    c0 = np.asarray(_FACES[face][0], dtype=np.float64)
    cy, sy = math.cos(box[6]), math.sin(box[6])
    normal = np.array([cy * c0[0] - sy * c0[1], sy * c0[0] + cy * c0[1], c0[2]])
    centre = box[:3] + normal * (np.abs(c0) @ box[3:6]) / 2
    return float(normal @ (centre - camera)) < 0


def _render_box(cv: _Canvas, box: np.ndarray, colour: np.ndarray, item: int, texture_amp: float,
                car: bool, rng: np.random.Generator) -> None:
    faces = [f for f in _FACES if _facing(box, f, cv.camera)]
    for face in faces:
        cv.quad(_face_quad(box, face), colour * _SHADE[face], item, texture_amp)
    if not car:
        return
    glass = np.array([0.12, 0.15, 0.22]) * rng.uniform(0.8, 1.2)
    tyre = np.array([0.05, 0.05, 0.05])
    # Details sit 2 cm in front of their face so the depth test shows them.
    for face in [f for f in ("front", "back") if f in faces]:
        cv.quad(_face_quad(box, face, (-0.8, 0.8), (0.15, 0.8), 0.02), glass, item, 0.02)
        lamp = np.array([1.0, 0.95, 0.75]) if face == "front" else np.array([0.75, 0.02, 0.02])
        for a in ((-0.9, -0.6), (0.6, 0.9)):
            cv.quad(_face_quad(box, face, a, (-0.45, -0.2), 0.02), lamp, item, 0.0)
    for face in [f for f in ("left", "right") if f in faces]:
        cv.quad(_face_quad(box, face, (-0.55, 0.45), (0.15, 0.8), 0.02), glass, item, 0.02)
        for a in ((-0.8, -0.5), (0.5, 0.8)):
            cv.quad(_face_quad(box, face, a, (-1.0, -0.45), 0.02), tyre, item, 0.0)


def _render_person(cv: _Canvas, it: _Item, item: int) -> None:
    """Pedestrian (label 1) or cyclist (label 2) as a flat cut-out at the box centre's depth."""
    box = it.box
    uv, depth = cv.project(box_corners(box)[0])
    win = cv.window(uv)
    if win is None:
        return
    ys, xs = win
    px, py = np.meshgrid(np.arange(xs.start, xs.stop, dtype=np.float64), np.arange(ys.start, ys.stop, dtype=np.float64))
    bottom = box[:3] - np.array([0, 0, box[5] / 2])
    ub, vb = cv.project(bottom[None])[0][0]
    dc = float(cv.to_cam(box[None, :3])[0, 2])  # one depth for the whole cut-out
    sx, sy = cv.k[0, 0] / dc, cv.k[1, 1] / dc  # pixels per metre at the object's depth
    hscale = box[5] / 1.73

    def rect(cx, half_w, h0, h1):  # lateral centre (m), half width (m), heights above ground (m)
        return (np.abs(px - (ub + cx * sx)) <= max(half_w * sx, 0.5)) & (py <= vb - h0 * sy) & (py >= vb - h1 * sy)

    def ellipse(cx, cz, rx, rz):
        return ((px - (ub + cx * sx)) / max(rx * sx, 0.5)) ** 2 + ((py - (vb - cz * sy)) / max(rz * sy, 0.5)) ** 2 <= 1

    colours = np.zeros(px.shape + (3,))
    mask = np.zeros(px.shape, dtype=bool)

    def paint(m, col):
        colours[m] = col
        mask[:] |= m

    cloth, skin = it.colour, it.extra["skin"]
    if it.label == 1:
        paint(rect(-0.09, 0.07, 0.0, 0.85 * hscale) | rect(0.09, 0.07, 0.0, 0.85 * hscale), it.extra["legs"])
        torso = rect(0.0, 0.2, 0.8 * hscale, 1.45 * hscale)
        paint(torso, cloth)
        if it.extra["stripes"][0] > 0:
            stripes = torso & (((vb - py) / sy / 0.12).astype(int) % 2 == 0)
            paint(stripes, cloth * 0.6)
        paint(rect(-0.25, 0.05, 0.85 * hscale, 1.42 * hscale) | rect(0.25, 0.05, 0.85 * hscale, 1.42 * hscale),
              cloth * 0.8)
        paint(ellipse(0.0, 1.58 * hscale, 0.1, 0.12), skin)
    else:
        # Two wheels along the heading; their apparent width shrinks when seen end-on.
        head = np.array([math.cos(box[6]), math.sin(box[6]), 0.0])
        view = box[:3] / np.linalg.norm(box[:3])
        squash = max(abs(float(np.cross(head, view)[2])), 0.25)
        axle = head * 0.55 * box[3] / 1.76
        wheel_uv, _ = cv.project(np.stack([bottom + axle + [0, 0, 0.34], bottom - axle + [0, 0, 0.34]]))
        for wu, wv in wheel_uv:
            d2 = ((px - wu) / max(0.34 * sx * squash, 0.5)) ** 2 + ((py - wv) / max(0.34 * sy, 0.5)) ** 2
            paint((d2 <= 1.0) & (d2 >= 0.55), np.array([0.04, 0.04, 0.04]))
        frame = (np.abs(py - (vb - 0.5 * sy)) <= max(0.05 * sy, 0.5)) & (px >= wheel_uv[:, 0].min()) & (
            px <= wheel_uv[:, 0].max())
        paint(frame, it.extra["legs"])
        paint(rect(0.0, 0.09, 0.45 * hscale, 0.95 * hscale), it.extra["legs"])
        paint(rect(0.0, 0.19, 0.9 * hscale, 1.45 * hscale), cloth)
        paint(ellipse(0.0, 1.57 * hscale, 0.11, 0.12), it.extra["helmet"])
    cv.sprite(win, mask, colours, dc, item, 0.04)


def _background(rng: np.random.Generator, cfg: SceneConfig, cv_k: np.ndarray) -> np.ndarray:
    h, w = cfg.image_size
    v = np.arange(h, dtype=np.float64)[:, None]
    horizon = cv_k[1, 2]  # zero camera pitch: the horizon is the principal row
    tint = rng.normal(0.0, 0.015, 3)
    sky_top, sky_hor = rng.uniform(0.55, 0.75), rng.uniform(0.75, 0.9)
    frac = np.clip(v / max(horizon, 1.0), 0, 1)
    sky = sky_top + (sky_hor - sky_top) * frac
    g_far, g_near = rng.uniform(0.4, 0.55), rng.uniform(0.25, 0.4)
    gfrac = np.clip((v - horizon) / max(h - horizon, 1.0), 0, 1)
    ground = g_far + (g_near - g_far) * gfrac
    base = np.where(v < horizon, sky, ground) * np.ones((1, w))
    base = base + 0.08 * _smooth_noise(rng, h, w, 16) + 0.04 * _smooth_noise(rng, h, w, 4)
    rgb = np.clip(base[..., None] + tint, 0, 1)
    # Distant buildings above the horizon: grey blocks (beyond radar range, so no returns).
    for _ in range(int(rng.integers(3, 8))):
        x0 = int(rng.integers(0, w))
        bw = int(rng.integers(w // 12, w // 4))
        top = int(max(horizon - rng.uniform(0.1, 0.45) * h, 0))
        rgb[top:int(horizon) + 1, x0:x0 + bw] = _grey(rng, 0.35, 0.75)
    return rgb


def _render(rng: np.random.Generator, cfg: SceneConfig, objects: List[_Item], clutter: List[_Item],
            lighting: str) -> Tuple[np.ndarray, np.ndarray]:
    h, w = cfg.image_size
    k = cfg.intrinsics()
    rgb = _background(rng, cfg, k)
    texture = rng.normal(0.0, 1.0, (h, w))
    cv = _Canvas(cfg, rgb, texture)
    for i, it in enumerate(objects):
        if it.label == 0:
            _render_box(cv, it.box, it.colour, i, 0.05, True, rng)
        else:
            _render_person(cv, it, i)
    for j, it in enumerate(clutter):
        _render_box(cv, it.box, it.colour, len(objects) + j, 0.12, False, rng)
    img = cv.rgb
    if lighting == "dark":
        img = img * rng.uniform(*cfg.dark_gain) + rng.normal(0, cfg.dark_noise, img.shape)
    elif lighting == "dazzle":
        # A bright bloom (sun / headlights) washing out part of the image, plus veiling glare.
        cu, cvv = rng.uniform(0.15, 0.85) * w, rng.uniform(0.15, 0.55) * h
        sigma = rng.uniform(0.2, 0.4) * w
        yy, xx = np.mgrid[0:h, 0:w]
        bloom = rng.uniform(0.75, 0.95) * np.exp(-((xx - cu) ** 2 + (yy - cvv) ** 2) / (2 * sigma ** 2))
        img = img + (1 - img) * np.clip(bloom + 0.1, 0, 1)[..., None]
    img = img + rng.normal(0, cfg.image_noise, img.shape)
    return np.clip(img, 0, 1), cv.ids
