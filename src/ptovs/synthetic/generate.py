"""Presets and the on-disk layout of a synthetic PT-OVS scene (docs/synthetic.md).

`generate_scene` writes, image by image (memory stays bounded for `scale`):

    out/<name>/dense/images/<stem>.jpg        JPEG q95, sizes vary
    out/<name>/dense/sparse/                  COLMAP model (pycolmap, binary)
    out/<name>/<preset>.tsv                   split file
    out/label/<name>/<stem>.json|.jpg         ISAT labels of the evaluation views
    out/<name>/synthetic/vocabulary.json      for the stand-in encoder only
    out/<name>/synthetic/truth/               cameras.json, parts.json, points3D.npz,
                                              <stem>.npz (part_id, transient, depth)
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import shutil
import zipfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from ptovs.synthetic.screen import PartScreen, screen_record, screen_world
from ptovs.synthetic.world import (
    DISTRACTORS,
    Appearance,
    Billboard,
    Camera,
    View,
    World,
    build_world,
    cast,
    neutral_appearance,
    part_swatch,
    random_texture,
    render,
    render_truth,
    sample_appearance,
    sample_camera,
    sample_transients,
    screen_boxes,
    sky_swatch,
    texture_albedo,
)

logger = logging.getLogger(__name__)

TRUTH_VERSION = 2  # 2: screened queries, every labelled part a query
STYLES = (
    "Neoclassical",
    "Gothic",
    "Baroque",
    "Romanesque",
    "Byzantine",
    "Renaissance",
    "Georgian",
    "Palladian",
    "Moorish",
    "Art Deco",
    "Victorian Gothic",
    "Edwardian Baroque",
)
"""Style names the generator gives landmarks (`scene_styles`)."""
N_STYLES = 5  # candidates per scene, as the paper's LLM proposes
# q95 without chroma subsampling: at ~96 px, 4:2:0 visibly smears part colours
_JPEG = [
    cv2.IMWRITE_JPEG_QUALITY,
    95,
    cv2.IMWRITE_JPEG_SAMPLING_FACTOR,
    cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444,
]
_TRACK_DEPTH_RTOL = 0.01  # a track element's pixel-centre depth is within 1% of z


@dataclass(frozen=True)
class Preset:
    """Size of a generated scene.

    Every part labelled in some evaluation view is a query, unless the screen
    (`ptovs.synthetic.screen`) finds its phrase unanswerable.
    """

    n_train: int
    n_test: int
    n_eval: int
    n_cand: int  # frontal train cameras the evaluation views are chosen from
    long_side: tuple[int, int]  # range of the image's long side, pixels
    n_parts: tuple[int, int]  # range
    aa: int  # samples per pixel (1 or 5)
    points_per_image: int
    track_keep: float  # chance to keep a visible observation in a track
    swatch_px: int  # resolution the vocabulary swatches are rendered at
    max_cover: float = 0.4  # largest transient coverage of an image
    max_train: int = 0
    """The most train photos `--photos` may ask (0: n_train). Those past n_train are
    more photos of the same world: cameras drawn as the others' (never an
    evaluation candidate), after every photo of the preset's own plan."""
    scale: int = 1
    """Photograph the plan at `scale` times the side: the world, cameras, evaluation
    views and screen are those of the same preset at scale 1 (drawn at
    `long_side`), and only the photos have more pixels."""

    @property
    def train_limit(self) -> int:
        """The most train photos a scene of this preset may have."""
        return max(self.max_train, self.n_train)


PRESETS: dict[str, Preset] = {
    "tiny": Preset(
        n_train=12,
        n_test=1,
        n_eval=2,
        n_cand=8,
        long_side=(88, 104),
        n_parts=(3, 3),
        aa=5,
        points_per_image=60,
        track_keep=1.0,
        swatch_px=32,
    ),
    # the accuracy instrument's scenes (bench/accuracy.py): bench's landmarks and
    # evaluation design at about half the image side and 60 % of the views
    "small": Preset(
        n_train=48,
        n_test=4,
        n_eval=20,
        n_cand=30,
        long_side=(176, 256),
        n_parts=(5, 7),
        aa=5,
        points_per_image=100,
        track_keep=1.0,
        swatch_px=64,
    ),
    "bench": Preset(
        n_train=80,
        n_test=8,
        n_eval=20,
        n_cand=42,
        long_side=(240, 400),
        n_parts=(6, 8),
        aa=5,
        points_per_image=120,
        track_keep=1.0,
        swatch_px=96,
    ),
    # a Brandenburg-sized collection (PT-OVS: 763 train photos at about 700 px on the
    # long side): bench's landmarks and evaluation design at a real photo size.
    # One sample a pixel (at this size aliasing is a pixel's, not a part's) and a
    # tenth of each point's observations keep generation and the model's tracks
    # within minutes and memory; `--photos N` takes the first N train photos.
    "landmark": Preset(
        n_train=763,
        n_test=8,
        n_eval=20,
        n_cand=42,
        long_side=(640, 760),
        n_parts=(6, 8),
        aa=1,
        points_per_image=60,
        track_keep=0.1,
        swatch_px=96,
        max_train=2934,  # Notre-Dame, PT-OVS's largest scene
    ),
    "scale": Preset(
        n_train=3000,
        n_test=60,
        n_eval=4,
        n_cand=14,
        long_side=(60, 68),
        n_parts=(6, 8),
        aa=1,
        points_per_image=8,
        track_keep=0.02,
        swatch_px=24,
    ),
}


# small's scenes photographed at three times the side (528-768 px, parts 60-250 px):
# the same worlds and cameras as small, at the photo size the stand-in version 2 was
# calibrated at (issue 41) and near PT-OVS's (about 700 px)
PRESETS["small-3x"] = dataclasses.replace(PRESETS["small"], scale=3)


def _rng(seed: int, *stream: int) -> np.random.Generator:
    return np.random.default_rng([seed, *stream])


def _min_px(cam: Camera, frac: float, floor: int) -> int:
    return max(floor, int(frac * cam.width * cam.height))


# ------------------------------------------------------------------- labels --


def _splice_holes(outer: np.ndarray, holes: list[np.ndarray]) -> np.ndarray:
    """One polygon for a region with holes: each hole joined by a zero-width bridge.

    cv2.fillPoly fills with the even-odd rule, so the bridged hole stays empty.
    """
    poly = outer
    for h in holes:
        d = ((poly[:, None, :].astype(np.int64) - h[None, :, :]) ** 2).sum(-1)
        a, b = np.unravel_index(int(np.argmin(d)), d.shape)
        hh = np.roll(h, -b, axis=0)
        poly = np.concatenate([poly[: a + 1], hh, hh[:1], poly[a:]], axis=0)
    return poly


def mask_polygons(mask: np.ndarray) -> list[np.ndarray]:
    """One polygon per 8-connected component of a mask (holes bridged in).

    Args:
        mask: [H, W] bool.

    Returns:
        int32 polygons [n, 2] of (x, y) vertices; filling them all with
        cv2.fillPoly at [H, W] reproduces the mask.
    """
    contours, hier = cv2.findContours(
        mask.astype(np.uint8), cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE
    )
    if not contours:
        return []
    hier = hier[0]
    out = []
    for k, c in enumerate(contours):
        if hier[k][3] != -1:
            continue
        holes = [contours[j][:, 0, :] for j in range(len(contours)) if hier[j][3] == k]
        out.append(_splice_holes(c[:, 0, :], holes).astype(np.int32))
    return out


MIN_COMPONENT_PX = 3
"""Connected pieces of a query's region smaller than this are left out of the label
and of its truth alike: their contour has fewer than 3 points, which is no
polygon (ISAT readers, ours included, refuse it)."""


def query_mask(part_id: np.ndarray, pids: list[int]) -> np.ndarray:
    """The truth mask of a query in one image, as its label encodes it.

    The pixels of the query's parts, without 8-connected pieces smaller than
    MIN_COMPONENT_PX (slivers of a part seen at a grazing angle).
    """
    mask = np.isin(part_id, pids)
    if not mask.any():
        return mask
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), 8)
    small = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] < MIN_COMPONENT_PX)
    small = small[small > 0]
    if len(small):
        mask &= ~np.isin(lab, small)
    return mask


def isat_label(
    part_id: np.ndarray,  # [H, W] int16
    queries: dict[str, list[int]],
    name: str,
    folder: str,
    min_px: int,
) -> dict:
    """ISAT JSON (docs/method.md §1.2) of one evaluation image from its part-id map.

    Args:
        part_id: truth part ids, [H, W].
        queries: query phrase -> part ids it covers.
        name: the image file name ("<stem>.jpg").
        folder: the value of info.folder.
        min_px: a query with fewer pixels is left out of this image.

    Returns:
        The label dict; categories are the query strings verbatim.
    """
    H, W = part_id.shape
    objects = []
    for group, (query, pids) in enumerate(queries.items(), start=1):
        mask = query_mask(part_id, pids)
        if mask.sum() < min_px:
            continue
        for poly in mask_polygons(mask):
            if len(poly) < 3:  # cannot happen after query_mask; never write one
                raise AssertionError(f"{name}: {query!r} polygon of {len(poly)} points")
            objects.append(
                {
                    "category": query,
                    "group": group,
                    "segmentation": poly.tolist(),
                    "area": float(cv2.contourArea(poly)),
                    "layer": float(len(objects) + 1),
                    "bbox": [
                        int(poly[:, 0].min()),
                        int(poly[:, 1].min()),
                        int(poly[:, 0].max()),
                        int(poly[:, 1].max()),
                    ],
                    "iscrowd": False,
                    "note": "",
                }
            )
    info = {
        "description": "ISAT",
        "folder": folder,
        "name": name,
        "width": int(W),
        "height": int(H),
        "depth": 3,
        "note": "",
    }
    return {"info": info, "objects": objects}


def fill_label(label: dict) -> dict[str, np.ndarray]:
    """Category -> [H, W] bool mask, filled as the evaluation reads ISAT files."""
    H, W = label["info"]["height"], label["info"]["width"]
    out: dict[str, np.ndarray] = {}
    for obj in label["objects"]:
        m = out.setdefault(obj["category"], np.zeros((H, W), np.uint8))
        cv2.fillPoly(m, [np.asarray(obj["segmentation"], np.int32)], 1)
    return {k: v.astype(bool) for k, v in out.items()}


# ------------------------------------------------------------------- points --


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


# --------------------------------------------------------------- vocabulary --


def scene_vocabulary(
    world: World, preset: Preset, distractors: list[str], standin: int = 1
) -> dict:
    """The stand-in encoder's vocabulary: phrase -> canonical swatch description.

    `standin` 5 adds what that version of the stand-in renders its text side
    from: the world ("world") and each part phrase's part ids ("parts")."""
    from ptovs.encoders.synthetic import generic_vocabulary

    phrases: dict[str, dict] = {}
    for part in world.parts:
        sw = part_swatch(world, part, preset.swatch_px)
        phrases[part.query] = sw
        phrases.setdefault(part.name.title(), sw)
    phrases["sky"] = sky_swatch()
    ground = {
        "kind": "texture",
        "texture": world.ground.to_dict(),
        "origin": [0.0, 0.0, 0.0],
        "e1": [1.0, 0.0, 0.0],
        "e2": [0.0, 1.0, 0.0],
        "extent": 6.0,
        "light": part_swatch(world, world.parts[0], 1)["light"],
        "gamma": 2.2,
        "render_px": preset.swatch_px,
    }
    phrases["ground"] = ground
    # a distractor looks like something real that is not in the scene
    for k, phrase in enumerate(distractors):
        rng = np.random.default_rng(
            [int.from_bytes(phrase.encode()[:8].ljust(8, b"\0"), "little"), k]
        )
        tex = random_texture(rng, 3.0)
        phrases[phrase] = dict(
            ground, texture=tex.to_dict(), e2=[0.0, 0.0, -1.0], extent=3.0
        )
    out = {
        "version": 1,
        "phrases": phrases,
        "generic": generic_vocabulary(sky=phrases["sky"], ground=ground),
    }
    if standin == 5:
        parts: dict[str, list[int]] = {}
        for part in world.parts:
            parts.setdefault(part.query, []).append(part.id)
        for part in world.parts:  # a part's name, where it is no one's query
            name = part.name.title()
            if name in phrases and name not in {q.query for q in world.parts}:
                parts.setdefault(name, []).append(part.id)
        out.update(version=standin, world=world.to_dict(), parts=parts)
    elif standin != 1:
        raise ValueError(f"standin must be 1 or 5, got {standin!r}")
    return out


STYLE_AZIMUTHS = (-40.0, 0.0, 40.0)
"""Viewpoints (degrees around the front) a style's look is photographed from."""
STYLE_PX = 128


def landmark_look(world: World) -> list[dict]:
    """A landmark's whole look (a style's text side), as an equal-weight mixture.

    Three swatches of kind "landmark": the whole landmark rendered under the
    neutral daylight from the front and 40 degrees to either side
    (`world.landmark_camera`), masked to the landmark and cropped as a segment
    crop is. The stand-in encoder embeds a style as the normalised mean of the
    three views' content vectors, so a style matches photos of the landmark it
    was drawn from, under any light, and no single part of it. Part names are
    blanked in the stored world: only geometry and textures define the look.
    (Version 1 mixed the parts' own swatches weighted by size squared; the
    encoder could not tell landmarks apart through it: 42 % of bench photos and
    70 % of tiny photos picked their own landmark's style, against 82 % and 89 %
    with the rendered views; work measured in docs/benchmarks.md.)
    """
    d = world.to_dict()
    for p in d["parts"]:
        p["name"] = p["query"] = ""
    w = round(1.0 / len(STYLE_AZIMUTHS), 6)
    return [
        {
            "weight": w,
            "swatch": {"kind": "landmark", "world": d, "azimuth": az, "px": STYLE_PX},
        }
        for az in STYLE_AZIMUTHS
    ]


def scene_styles(preset: Preset, seed: int, world: World) -> tuple[str, dict]:
    """(true style, {candidate style: mixture}) of a seed's landmark.

    Five names are drawn from STYLES (own random stream, so worlds, cameras and
    labels of existing seeds are unchanged); the first is this landmark's style,
    bound to its look (`landmark_look`); each other one is bound to the look of
    the landmark of another seed of the same preset (seed + 7919·k), a
    distractor that looks like a real landmark that is not this one. The
    vocabulary lists the candidates sorted by name, so nothing in it says which
    is true; truth/parts.json does.
    """
    worlds = style_worlds(preset, seed, world)
    styles = {name: landmark_look(w) for name, w in worlds.items()}
    return next(iter(worlds)), dict(sorted(styles.items()))


def style_worlds(preset: Preset, seed: int, world: World) -> dict[str, World]:
    """{style name: the landmark whose look defines it}, the true style first
    (`scene_styles`)."""
    rng = _rng(seed, 8)
    names = [STYLES[i] for i in rng.permutation(len(STYLES))[:N_STYLES]]
    out = {names[0]: world}
    for k, name in enumerate(names[1:], start=1):
        out[name] = _world(preset, seed + 7919 * k)
    return out


# ---------------------------------------------------------------- planning --


def _choose_eval(
    world: World, preset: Preset, cand: list[int], cams: list[Camera]
) -> tuple[list[int], dict[int, np.ndarray]]:
    """Evaluation views, from a truth-only pass over the candidate cameras.

    First a view for each part seen (>= 1 % of an image) in some candidate, in
    part order, then the candidates that see the most parts; `preset.n_eval` in
    all (so on `tiny` a third part may be labelled in no view, and is then no
    query). Returns the views and the candidates' part-id maps.
    """
    counts, truths = {}, {}
    for i in cand:
        pid, _ = render_truth(world, cams[i])
        truths[i] = pid
        m = _min_px(cams[i], 0.01, 12)
        counts[i] = {p.id: int((pid == p.id).sum()) >= m for p in world.parts}
    seen = [p.id for p in world.parts if any(counts[i][p.id] for i in cand)]
    if not seen:
        raise RuntimeError("no part is visible in any evaluation candidate")
    chosen: list[int] = []
    for q in seen:  # every part seen gets at least one evaluation view
        for i in cand:
            if counts[i][q] and i not in chosen:
                chosen.append(i)
                break
    score = sorted(cand, key=lambda i: -sum(counts[i][q] for q in seen))
    for i in score:
        if len(chosen) >= preset.n_eval:
            break
        if i not in chosen and any(counts[i][q] for q in seen):
            chosen.append(i)
    return sorted(chosen[: preset.n_eval]), truths


def label_mask(part_id: np.ndarray, pid: int, cam: Camera) -> np.ndarray | None:
    """A part's label mask in a view, or None when the view does not label it
    (fewer pixels than 0.2 % of the image, at least 12)."""
    mask = query_mask(part_id, [pid])
    return mask if mask.sum() >= _min_px(cam, 0.002, 12) else None


def _prepare_out(out: Path, name: str) -> tuple[Path, Path]:
    scene = out / name
    label = out / "label" / name
    if scene.exists() and any(scene.iterdir()):
        if not (scene / "synthetic" / "truth").is_dir():
            raise FileExistsError(
                f"{scene} exists and is not a synthetic scene; refusing to overwrite"
            )
        shutil.rmtree(scene)
    if label.exists():
        shutil.rmtree(label)
    for p in (
        scene / "dense" / "images",
        scene / "dense" / "sparse",
        scene / "synthetic" / "truth",
        label,
    ):
        p.mkdir(parents=True, exist_ok=True)
    return scene, label


def _save_npz(path: Path, **arrays: np.ndarray) -> None:
    """np.savez_compressed with fixed zip timestamps: byte-identical reruns."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for key, arr in arrays.items():
            info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            with zf.open(info, "w", force_zip64=True) as f:
                np.lib.format.write_array(f, np.asanyarray(arr), allow_pickle=False)


def _write_json(path: Path, obj) -> None:
    path.write_text(json.dumps(obj, indent=1) + "\n")


# ------------------------------------------------------------------ generate --


def _world(cfg: Preset, seed: int) -> World:
    rng = _rng(seed, 0)
    return build_world(rng, int(rng.integers(cfg.n_parts[0], cfg.n_parts[1] + 1)))


@dataclass(frozen=True)
class ScenePlan:
    """Everything about a seed's scene decided before any photo is rendered."""

    world: World  # with the screen's redrawn textures
    test_ids: set[int]
    stems: list[str]
    cams: list[Camera]
    eval_ids: list[int]
    queries: dict[str, list[int]]  # query phrase -> part ids (screened)
    distractor: str
    screen: dict[int, PartScreen]  # the screen's verdict on every part


def plan_scene(preset: str, seed: int, standin: int = 1, extra: int = 0) -> ScenePlan:
    """The plan of (preset, seed): world, cameras, evaluation views, screened queries.

    Renders only truth maps and the screen's neutral crops, so every preset's
    queries and labels can be checked over many seeds cheaply. `extra` train
    photos past the preset's (up to its max_train) come after them, each drawn
    from its own index's streams: the rest of the plan is the same with or
    without them.
    """
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose from {sorted(PRESETS)}")
    if standin not in (1, 5):
        raise ValueError(
            f"stand-in version {standin!r} is not available (only 1 and 5 are); "
            "use standin=1 or standin=5"
        )
    cfg = PRESETS[preset]
    world = _world(cfg, seed)
    n_img = cfg.n_train + cfg.n_test
    draw = _rng(seed, 1)
    test_ids = set(draw.choice(n_img, cfg.n_test, replace=False).tolist())
    train_ids = [i for i in range(n_img) if i not in test_ids]
    n_cand = min(len(train_ids), cfg.n_cand)
    cand = sorted(draw.choice(train_ids, n_cand, replace=False).tolist())
    stems = [
        f"{seed:02d}{i:06d}_{int(draw.integers(10**9, 10**10))}" for i in range(n_img)
    ]
    cams = [
        sample_camera(_rng(seed, 2, i), world, cfg.long_side, frontal=i in cand)
        for i in range(n_img)
    ]
    if not 0 <= extra <= cfg.train_limit - cfg.n_train:
        raise PhotoCountError(
            f"preset {preset!r} holds at most {cfg.train_limit} train photos; "
            f"{cfg.n_train + extra} asked"
        )
    for i in range(n_img, n_img + extra):
        own = _rng(seed, 9, i)
        stems.append(f"{seed:02d}{i:06d}_{int(own.integers(10**9, 10**10))}")
        cams.append(
            sample_camera(_rng(seed, 2, i), world, cfg.long_side, frontal=False)
        )
    eval_ids, cand_truths = _choose_eval(world, cfg, cand, cams)
    eval_cams = [cams[i] for i in eval_ids]
    truths = [cand_truths[i] for i in eval_ids]
    labelled = [
        p.id
        for p in world.parts
        if any(
            label_mask(t, p.id, c) is not None
            for t, c in zip(truths, eval_cams, strict=True)
        )
    ]
    world, verdict = screen_world(
        world,
        seed,
        eval_cams,
        truths,
        labelled,
        lambda w: scene_vocabulary(w, cfg, [], standin),
        label_mask,
    )
    queries = {p.query: [p.id] for p in world.parts if verdict[p.id].answerable}
    if not queries:
        raise RuntimeError(
            f"seed {seed}: no part's phrase passes the answerability screen"
        )
    used = {p.query for p in world.parts}
    distractors = [d for d in DISTRACTORS if d not in used]
    distractor = distractors[int(draw.integers(len(distractors)))]
    cams = [c.scaled(cfg.scale) for c in cams]  # after the screen: as at scale 1
    return ScenePlan(
        world, test_ids, stems, cams, eval_ids, queries, distractor, verdict
    )


class PhotoCountError(ValueError):
    """`--photos N` outside what the preset holds (the message says the range)."""


def photo_subset(plan: ScenePlan, preset: str, photos: int | None) -> list[int]:
    """The images a scene of `photos` train photos keeps, as indices into the plan:
    every test and evaluation view, then the other train views in order. So the
    same world, test split and labelled views come at every size, and a smaller
    collection's photos are a subset of a larger one's (the same pixels)."""
    cfg = PRESETS[preset]
    n_img = cfg.n_train + cfg.n_test
    if photos is None or photos == cfg.n_train:
        return list(range(n_img))
    evals = [i for i in plan.eval_ids if i not in plan.test_ids]
    if not len(evals) <= photos <= cfg.train_limit:
        raise PhotoCountError(
            f"preset {preset!r} takes {len(evals)} to "
            f"{cfg.train_limit} train photos (its {len(evals)} labelled views are train "
            "photos)"
        )
    if photos > cfg.n_train:  # every photo of the plan, then the extra ones
        if len(plan.cams) < n_img + photos - cfg.n_train:
            raise ValueError("plan_scene(extra=...) planned fewer photos than asked")
        return list(range(n_img + photos - cfg.n_train))
    keep = set(plan.test_ids) | set(evals)
    others = [i for i in range(n_img) if i not in keep]
    return sorted(keep | set(others[: photos - len(evals)]))


def eval_labels(preset: str, seed: int) -> list[dict]:
    """The ISAT labels `generate_scene` writes for (preset, seed), without the rest.

    Renders only the evaluation views (labels do not depend on appearance), so
    every preset's labels can be checked over many seeds cheaply.
    """
    plan = plan_scene(preset, seed)
    world, stems, cams, queries = plan.world, plan.stems, plan.cams, plan.queries
    out = []
    for i in plan.eval_ids:
        part_id, _ = render_truth(world, cams[i])
        out.append(
            isat_label(
                part_id,
                queries,
                f"{stems[i]}.jpg",
                f"label/{preset}_s{seed}",
                _min_px(cams[i], 0.002, 12),
            )
        )
    return out


def _photo(
    plan: ScenePlan,
    cfg: Preset,
    i: int,
    seed: int,
    name: str,
    image_dir: Path,
    truth_dir: Path,
    label_dir: Path,
) -> tuple[dict, list[Billboard], tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Render photo `i` of the plan and write it with its truth (and, for an
    evaluation view, its ISAT label); returns its camera record, its occluders and
    its sample of surface points (xyz, part, pixel)."""
    cams, stems, world, queries = plan.cams, plan.stems, plan.world, plan.queries
    eval_set, test_ids = set(plan.eval_ids), plan.test_ids
    cam = cams[i]
    stem = stems[i]
    app = sample_appearance(_rng(seed, 3, i))
    is_eval = i in eval_set
    bbs = (
        []
        if is_eval
        else sample_transients(_rng(seed, 4, i), world, cam, cfg.max_cover)
    )
    view = render(world, cam, app, bbs, aa=cfg.aa)
    jpg = image_dir / f"{stem}.jpg"
    cv2.imwrite(str(jpg), cv2.cvtColor(view.image, cv2.COLOR_RGB2BGR), _JPEG)
    _save_npz(
        truth_dir / f"{stem}.npz",
        part_id=view.part_id,
        transient=view.transient,
        depth=view.depth,
    )
    if is_eval:
        lab = isat_label(
            view.part_id,
            queries,
            f"{stem}.jpg",
            f"label/{name}",
            _min_px(cam, 0.002, 12),
        )
        _check_label(lab, view.part_id, queries)
        _write_json(label_dir / f"{stem}.json", lab)
        shutil.copyfile(jpg, label_dir / f"{stem}.jpg")
    xyz, part, px = _sample_points(
        _rng(seed, 5, i), world, cam, view, cfg.points_per_image
    )
    rec = {"name": f"{stem}.jpg", "image_id": i + 1, **cam.to_dict()}
    rec.update(
        split="test" if i in test_ids else "train",
        eval=is_eval,
        appearance=app.to_dict(),
        hard=app.hard,
        transients=[b.to_dict() for b in bbs],
        transient_fraction=float(view.transient.mean()),
    )
    return rec, bbs, (xyz, part, px)


def generate_scene(
    out: Path,
    preset: str = "tiny",
    seed: int = 0,
    name: str | None = None,
    progress: bool = True,
    standin: int = 1,
    photos: int | None = None,
) -> Path:
    """Generate a synthetic landmark scene in PT-OVS layout.

    Deterministic for a given (preset, seed): identical truth and images. An
    existing synthetic scene of the same name is replaced.

    Args:
        out: the data root (the scene goes to out/<name>, labels to out/label/<name>).
        preset: one of PRESETS.
        seed: a new seed is a new landmark, new cameras and new appearances.
        name: scene folder name; default f"{preset}_s{seed}".
        progress: show a tqdm bar over images.
        standin: the version of the stand-in for CLIP the scene is written for
            (1: the original; 5: calibrated against CLIP's published failure
            profile). It decides the screen's verdicts (so the textures) and the
            vocabulary; cameras and appearances are the same.

    Returns:
        The scene directory out/<name>.
    """
    import pycolmap

    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; choose from {sorted(PRESETS)}")
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    pycolmap.logging.minloglevel = 2
    cfg = PRESETS[preset]
    name = name or f"{preset}_s{seed}" + (f"_p{photos}" if photos else "")
    out = Path(out)
    scene, label_dir = _prepare_out(out, name)
    truth_dir = scene / "synthetic" / "truth"
    image_dir = scene / "dense" / "images"

    plan = plan_scene(preset, seed, standin, extra=max(0, (photos or 0) - cfg.n_train))
    world, queries = plan.world, plan.queries
    eval_ids, distractor = plan.eval_ids, plan.distractor
    ids = photo_subset(plan, preset, photos)
    cams = [plan.cams[i] for i in ids]
    n_img = len(ids)
    logger.info(
        "%s: %d parts, queries %s (+ distractor %r), %d eval views; screen: %s",
        name,
        len(world.parts),
        list(queries),
        distractor,
        len(eval_ids),
        ", ".join(f"{v.query} {v.status}" for v in plan.screen.values()),
    )

    records: list[dict] = []
    all_bbs: list[list[Billboard]] = []
    pts_xyz, pts_part, pts_src, pts_px = [], [], [], []
    for pos, i in enumerate(
        tqdm(ids, desc=f"synth {name}", disable=not progress, unit="img")
    ):
        rec, bbs, (xyz, part, px) = _photo(
            plan, cfg, i, seed, name, image_dir, truth_dir, label_dir
        )
        pts_xyz.append(xyz)
        pts_part.append(part)
        pts_src.append(np.full(len(xyz), pos))
        pts_px.append(px)
        all_bbs.append(bbs)
        records.append(rec)

    xyz = np.concatenate(pts_xyz)
    part = np.concatenate(pts_part).astype(np.int16)
    src = np.concatenate(pts_src)
    px = np.concatenate(pts_px)
    tracks = _tracks(world, cams, all_bbs, xyz, src, px, cfg, seed, progress, ids)
    keep = np.array([len(t) >= 2 for t in tracks])
    ids = _write_colmap(
        scene / "dense" / "sparse", records, cams, world, xyz, part, tracks, keep
    )
    _save_npz(
        truth_dir / "points3D.npz", point3D_id=ids, xyz=xyz[keep], part_id=part[keep]
    )

    with open(scene / f"{preset}.tsv", "w") as f:
        f.write("filename\tid\tsplit\tdataset\n")
        for r in records:
            f.write(f"{r['name']}\t{r['image_id']}\t{r['split']}\t{name}\n")
    vocab = scene_vocabulary(world, cfg, [distractor], standin)
    style, vocab["styles"] = scene_styles(cfg, seed, world)
    _write_json(scene / "synthetic" / "vocabulary.json", vocab)
    parts = world.to_dict()
    parts.update(
        queries=list(queries) + [distractor],
        query_parts=queries,
        distractors=[distractor],
        style=style,
        style_candidates=list(vocab["styles"]),
        preset=preset,
        seed=seed,
        screen=screen_record(plan.screen),
        version=TRUTH_VERSION,
    )
    _write_json(truth_dir / "parts.json", parts)
    _write_json(
        truth_dir / "cameras.json",
        {"images": records, "preset": preset, "seed": seed, "version": TRUTH_VERSION},
    )
    logger.info("%s: %d images, %d points3D -> %s", name, n_img, int(keep.sum()), scene)
    return scene


def _check_label(lab: dict, part_id: np.ndarray, queries: dict[str, list[int]]) -> None:
    for cat, m in fill_label(lab).items():
        gt = query_mask(part_id, queries[cat])
        iou = (m & gt).sum() / max(1, (m | gt).sum())
        if iou < 0.98:
            logger.warning(
                "%s: polygons of %r reproduce the mask with IoU %.3f",
                lab["info"]["name"],
                cat,
                iou,
            )


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


# ---------------------------------------------------------------- re-render --


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
