"""A generated synthetic scene read back: its truth, dense surface samples,
re-renders of its cameras and clean copies of its photos."""

from __future__ import annotations

import functools
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from ptovs.synthetic.points import _backproject
from ptovs.synthetic.presets import _JPEG, PRESETS, _prepare_out, _rng
from ptovs.synthetic.world import (
    Appearance,
    Billboard,
    Camera,
    View,
    World,
    neutral_appearance,
    render,
    render_truth,
    sample_appearance,
    sample_transients,
)


def load_truth(scene_dir: Path) -> tuple[World, dict]:
    """The world and the cameras.json dict of a generated scene."""
    truth = Path(scene_dir) / "synthetic" / "truth"
    if not (truth / "parts.json").is_file():
        raise FileNotFoundError(
            f"{truth / 'parts.json'} not found; is {scene_dir} a synthetic scene?"
        )
    world = World.from_dict(json.loads((truth / "parts.json").read_text()))
    cameras = json.loads((truth / "cameras.json").read_text())
    return world, cameras


SURFACE_SAMPLES = 400_000
"""Budget of `surface_samples` (bench: about 0.4 % of the landmark radius apart)."""


@functools.lru_cache(maxsize=4)
def surface_samples(
    scene_dir: Path, budget: int = SURFACE_SAMPLES
) -> tuple[np.ndarray, np.ndarray]:
    """Dense truth: the world's surfaces seen by the scene's cameras, with part ids.

    Every pixel centre of every camera (cameras.json) is ray-cast against the
    world (no occluders); the hits on the landmark and on the ground within 1.5
    bounding radii of its centre are kept, and a seeded subset of `budget` of them
    is returned. Unlike points3D.npz (the sparse, tracked points: 60 per image on
    tiny) it covers every seen surface densely enough to tell which part a
    Gaussian centre sits on.

    Returns:
        xyz [M, 3] float32 and part ids [M] int16 (-1 = ground).
    """
    world, cameras = load_truth(Path(scene_dir))
    xyz, part = [], []
    for rec in cameras["images"]:
        cam = Camera.from_dict(rec)
        pid, depth = render_truth(world, cam)
        p, near = _backproject(world, cam, depth)
        keep = np.isfinite(depth) & ((pid >= 0) | near)
        xyz.append(p[keep].astype(np.float32))
        part.append(pid[keep].astype(np.int16))
    xyz_all, part_all = np.concatenate(xyz), np.concatenate(part)
    if len(xyz_all) > budget:
        pick = np.sort(np.random.default_rng(0).choice(len(xyz_all), budget, False))
        xyz_all, part_all = xyz_all[pick], part_all[pick]
    return xyz_all, part_all


def nearest_parts(
    scene_dir: Path, xyz: np.ndarray, max_dist: float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The world's part at each 3-D point: that of the nearest truth surface sample.

    Args:
        scene_dir: a generated scene (its world and cameras: `surface_samples`).
        xyz: [N, 3] points, e.g. Gaussian centres.
        max_dist: points farther than this from every sample get -2 (nowhere,
            e.g. floaters or Gaussians inside a solid); default 5 % of the
            landmark's bounding radius.

    Returns:
        part ids [N] int16 and distances [N] float32.
    """
    ref_np, part = surface_samples(Path(scene_dir).resolve())
    if max_dist is None:
        truth = Path(scene_dir) / "synthetic" / "truth"
        max_dist = 0.05 * json.loads((truth / "parts.json").read_text())["radius"]
    q = torch.from_numpy(np.asarray(xyz, np.float32).reshape(-1, 3))
    if len(ref_np) == 0 or len(q) == 0:
        return np.full(len(q), -2, np.int16), np.full(len(q), np.inf, np.float32)
    ref = torch.from_numpy(ref_np)
    ids = np.empty(len(q), np.int64)
    dist = np.empty(len(q), np.float32)
    rows = max(1, (1 << 25) // len(ref))  # distance blocks of at most 128 MB
    for a in range(0, len(q), rows):
        d = torch.cdist(
            q[a : a + rows], ref, compute_mode="donot_use_mm_for_euclid_dist"
        )
        best = d.min(1)
        ids[a : a + rows], dist[a : a + rows] = (
            best.indices.numpy(),
            best.values.numpy(),
        )
    return np.where(dist <= max_dist, part[ids], np.int16(-2)).astype(np.int16), dist


def rerender(
    world: World,
    record: dict,
    appearance: str | Appearance = "own",
    occluders: str = "own",
    seed: int = 0,
    aa: int = 5,
) -> tuple[View, Appearance]:
    """Render a truth camera again under another appearance or other occluders.

    Args:
        world: the scene's world (see load_truth).
        record: the image's entry of cameras.json.
        appearance: "own" (as generated), "neutral", "hard" (a random hard
            condition), "random", or an Appearance.
        occluders: "own", "none", or "force" (at least one new billboard).
        seed: seeds the random appearance and occluders.
        aa: samples per pixel.

    Returns:
        The view and the appearance used.
    """
    cam = Camera.from_dict(record)
    rng = _rng(seed, 7, int(record["image_id"]))
    if isinstance(appearance, Appearance):
        app = appearance
    elif appearance == "own":
        app = Appearance.from_dict(record["appearance"])
    elif appearance == "neutral":
        app = neutral_appearance()
    elif appearance in ("hard", "random"):
        app = sample_appearance(rng, hard=appearance == "hard")
    else:
        raise ValueError(f"unknown appearance {appearance!r}")
    if occluders == "own":
        bbs = [Billboard.from_dict(b) for b in record.get("transients", [])]
    elif occluders == "none":
        bbs = []
    elif occluders == "force":
        bbs = []
        for _ in range(20):
            bbs = sample_transients(rng, world, cam, max_cover=0.4)
            if bbs:
                break
    else:
        raise ValueError(f"unknown occluders {occluders!r}")
    return render(world, cam, app, bbs, aa=aa), app


def clean_scene(
    scene_dir: Path, out: Path, progress: bool = False, appearance: str = "neutral"
) -> Path:
    """A copy of a generated scene whose photos are clean re-renders.

    Every image is rendered again at its own camera under `appearance` ("neutral",
    or "own": the photo's own, so only the occluders go) without occluders, at the
    same size, and written as the generator writes
    photos (JPEG q95, 4:4:4). Everything else (model, split, labels, truth,
    vocabulary) is copied unchanged, labels into out/../label/<name>. The clean-
    feature oracle of bench/accuracy.py extracts its features from these.

    Args:
        scene_dir: a generated scene (out of `generate_scene`).
        out: the new scene folder (replaced if it holds a synthetic scene).
        progress: show a tqdm bar over images.
        appearance: "neutral" or "own" (see `rerender`).

    Returns:
        `out`.
    """
    scene_dir, out = Path(scene_dir), Path(out)
    world, cams = load_truth(scene_dir)
    scene, label = _prepare_out(out.parent, out.name)
    shutil.rmtree(scene)
    shutil.copytree(scene_dir, scene, ignore=shutil.ignore_patterns("images"))
    (scene / "dense" / "images").mkdir()
    src_labels = scene_dir.parent / "label" / scene_dir.name
    if src_labels.is_dir():
        shutil.rmtree(label)
        shutil.copytree(src_labels, label)
    aa = PRESETS[cams["preset"]].aa if cams.get("preset") in PRESETS else 5
    for rec in tqdm(cams["images"], desc=f"clean {out.name}", disable=not progress):
        view, _ = rerender(world, rec, appearance=appearance, occluders="none", aa=aa)
        path = scene / "dense" / "images" / rec["name"]
        cv2.imwrite(str(path), cv2.cvtColor(view.image, cv2.COLOR_RGB2BGR), _JPEG)
    return scene
