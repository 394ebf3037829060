"""Radar simulation of the synthetic scenes: surface returns, multipath ghosts, noise, occlusion, Doppler."""

from __future__ import annotations

import math
from typing import Dict, List

import numpy as np

from .config import _CLASS_RADAR, _CLUTTER_RADAR, SceneConfig
from .geometry import _segment_hits_boxes
from .layout import _Item


def _surface_points(rng: np.random.Generator, box: np.ndarray, n: int, z_frac=(0.05, 0.95)) -> np.ndarray:
    """``(n, 3)`` points uniform on the radar-facing vertical faces of ``box`` (weighted by visible area)."""
    c, s = math.cos(box[6]), math.sin(box[6])
    ax = np.array([[c, s], [-s, c]])  # rows: local x, local y axes in the sensor frame
    # Four vertical faces: (normal axis, sign, half-width along the other axis, half-extent of normal axis).
    normals, centres, tangents, widths = [], [], [], []
    for a in (0, 1):
        for sign in (1.0, -1.0):
            nrm = sign * ax[a]
            normals.append(nrm)
            centres.append(box[:2] + nrm * box[3 + a] / 2)
            tangents.append(ax[1 - a])
            widths.append(box[3 + (1 - a)])
    normals, centres, tangents, widths = map(np.asarray, (normals, centres, tangents, widths))
    view = -centres / np.linalg.norm(centres, axis=1, keepdims=True)
    cosang = (normals * view).sum(1)
    weight = np.clip(cosang, 0, None) * widths
    if n == 0 or weight.sum() <= 0:
        return np.zeros((0, 3))
    face = rng.choice(4, size=n, p=weight / weight.sum())
    along = rng.uniform(-0.5, 0.5, n) * widths[face]
    # Returns come from just inside the skin (wheel arches, bodies, limbs), so an accurate label box
    # contains most of them, as on real data.
    depth_ext = np.where(np.arange(4) < 2, box[3], box[4])[face]
    inset = rng.uniform(0.05, 1.0, n) * np.minimum(0.35, 0.45 * depth_ext)
    xy = centres[face] + tangents[face] * along[:, None] - normals[face] * inset[:, None]
    z = box[2] - box[5] / 2 + rng.uniform(z_frac[0], z_frac[1], n) * box[5]
    return np.concatenate([xy, z[:, None]], 1)


def _expected_points(base: float, box: np.ndarray, cfg: SceneConfig) -> float:
    r = float(np.hypot(box[0], box[1]))
    return base * cfg.points_scale * float(np.clip(10.0 / max(r, 1e-3), 0.35, 2.5))


def _radar(rng: np.random.Generator, cfg: SceneConfig, objects: List[_Item], clutter: List[_Item],
           ego_v: np.ndarray) -> Dict[str, np.ndarray]:
    items = objects + clutter
    all_boxes = np.stack([it.box for it in items]) if items else np.zeros((0, 7))
    pos, vel, rcs, scan, src, owner, item_idx, extra_dop = [], [], [], [], [], [], [], []
    ns = cfg.num_scans

    def add(*columns):
        for store, col in zip((pos, vel, rcs, scan, src, owner, item_idx, extra_dop), columns):
            store.append(col)

    for i, it in enumerate(items):
        if it.is_object:
            sig = _CLASS_RADAR[it.label]
            lam = _expected_points(sig["points"], it.box, cfg) * ns
        else:
            sig = _CLUTTER_RADAR[it.label]
            per = sig["points"] * (it.box[3] if it.label in (3, 4) else 1.0)
            lam = _expected_points(per, it.box, cfg) * ns
        n = int(rng.poisson(lam))
        if it.is_object and it.label == 2:
            # A cyclist's returns come mostly from the rider (a pedestrian-sized sub-box), which makes
            # pedestrians and cyclists look alike to the radar.
            rider = it.box.copy()
            rider[3] = min(0.75, rider[3])
            n_r = int(rng.binomial(n, 0.8))
            p = np.concatenate([_surface_points(rng, rider, n_r, (0.2, 0.98)),
                                _surface_points(rng, it.box, n - n_r, (0.02, 0.45))])
        else:
            z_frac = (0.05, 0.95)
            if not it.is_object and it.label == 0:
                # A pole returns from person height only (like a pedestrian), not from its full length.
                z_frac = (0.03, min(0.95, 1.7 / it.box[5]))
            elif not it.is_object and it.label == 4:
                z_frac = (0.4, 1.0)  # the rail, not the posts
            p = _surface_points(rng, it.box, n, z_frac)
        k = rng.integers(0, ns, len(p))
        # Ego-motion-compensated accumulation: moving objects' older returns trail behind them.
        p[:, :2] -= (k * cfg.scan_period)[:, None] * it.velocity[None]
        micro = cfg.micro_doppler if (it.is_object and it.label in (1, 2) and np.any(it.velocity)) else 0.0
        m = len(p)
        add(p, np.repeat(it.velocity[None], m, 0), it.rcs_mean + rng.normal(0, cfg.rcs_noise, m), k,
            np.full(m, 0 if it.is_object else 2), np.full(m, i if it.is_object else -1), np.full(m, i),
            np.full(m, micro))
        if it.is_object:
            # Multipath ghosts: behind the object along the line of sight, with the object's Doppler.
            g = int(rng.poisson(cfg.ghost_rate * ns))
            if g:
                base = _surface_points(rng, it.box, g)
                gk = rng.integers(0, ns, g)
                base[:, :2] -= (gk * cfg.scan_period)[:, None] * it.velocity[None]
                dist = np.linalg.norm(base, axis=1, keepdims=True)
                gp = base * (1.0 + rng.uniform(0.8, 5.0, (g, 1)) / dist)
                add(gp, np.repeat(it.velocity[None], g, 0), it.rcs_mean - 6 + rng.normal(0, cfg.rcs_noise, g), gk,
                    np.full(g, 1), np.full(g, i), np.full(g, i), np.full(g, micro))

    x0, y0, z0, x1, y1, z1 = cfg.point_cloud_range
    half_fov = math.radians(cfg.radar_fov / 2)
    nn_ = int(rng.poisson(cfg.noise_points * ns))
    r = rng.uniform(max(x0, 1.0), x1, nn_)
    a = rng.uniform(-half_fov, half_fov, nn_)
    noise_p = np.stack([r * np.cos(a), r * np.sin(a), -cfg.radar_height + rng.uniform(0.0, 2.5, nn_)], 1)
    noise_v = np.zeros((nn_, 2))
    outlier = rng.random(nn_) < cfg.noise_doppler_outlier_prob
    # A random radial speed, expressed as a velocity along the line of sight.
    noise_v[outlier] = (rng.uniform(-3, 3, outlier.sum())[:, None] * noise_p[outlier, :2]
                        / np.linalg.norm(noise_p[outlier, :2], axis=1, keepdims=True))
    add(noise_p, noise_v, rng.normal(-6.0, 4.0, nn_), rng.integers(0, ns, nn_), np.full(nn_, 3), np.full(nn_, -1),
        np.full(nn_, -1), np.zeros(nn_))

    p = np.concatenate(pos)
    v = np.concatenate(vel)
    rcs_ = np.concatenate(rcs)
    k = np.concatenate(scan)
    source = np.concatenate(src).astype(np.int64)
    own = np.concatenate(owner).astype(np.int64)
    idx = np.concatenate(item_idx).astype(np.int64)
    micro = np.concatenate(extra_dop)

    # Occlusion: a return hidden behind another item survives only with probability occlusion_leak.
    hits = _segment_hits_boxes(p, all_boxes)
    if hits.size:
        hits[np.arange(len(p))[idx >= 0], idx[idx >= 0]] = False
    # People are thin and not metal: the radar sees past them far more often than past a car or a wall
    # (this is why the paper finds the worst blurring for pedestrians and cyclists, Fig. 1d).
    soft = np.array([it.is_object and it.label in (1, 2) for it in items], dtype=bool)
    hard_hit = hits[:, ~soft].any(1) & (source != 3)
    soft_hit = hits[:, soft].any(1) & (source != 3)
    u = rng.random(len(p))
    keep = np.where(hard_hit, u < cfg.occlusion_leak, np.where(soft_hit, u < cfg.occlusion_leak_people, True))

    # Doppler from the true geometry; ego moves along +x (relative velocity = v - v_ego).
    rng_true = np.linalg.norm(p, axis=1)
    unit = p / np.maximum(rng_true, 1e-9)[:, None]
    v_rc = (v * unit[:, :2]).sum(1) + rng.normal(0, 1, len(p)) * np.sqrt(cfg.doppler_noise ** 2 + micro ** 2)
    v_r = v_rc - (ego_v[None] * unit[:, :2]).sum(1)

    # Spherical measurement noise.
    az = np.arctan2(p[:, 1], p[:, 0]) + rng.normal(0, math.radians(cfg.azimuth_noise), len(p))
    el = np.arcsin(np.clip(p[:, 2] / np.maximum(rng_true, 1e-9), -1, 1)) + rng.normal(
        0, math.radians(cfg.elevation_noise), len(p))
    rr = rng_true + rng.normal(0, cfg.range_noise, len(p))
    meas = np.stack([rr * np.cos(el) * np.cos(az), rr * np.cos(el) * np.sin(az), rr * np.sin(el)], 1)

    in_range = ((meas[:, 0] >= x0) & (meas[:, 0] < x1) & (meas[:, 1] >= y0) & (meas[:, 1] < y1)
                & (meas[:, 2] >= z0) & (meas[:, 2] < z1) & (np.abs(az) <= half_fov))
    keep &= in_range
    pts = np.concatenate([meas, rcs_[:, None], v_r[:, None], v_rc[:, None], (-k)[:, None].astype(np.float64)], 1)  # int negation: t = +0.0, not -0.0
    return dict(points=pts[keep], source=source[keep], owner=own[keep])
