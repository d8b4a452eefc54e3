"""The sparse model of a synthetic scene: surface points sampled from the
photos, their tracks across the other photos, and the COLMAP model."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tqdm import tqdm

from ptovs.synthetic.presets import Preset, _rng
from ptovs.synthetic.world import (
    Billboard,
    Camera,
    View,
    World,
    cast,
    screen_boxes,
    texture_albedo,
)

_TRACK_DEPTH_RTOL = 0.01  # a track element's pixel-centre depth is within 1% of z


def clean_albedo(world: World, part_id: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Display-space albedo [N, 3] of the clean texture at surface points [N, 3]."""
    out = np.zeros((len(p), 3))
    for part in world.parts:
        sel = part_id == part.id
        if sel.any():
            out[sel] = texture_albedo(part.texture, p[sel])
    sel = part_id < 0
    if sel.any():
        out[sel] = texture_albedo(world.ground, p[sel])
    return out


def _backproject(
    world: World, cam: Camera, depth: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """World points [H, W, 3] of a depth map's pixel centres (the camera centre
    where the depth is not finite), and whether each lies within 1.5 bounding
    radii of the landmark's centre, horizontally ([H, W] bool)."""
    H, W = depth.shape
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    xyz = cam.centre + np.where(np.isfinite(depth), depth, 0.0)[..., None] * (
        cam.ray_dirs(jj, ii)
    )
    near = np.hypot(xyz[..., 0] - world.center[0], xyz[..., 1] - world.center[1])
    return xyz, near < 1.5 * world.radius


def _sample_points(
    rng: np.random.Generator, world: World, cam: Camera, view: View, k: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """k surface points seen at pixel centres of a view: xyz, part id, pixel (i, j)."""
    W = view.depth.shape[1]
    ok = np.isfinite(view.depth) & ~view.transient
    # ground points only near the landmark
    C = cam.centre
    _, near = _backproject(world, cam, view.depth)
    ground_ok = ok & (view.part_id < 0) & near
    land = np.flatnonzero(ok & (view.part_id >= 0))
    grd = np.flatnonzero(ground_ok)
    n_land = min(len(land), int(round(0.75 * k)))
    n_grd = min(len(grd), k - n_land)
    pick = np.concatenate(
        [
            rng.choice(land, n_land, replace=False) if n_land else land[:0],
            rng.choice(grd, n_grd, replace=False) if n_grd else grd[:0],
        ]
    )
    pick.sort()
    i, j = np.divmod(pick, W)
    d0 = cam.ray_dirs(j + 0.5, i + 0.5)
    # the stored depth is float32: cast again to put the point on the surface
    t, prim, _ = cast(world, C, d0)
    pts = C + t[:, None] * d0
    return pts, world.part_of(prim), np.stack([i, j], 1)


def _uv_cands(world: World, cam: Camera, uv: np.ndarray) -> list[np.ndarray]:
    out = []
    for b in screen_boxes(world, cam):
        if b is None:
            out.append(np.zeros(0, np.int64))
            continue
        i0, i1, j0, j1 = b
        sel = (uv[:, 0] >= j0) & (uv[:, 0] < j1) & (uv[:, 1] >= i0) & (uv[:, 1] < i1)
        out.append(np.flatnonzero(sel))
    return out


def _observations(
    world: World,
    cam: Camera,
    billboards: list[Billboard],
    xyz: np.ndarray,
    idx: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Which of the points xyz[idx] a camera sees cleanly, and their projections.

    A point is observed when nothing (landmark, ground or transient) lies between
    it and the camera, and the truth depth at the pixel centre it projects to is
    within 1% of its depth (no silhouette edge in between).
    """
    if len(idx) == 0:
        return idx, np.zeros((0, 2))
    X = xyz[idx]
    uv, z = cam.project(X)
    C = cam.centre
    d = X - C  # t = 1 at the point
    t, _, _ = cast(world, C, d, _uv_cands(world, cam, uv))
    vis = t >= 1.0 - 1e-6
    for bb in billboards:
        tb, _ = bb.intersect(C, d)
        vis &= tb >= 1.0
    pc = np.floor(uv) + 0.5
    dc = cam.ray_dirs(pc[:, 0], pc[:, 1])
    tc, _, _ = cast(world, C, dc, _uv_cands(world, cam, pc))
    for bb in billboards:
        tb, _ = bb.intersect(C, dc)
        vis &= tb >= tc
    vis &= np.abs(tc - z) <= _TRACK_DEPTH_RTOL * z
    return idx[vis], uv[vis]


def _tracks(
    world: World,
    cams: list[Camera],
    bbs: list[list[Billboard]],
    xyz: np.ndarray,
    src: np.ndarray,
    px: np.ndarray,
    cfg: Preset,
    seed: int,
    progress: bool,
    ids: list[int],
) -> list[list[tuple[int, float, float]]]:
    """Per point, its observations (position in `cams`, u, v); the source view
    first. `ids`: each camera's index in the plan (it keys the random draws, so a
    photo keeps its observations in a subset of the collection)."""
    tracks: list[list[tuple[int, float, float]]] = [
        [(int(s), float(p[1]) + 0.5, float(p[0]) + 0.5)]
        for s, p in zip(src, px, strict=True)
    ]
    for c, cam in enumerate(
        tqdm(cams, desc="tracks", disable=not progress, unit="img")
    ):
        uv, z = cam.project(xyz)
        inb = (z > 1e-6) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0)
        inb &= (uv[:, 1] < cam.height) & (src != c)
        idx = np.flatnonzero(inb)
        if cfg.track_keep < 1.0:
            idx = idx[_rng(seed, 6, ids[c]).random(len(idx)) < cfg.track_keep]
        idx, uvk = _observations(world, cam, bbs[c], xyz, idx)
        for k, (u, v) in zip(idx.tolist(), uvk.tolist(), strict=True):
            tracks[k].append((c, u, v))
    return tracks


def _write_colmap(
    sparse: Path,
    records: list[dict],
    cams: list[Camera],
    world: World,
    xyz: np.ndarray,
    part: np.ndarray,
    tracks: list[list[tuple[int, float, float]]],
    keep: np.ndarray,
) -> np.ndarray:
    """Write the COLMAP model; returns the point3D ids of the kept points."""
    import pycolmap

    kps: list[list[tuple[float, float]]] = [[] for _ in cams]
    elems: list[list[tuple[int, int]]] = []
    for k in np.flatnonzero(keep):
        el = []
        for c, u, v in tracks[k]:
            el.append((records[c]["image_id"], len(kps[c])))
            kps[c].append((u, v))
        elems.append(el)
    rec = pycolmap.Reconstruction()
    for c, (cam, r) in enumerate(zip(cams, records, strict=True)):
        iid = r["image_id"]
        K = cam.K
        rec.add_camera_with_trivial_rig(
            pycolmap.Camera(
                model="PINHOLE",
                width=cam.width,
                height=cam.height,
                params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]],
                camera_id=iid,
            )
        )
        kp = np.asarray(kps[c], np.float64).reshape(-1, 2)
        img = pycolmap.Image(name=r["name"], keypoints=kp, camera_id=iid, image_id=iid)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(cam.R.copy()), cam.t.copy())
        rec.add_image_with_trivial_frame(img, pose)
    colours = (
        np.clip(clean_albedo(world, part[keep], xyz[keep]), 0, 1) * 255 + 0.5
    ).astype(np.uint8)
    ids = []
    for X, col, el in zip(xyz[keep], colours, elems, strict=True):
        tr = pycolmap.Track()
        for iid, p2 in el:
            tr.add_element(iid, p2)
        ids.append(rec.add_point3D(X, tr, col))
    rec.write(str(sparse))
    return np.asarray(ids, np.int64)
