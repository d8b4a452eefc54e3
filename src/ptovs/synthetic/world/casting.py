"""Primary and shadow rays: the nearest hit per pixel and its part."""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from ptovs.synthetic.world.cameras import Camera
from ptovs.synthetic.world.constants import GROUND, NO_HIT
from ptovs.synthetic.world.landmark import World
from ptovs.synthetic.world.primitives import dot3


def screen_boxes(world: World, cam: Camera) -> list[tuple[int, int, int, int] | None]:
    """Conservative pixel box of every primitive's bounding box in a camera.

    Args:
        world: the world.
        cam: the camera.

    Returns:
        Per primitive, (i0, i1, j0, j1) (rows i0:i1, columns j0:j1), or None when
        it projects outside the image.
    """
    out = []
    for p in world.prims:
        uv, z = cam.project(p.corners())
        if (z <= 1e-6).any():
            out.append((0, cam.height, 0, cam.width))
            continue
        j0 = max(0, int(math.floor(uv[:, 0].min())) - 1)
        j1 = min(cam.width, int(math.ceil(uv[:, 0].max())) + 1)
        i0 = max(0, int(math.floor(uv[:, 1].min())) - 1)
        i1 = min(cam.height, int(math.ceil(uv[:, 1].max())) + 1)
        out.append((i0, i1, j0, j1) if (i1 > i0 and j1 > j0) else None)
    return out


def cast(
    world: World,
    o: np.ndarray,
    d: np.ndarray,
    cands: Sequence[np.ndarray | None] | None = None,
    ground: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First hit of rays with the landmark and the ground.

    Args:
        world: the world.
        o: origins, [3] (shared) or [R, 3].
        d: directions, [R, 3].
        cands: per primitive, the indices of the rays that may hit it (None: all).
        ground: include the ground plane z = 0.

    Returns:
        t [R] (inf: sky), primitive index [R] int32 (NO_HIT, GROUND or >= 0),
        and unit normals [R, 3].
    """
    n_rays = len(d)
    best_t = np.full(n_rays, np.inf)
    best_i = np.full(n_rays, NO_HIT, np.int32)
    best_n = np.zeros((n_rays, 3))
    for k, prim in enumerate(world.prims):
        idx = None if cands is None else cands[k]
        if idx is None:
            t, n = prim.intersect(o, d)
            better = t < best_t
            best_t[better] = t[better]
            best_i[better] = k
            best_n[better] = n[better]
            continue
        if len(idx) == 0:
            continue
        oo = o if o.ndim == 1 else o[idx]
        t, n = prim.intersect(oo, d[idx])
        better = t < best_t[idx]
        sel = idx[better]
        best_t[sel] = t[better]
        best_i[sel] = k
        best_n[sel] = n[better]
    if ground:
        oz = o[2] if o.ndim == 1 else o[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            tg = np.where((d[:, 2] < 0) & (oz > 0), -oz / d[:, 2], np.inf)
        better = tg < best_t
        best_t[better] = tg[better]
        best_i[better] = GROUND
        best_n[better] = (0.0, 0.0, 1.0)
    return best_t, best_i, best_n


def grid_candidates(boxes, rows: int, cols: int) -> list[np.ndarray]:
    out = []
    for b in boxes:
        if b is None:
            out.append(np.zeros(0, np.int64))
            continue
        i0, i1, j0, j1 = b
        out.append(
            (np.arange(i0, i1)[:, None] * cols + np.arange(j0, j1)[None, :]).ravel()
        )
    return out


def in_shadow(world: World, p: np.ndarray, light: np.ndarray) -> np.ndarray:
    """Whether points [N, 3] are in the shadow of the landmark (directional light)."""
    if len(p) == 0:
        return np.zeros(0, bool)
    # Cull per primitive in the plane perpendicular to the light.
    e1 = np.cross(light, [0.0, 0.0, 1.0] if abs(light[2]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(light, e1)
    a, b, c = dot3(p, e1), dot3(p, e2), dot3(p, light)
    cands = []
    for prim in world.prims:
        cr = prim.corners()
        ca, cb, cc = dot3(cr, e1), dot3(cr, e2), dot3(cr, light)
        sel = (
            (a >= ca.min())
            & (a <= ca.max())
            & (b >= cb.min())
            & (b <= cb.max())
            & (c <= cc.max())
        )
        cands.append(np.flatnonzero(sel))
    d = np.broadcast_to(light, p.shape).copy()
    t, _, _ = cast(world, p, d, cands, ground=False)
    return np.isfinite(t)
