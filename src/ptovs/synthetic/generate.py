"""Presets and the on-disk layout of a synthetic PT-OVS scene (docs/synthetic.md).

`generate_scene` writes, image by image (memory stays bounded for `scale`):

    out/<name>/dense/images/<stem>.jpg        JPEG q95, sizes vary
    out/<name>/dense/sparse/                  COLMAP model (pycolmap, binary)
    out/<name>/<preset>.tsv                   split file
    out/label/<name>/<stem>.json|.jpg         ISAT labels of the evaluation views
    out/<name>/synthetic/vocabulary.json      for the stand-in encoder only
    out/<name>/synthetic/truth/               cameras.json, parts.json, points3D.npz,
                                              <stem>.npz (part_id, transient, depth)

The parts of the generator live beside this module: `presets` (PRESETS, the
seed's random streams, file helpers), `plan` (`plan_scene`: world, cameras,
screened queries), `labels` (ISAT labels), `points` (sparse points, tracks,
the COLMAP model), `vocabulary` (the stand-in's vocabulary and styles) and
`rerender` (a generated scene read back). Their public names are importable
from here.
"""

from __future__ import annotations

import logging
import shutil
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from ptovs.synthetic.labels import (
    MIN_COMPONENT_PX,
    fill_label,
    isat_label,
    label_mask,
    mask_polygons,
    query_mask,
)
from ptovs.synthetic.plan import (
    PhotoCountError,
    ScenePlan,
    eval_labels,
    photo_subset,
    plan_scene,
)
from ptovs.synthetic.points import _sample_points, _tracks, _write_colmap, clean_albedo
from ptovs.synthetic.presets import (
    _JPEG,
    N_STYLES,
    PRESETS,
    STYLES,
    TRUTH_VERSION,
    Preset,
    _min_px,
    _prepare_out,
    _rng,
    _save_npz,
    _write_json,
)
from ptovs.synthetic.rerender import (
    SURFACE_SAMPLES,
    clean_scene,
    load_truth,
    nearest_parts,
    rerender,
    surface_samples,
)
from ptovs.synthetic.screen import screen_record
from ptovs.synthetic.vocabulary import (
    STYLE_AZIMUTHS,
    STYLE_PX,
    landmark_look,
    scene_styles,
    scene_vocabulary,
    style_worlds,
)
from ptovs.synthetic.world import (
    Billboard,
    render,
    sample_appearance,
    sample_transients,
)

logger = logging.getLogger(__name__)


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


__all__ = [
    "MIN_COMPONENT_PX",
    "N_STYLES",
    "PRESETS",
    "PhotoCountError",
    "Preset",
    "STYLES",
    "STYLE_AZIMUTHS",
    "STYLE_PX",
    "SURFACE_SAMPLES",
    "ScenePlan",
    "TRUTH_VERSION",
    "clean_albedo",
    "clean_scene",
    "eval_labels",
    "fill_label",
    "generate_scene",
    "isat_label",
    "label_mask",
    "landmark_look",
    "load_truth",
    "mask_polygons",
    "nearest_parts",
    "photo_subset",
    "plan_scene",
    "query_mask",
    "rerender",
    "scene_styles",
    "scene_vocabulary",
    "style_worlds",
    "surface_samples",
]
