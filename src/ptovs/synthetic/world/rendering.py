"""Rendering a photo by exact ray casting: shading, sky, occluders, filters,
anti-aliasing; and the per-pixel truth (part ids, depth).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ptovs.synthetic.world.appearance import Appearance
from ptovs.synthetic.world.cameras import Camera
from ptovs.synthetic.world.casting import cast, grid_candidates, in_shadow, screen_boxes
from ptovs.synthetic.world.constants import AA_OFFSETS, GROUND, LUMA, SEPIA
from ptovs.synthetic.world.landmark import World
from ptovs.synthetic.world.primitives import dot3
from ptovs.synthetic.world.textures import smooth_step, texture_albedo
from ptovs.synthetic.world.transients import Billboard


@dataclass
class View:
    """A rendered image and its truth at pixel centres."""

    image: np.ndarray  # [H, W, 3] uint8 RGB
    part_id: np.ndarray  # [H, W] int16, -1 sky/ground
    transient: np.ndarray  # [H, W] bool
    depth: np.ndarray  # [H, W] float32 camera z of landmark or ground, inf for sky


def to_linear(c) -> np.ndarray:
    return np.asarray(c, float) ** 2.2


def develop(radiance: np.ndarray, app: Appearance) -> np.ndarray:
    """Camera processing: exposure, tint, filter, clip, gamma, 8-bit rounding.

    Args:
        radiance: linear RGB, [..., 3].
        app: the appearance.

    Returns:
        uint8 RGB, [..., 3].
    """
    x = radiance * (2.0**app.exposure) * np.asarray(app.tint)
    if app.filter != "none":
        y = x[..., 0] * LUMA[0] + x[..., 1] * LUMA[1] + x[..., 2] * LUMA[2]
        x = y[..., None] * (SEPIA if app.filter == "sepia" else np.ones(3))
    x = np.clip(x, 0.0, 1.0) ** (1.0 / app.gamma)
    return np.floor(x * 255.0 + 0.5).astype(np.uint8)


def _sky(app: Appearance, d: np.ndarray) -> np.ndarray:
    dn = d / np.linalg.norm(d, axis=1, keepdims=True)
    w = smooth_step(0.0, 0.5, dn[:, 2])[:, None]
    rad = to_linear(app.sky_horizon) * (1 - w) + to_linear(app.sky_zenith) * w
    if app.sky in ("day", "dusk") and app.sun_dir[2] > 0:
        glow = np.clip(dot3(dn, np.asarray(app.sun_dir)), 0, 1) ** 64
        rad = rad + 0.4 * glow[:, None] * to_linear(app.sun_color)
    return rad


def surface_albedo(
    world: World, prim: np.ndarray, p: np.ndarray, footprint: np.ndarray | None = None
) -> np.ndarray:
    """Display-space albedo [N, 3] at hit points of primitives / the ground.

    Args:
        world: the world.
        prim: primitive index per point (>= 0 or GROUND), [N].
        p: world points, [N, 3].
        footprint: world size of a pixel per point, [N]; None for the clean texture.

    Returns:
        [N, 3] float64.
    """
    out = np.zeros((len(p), 3))
    part = world.part_of(prim)
    for k, part_k in enumerate(world.parts):
        sel = np.flatnonzero((part == k) & (prim >= 0))
        if len(sel):
            fp = None if footprint is None else footprint[sel]
            out[sel] = texture_albedo(part_k.texture, p[sel], fp)
    sel = np.flatnonzero(prim == GROUND)
    if len(sel):
        fp = None if footprint is None else footprint[sel]
        out[sel] = texture_albedo(world.ground, p[sel], fp)
    return out


def render(
    world: World,
    cam: Camera,
    app: Appearance,
    billboards: Sequence[Billboard] = (),
    aa: int = 5,
    shadows: bool = True,
) -> View:
    """Ray-cast one image with its truth.

    Args:
        world: the world.
        cam: the camera.
        app: the appearance.
        billboards: transient occluders.
        aa: samples per pixel, 1 (pixel centre) or 5 (centre and four diagonals).
        shadows: cast shadow rays towards the sun.

    Returns:
        The view: colour image and truth at pixel centres.
    """
    if aa not in AA_OFFSETS:
        raise ValueError(f"aa must be one of {sorted(AA_OFFSETS)}, got {aa}")
    H, W = cam.height, cam.width
    C = cam.centre
    boxes = screen_boxes(world, cam)
    cands = grid_candidates(boxes, H, W)
    jj, ii = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    acc = np.zeros((H * W, 3))
    light = np.asarray(app.sun_dir)
    amb = app.ambient * np.asarray(app.ambient_color)
    sun = app.sun_strength * np.asarray(app.sun_color)
    fx = cam.K[0, 0]
    truth = None
    for s, (du, dv) in enumerate(AA_OFFSETS[aa]):
        d = cam.ray_dirs(jj + du, ii + dv).reshape(-1, 3)
        t, prim, n = cast(world, C, d, cands)
        tb = np.full(len(d), np.inf)
        kb = np.full(len(d), -1)
        sq = np.zeros((len(d), 2))
        for k, bb in enumerate(billboards):
            tk, sqk = bb.intersect(C, d)
            better = tk < tb
            tb[better], kb[better], sq[better] = tk[better], k, sqk[better]
        trans = tb < t
        if s == 0:
            truth = (
                world.part_of(prim).reshape(H, W),
                trans.reshape(H, W),
                np.where(np.isfinite(t), t, np.inf).astype(np.float32).reshape(H, W),
            )
        rad = np.zeros((len(d), 3))
        hit = np.flatnonzero(np.isfinite(t) & ~trans)
        if len(hit):
            dn = np.linalg.norm(d[hit], axis=1)
            p = C + t[hit, None] * d[hit]
            nn = n[hit]
            cos_i = np.abs(dot3(nn, d[hit])) / dn
            footprint = t[hit] * dn / fx / np.maximum(cos_i, 0.1)
            alb = to_linear(surface_albedo(world, prim[hit], p, footprint))
            ndl = np.clip(dot3(nn, light), 0.0, None)
            if shadows and light[2] > 0.02:
                lit = np.flatnonzero(ndl > 0)
                sh = in_shadow(world, p[lit] + 1e-4 * nn[lit], light)
                ndl[lit[sh]] = 0.0
            rad[hit] = alb * (amb + ndl[:, None] * sun)
        bh = np.flatnonzero(trans)
        if len(bh):
            for k, bb in enumerate(billboards):
                sel = bh[kb[bh] == k]
                if not len(sel):
                    continue
                loc = sq[sel]
                pl = np.stack(
                    [loc[:, 0] * bb.half_w, np.zeros(len(sel)), loc[:, 1] * bb.half_h],
                    1,
                )
                fp = tb[sel] * np.linalg.norm(d[sel], axis=1) / fx
                alb = to_linear(texture_albedo(bb.texture, pl, fp))
                nb = np.cross(bb.right, bb.up)
                ndl = abs(float(np.dot(nb, light)))
                rad[sel] = alb * (amb + ndl * sun)
        sky = np.flatnonzero(~np.isfinite(t) & ~trans)
        if len(sky):
            rad[sky] = _sky(app, d[sky])
        acc += rad
    acc /= len(AA_OFFSETS[aa])
    part_id, transient, depth = truth
    return View(develop(acc.reshape(H, W, 3), app), part_id, transient, depth)


def render_truth(world: World, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Part ids [H, W] int16 and depth [H, W] float64 at pixel centres (no shading)."""
    H, W = cam.height, cam.width
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d = cam.ray_dirs(jj, ii).reshape(-1, 3)
    t, prim, _ = cast(
        world, cam.centre, d, grid_candidates(screen_boxes(world, cam), H, W)
    )
    return world.part_of(prim).reshape(H, W), t.reshape(H, W)
