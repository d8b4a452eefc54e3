"""Structure from motion for a folder of unposed photos (pycolmap 4.x, CPU).

`ptovs <stage> --data DIR` where DIR holds only photos (`DIR/images/*` or `DIR/*`,
no COLMAP model, no split file) runs this first. The result is cached in the work
dir under a content key (photos' sha256 + `[sfm]` options), like any artifact, and
materialised as an ordinary COLMAP scene, `<work>/<scene>/sfm/<key[:12]>/`:

    images/        undistorted photos (PINHOLE)
    sparse/        the undistorted COLMAP model
    <scene>.tsv    split: every registered photo is train except a held-out
                   `test_fraction` (default 10 %, every k-th name in sorted order)

so every later stage reads it like a posed scene.

This module stages the photos, maps, undistorts and caches the result; the
`[sfm]` settings (SfmConfig) and the SIFT extraction and matching are in
`ptovs.sfm_match`.

Choices (measured on the bench preset, docs/findings.md):
- Photos are checked first: unreadable files and truncated JPEGs (no end-of-image
  marker: libjpeg decodes them with a warning that names no file) are skipped and
  listed; grey, 16-bit, alpha photos are converted to 8-bit RGB copies, and JPEGs
  with an EXIF orientation are staged as upright copies.
- SIFT on CPU with `max_image_size` 1024 and `max_num_features` 4096 keypoint
  locations (up to two orientations each, so up to 8192 features a photo).
- Pairing: exhaustive while its estimated time (pairs x 0.2 s x (features/4096)²,
  measured on real photos) fits `exhaustive_budget_s` (300 s: ~55 real photos).
  Beyond that, `retrieval`: a bag of visual words learnt on the collection's own SIFT
  descriptors (k-means, tf-idf, cosine) picks each photo's `retrieval_k` nearest
  photos, because no vocabulary tree can be downloaded here; `vocabtree` uses a tree
  file the user gives (`vocab_tree`); `sequential` suits video frames.
- Repeated texture (tiles, checkers, stripes) is dropped before matching: a
  feature with a near-twin descriptor elsewhere in the same photo
  (`repeat_threshold`) cannot be matched reliably, and on the bench photos such
  features (88 % of the wrong pairs' inliers lay on the checkered ground) made 65 %
  of the verified pairs wrong (685 against 369 right); dropping them leaves 51
  wrong against 347 right. The real sets keep their pose error and time.
- COLMAP's pixel thresholds (4 px two-view, triangulation and filtering; 12 px to
  register a photo) assume ~1,000-px photos; they are scaled by the median photo
  size / 1024 (`pixel_scale`, clamped to 0.25..1), so 250-px photos get 1 px and 3
  px, and photos of 1,024 px or more keep COLMAP's values.
- Two-view geometry and the mapper need `min_num_matches` (10) inliers and a photo
  registers on `min_pose_inliers` (12) 2D-3D inliers: with the two choices above,
  bench seeds 0-2 register 56 / 61 / 68 of 88 photos at ~1 deg median rotation error
  (46 / 62 / 56 at 2-3 deg with COLMAP's 15 and 30 and neither choice; see
  docs/findings.md). The structure-less registration fallback is off (it took
  most of 293 s on one bench image).
- One camera per photo (`camera_mode = "per_image"`): Internet photos differ in
  focal length and size. SIMPLE_RADIAL, then `pycolmap.undistort_images`.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ptovs.artifacts import Store, json_dataset
from ptovs.atomic import atomic_dir
from ptovs.errors import InputError, MissingInputError
from ptovs.pipeline import IMAGE_EXTS
from ptovs.scene import jpeg_truncated
from ptovs.scene.images import report_alpha
from ptovs.sfm_match import (
    SfmConfig,
    drop_repeated_features,
    extract_features,
    match_features,
    pixel_scale,
)

log = logging.getLogger(__name__)

NAME = "sfm"
VERSION = 3  # 2: EXIF-rotated JPEGs are staged upright; 3: repeated features dropped
MIN_REGISTERED = 3


# ------------------------------------------------------------------ detection


def is_posed(path: Path) -> bool:
    """Whether `path` holds a posed scene (PhotoTourism's `dense/`, or `sparse/`)."""
    return (path / "dense").is_dir() or (path / "sparse").is_dir()


def photo_dir(path: Path) -> Path | None:
    """The photo folder if `path` is an unposed collection, else None."""
    path = Path(path)
    if is_posed(path):
        return None
    for cand in (path / "images", path):
        if cand.is_dir() and any(
            p.suffix.lower() in IMAGE_EXTS for p in cand.iterdir() if p.is_file()
        ):
            return cand
    return None


def list_photos(folder: Path) -> list[Path]:
    return sorted(
        p
        for p in Path(folder).iterdir()
        if p.is_file() and p.suffix.lower() in IMAGE_EXTS
    )


def _stage_photos(photos: list[Path], out: Path) -> tuple[list[str], dict[str, str]]:
    """Copy usable photos into `out` as 8-bit RGB; returns (names, {skipped: why})."""
    out.mkdir(parents=True, exist_ok=True)
    names, skipped = [], {}
    for src in photos:
        if jpeg_truncated(src):
            skipped[src.name] = "truncated JPEG (no end-of-image marker)"
            log.warning(
                "photo %s is a truncated JPEG; skipped (re-copy or re-export it)", src
            )
            continue
        img = cv2.imread(str(src), cv2.IMREAD_UNCHANGED)
        if img is None:
            skipped[src.name] = "cannot be decoded"
            log.warning("photo %s cannot be decoded; skipped", src)
            continue
        upright = _exif_upright(src)
        if upright is not None:
            img = upright
        elif img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3:
            dst = out / src.name
            shutil.copyfile(src, dst)
            names.append(dst.name)
            continue
        if img.ndim == 3 and img.shape[2] in (2, 4):
            report_alpha(src, img[:, :, -1])
        if img.dtype == np.uint16:
            img = (img / 257.0).round().astype(np.uint8)
        elif img.dtype != np.uint8:
            img = np.nan_to_num(img, nan=0.0, posinf=1.0, neginf=0.0)  # as load_image
            img = (np.clip(img, 0, 1) * 255).round().astype(np.uint8)
        if img.ndim == 2:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        elif img.shape[2] == 2:
            img = cv2.cvtColor(img[:, :, 0], cv2.COLOR_GRAY2BGR)
        elif img.shape[2] == 4:
            img = img[:, :, :3]
        dst = out / (src.stem + ".png")
        if dst.exists() and dst.name != src.name:
            skipped[src.name] = f"name clash with {dst.name}"
            continue
        cv2.imwrite(str(dst), img)
        how = "converted to 8-bit RGB"
        if upright is not None:
            how = "turned upright (EXIF orientation)"
        log.info("photo %s %s as %s", src.name, how, dst.name)
        names.append(dst.name)
    return names, skipped


def _exif_upright(src: Path) -> np.ndarray | None:
    """A JPEG turned upright as its EXIF orientation says (8-bit BGR), or None when
    it has none. COLMAP and our loader read the stored pixels as they are, so a
    rotated phone photo is staged as an upright copy. Found by decoding at 1/8 size
    with and without the orientation applied (OpenCV reads the tag itself)."""
    if src.suffix.lower() not in (".jpg", ".jpeg"):
        return None
    turned = cv2.imread(str(src), cv2.IMREAD_REDUCED_COLOR_8)
    stored = cv2.imread(
        str(src), cv2.IMREAD_REDUCED_COLOR_8 | cv2.IMREAD_IGNORE_ORIENTATION
    )
    if turned is None or stored is None:
        return None
    if turned.shape == stored.shape and np.array_equal(turned, stored):
        return None
    return cv2.imread(str(src), cv2.IMREAD_COLOR)


def sfm_tips(config: SfmConfig, pairing: str = "") -> list[str]:
    """Settings to try when too few photos register: each one a step from the
    settings that ran (never the value already in use; `pairing`: the pairing
    that ran, when "auto" chose it)."""
    tips = []
    if config.min_num_matches > 6:
        tips.append(f"`ptovs --set sfm.min_num_matches={max(6, config.min_num_matches - 4)}` "
                    "(fewer inliers per pair)")  # fmt: skip
    if (pairing or config.pairing) != "exhaustive":
        tips.append("`ptovs --set sfm.pairing=exhaustive` (every pair matched)")
    if config.max_image_size < 2048:
        tips.append(f"`ptovs --set sfm.max_image_size={2 * config.max_image_size}` "
                    f"and `sfm.max_num_features={2 * config.max_num_features}` "
                    "(more features)")  # fmt: skip
    return tips


def sfm_threads() -> int:
    """COLMAP's threads: the process's thread count (`ptovs --threads`, which sets
    torch's), at most 8. One thread makes SfM repeatable run to run; more let
    COLMAP's parallel matching and bundle adjustment order their work freely."""
    import torch

    return max(1, min(torch.get_num_threads(), os.cpu_count() or 1, 8))


def run_sfm(photo_folder: Path, workdir: Path, config: SfmConfig) -> dict[str, Any]:
    """Pose the photos; returns the report and the paths of the undistorted model.

    Raises:
        InputError: fewer than 3 photos could be registered (with what to try).
    """
    import pycolmap

    pycolmap.logging.minloglevel = 2
    photos = list_photos(photo_folder)
    if not photos:
        raise MissingInputError(
            f"{photo_folder} holds no photos ({sorted(IMAGE_EXTS)})"
        )
    t0 = time.perf_counter()
    staged = workdir / "input"
    names, skipped = _stage_photos(photos, staged)
    if len(names) < MIN_REGISTERED:
        raise InputError(
            f"{photo_folder}: only {len(names)} usable photo(s) of {len(photos)}; "
            f"SfM needs at least {MIN_REGISTERED} overlapping photos"
        )
    db = workdir / "database.db"
    n_threads = sfm_threads()
    extract_features(db, staged, names, config, n_threads)
    if config.repeat_threshold > 0:
        before, after = drop_repeated_features(db, config.repeat_threshold)
        log.info(
            "repeated texture: %d of %d SIFT features dropped (repeat_threshold %.2f)",
            before - after,
            before,
            config.repeat_threshold,
        )
    t_extract = time.perf_counter() - t0
    t1 = time.perf_counter()
    scale = pixel_scale(db, config)
    pairing = match_features(db, workdir, names, config, n_threads, scale)
    t_match = time.perf_counter() - t1

    t2 = time.perf_counter()
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = n_threads
    opts.min_num_matches = config.min_num_matches
    opts.structure_less_registration_fallback = config.structure_less
    opts.mapper.abs_pose_min_num_inliers = config.min_pose_inliers
    opts.mapper.abs_pose_max_error = 12.0 * scale
    opts.mapper.init_max_error = 4.0 * scale
    opts.mapper.filter_max_reproj_error = 4.0 * scale
    opts.triangulation.merge_max_reproj_error = 4.0 * scale
    opts.triangulation.complete_max_reproj_error = 4.0 * scale
    opts.random_seed = config.seed
    sparse = workdir / "sparse_raw"
    shutil.rmtree(sparse, ignore_errors=True)
    sparse.mkdir(parents=True)
    recs = pycolmap.incremental_mapping(db, staged, sparse, options=opts)
    t_map = time.perf_counter() - t2
    best = max(recs.values(), key=lambda r: r.num_reg_images(), default=None)
    rejected = _drop_bad_cameras(best) if best is not None else []
    registered = (
        sorted(best.images[i].name for i in best.reg_image_ids()) if best else []
    )
    unregistered = sorted(set(names) - set(registered))
    report = {
        "photos": len(photos),
        "usable": len(names),
        "registered": len(registered),
        "unregistered": unregistered,
        "skipped": skipped,
        "pairing": pairing,
        "pixel_scale": round(scale, 3),
        "rejected_cameras": rejected,
        "models": len(recs),
        "seconds": {
            "extract": round(t_extract, 2),
            "match": round(t_match, 2),
            "map": round(t_map, 2),
        },
    }
    if len(registered) < MIN_REGISTERED:
        raise InputError(
            f"{photo_folder}: SfM registered {len(registered)} of {len(photos)} photos "
            f"(at least {MIN_REGISTERED} are needed). Try: more photos that overlap "
            "(each part of the landmark seen from several nearby viewpoints), "
            + "".join(f"{tip}, " for tip in sfm_tips(config, pairing))
            + "or pose the photos with COLMAP yourself and pass the scene folder"
        )
    if unregistered:
        log.warning(
            "SfM registered %d of %d photos; not registered: %s",
            len(registered),
            len(photos),
            ", ".join(unregistered[:10]) + (" ..." if len(unregistered) > 10 else ""),
        )
    model_dir = sparse / "best"
    model_dir.mkdir()
    best.write(str(model_dir))
    return {"report": report, "model_dir": model_dir, "staged": staged}


def _drop_bad_cameras(rec) -> list[str]:
    """Deregister images whose refined camera is implausible; returns their names.

    A per-photo focal length is weakly constrained; now and then bundle adjustment
    ends with a negative or absurd focal or distortion (seen on a 14-photo walk:
    f = -81,559 px), which would make undistortion produce garbage.
    """
    bad = []
    for image_id in list(rec.reg_image_ids()):
        image = rec.images[image_id]
        cam = rec.cameras[image.camera_id]
        params = np.asarray(cam.params, np.float64)
        f = params[list(cam.focal_length_idxs())]
        size = max(cam.width, cam.height)
        extra = np.delete(
            params, list(cam.focal_length_idxs()) + list(cam.principal_point_idxs())
        )
        ok = (
            np.isfinite(params).all()
            and (f > 0.1 * size).all()
            and (f < 10.0 * size).all()
            and (np.abs(extra) < 1.0).all()
        )
        if not ok:
            bad.append(image.name)
            rec.deregister_frame(image.frame_id)
    if bad:
        log.warning(
            "SfM: %d photo(s) ended with an implausible camera and are left out: %s",
            len(bad),
            ", ".join(bad),
        )
    return bad


def _split_names(names: list[str], fraction: float) -> set[str]:
    """Every k-th name (sorted) is test, k = round(1 / fraction)."""
    if fraction <= 0 or len(names) < 2:
        return set()
    k = max(2, round(1.0 / fraction))
    return {n for i, n in enumerate(sorted(names)) if i % k == k // 2}


def _materialise(
    model_dir: Path, staged: Path, out: Path, scene: str, fraction: float
) -> None:
    import pycolmap

    for stale in out.parent.glob(f".{out.name}.*.tmp"):  # a killed run's (we hold
        shutil.rmtree(stale, ignore_errors=True)  # the store lock)
    with atomic_dir(out) as tmp:  # replaces `out` only once complete
        pycolmap.undistort_images(str(tmp), str(model_dir), str(staged))
        rec = pycolmap.Reconstruction(str(tmp / "sparse"))
        names = sorted(rec.images[i].name for i in rec.reg_image_ids())
        test = _split_names(names, fraction)
        with open(tmp / f"{scene}.tsv", "w") as fh:
            fh.write("filename\tid\tsplit\tdataset\n")
            for i, n in enumerate(names):
                fh.write(f"{n}\t{i}\t{'test' if n in test else 'train'}\t{scene}\n")
        for extra in ("stereo", "run-colmap-geometric.sh", "run-colmap-photometric.sh"):
            p = tmp / extra
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()


def _photos_key(
    photos: list[Path], folder: Path, work_dir: Path, scene: str, config: SfmConfig
) -> str:
    from ptovs.keys import artifact_key, fingerprint_files, model_file_deps

    cache = Path(work_dir) / scene / ".fingerprints.json"
    digest = fingerprint_files(photos, folder, cache)  # cached by size and mtime
    inputs = {"photos": digest, **model_file_deps(NAME, config, work_dir)}
    return artifact_key(NAME, VERSION, dataclasses.asdict(config), inputs)


def sfm_location(
    photo_folder: Path, scene: str, work_dir: Path, config: SfmConfig
) -> tuple[list[Path], str, Store, Path]:
    """(the photos, the sfm key, the store, the posed scene folder
    `<work>/<scene>/sfm/<key12>/`) of a photo folder; nothing is read but the
    photos' fingerprints."""
    photos = list_photos(photo_folder)
    key = _photos_key(photos, photo_folder, work_dir, scene, config)
    store = Store(work_dir)
    return photos, key, store, store.path(scene, NAME, key).with_suffix("")


def sfm_state(
    photo_folder: Path, scene: str, work_dir: Path, config: SfmConfig
) -> tuple[str, str, Path]:
    """(key, state, scene folder) of a photo folder's SfM, without running it.

    State: "done" (the posed scene is there), "partial" (the model is stored, the
    undistorted scene folder is not: `ptovs sfm` rebuilds it in seconds) or
    "missing".
    """
    _, key, store, out = sfm_location(photo_folder, scene, work_dir, config)
    art = store.lookup(scene, NAME, key)
    if art is None:
        return key, "missing", out
    art.close()
    done = (out / "sparse").is_dir() and (out / "images").is_dir()
    return key, "done" if done else "partial", out


def posed_scene(
    photo_folder: Path,
    scene: str,
    work_dir: Path,
    config: SfmConfig,
    *,
    force: bool = False,
) -> Path:
    """The materialised scene folder for a photo folder (runs SfM on a cache miss,
    or always with `force`)."""
    from ptovs.artifacts import provenance

    photos, key, store, out = sfm_location(photo_folder, scene, work_dir, config)
    with store.lock(scene, NAME, key):
        art = store.lookup(scene, NAME, key)
        if art is not None and force:
            art.close()
            os.remove(art.path)
            art = None
        if art is not None and (out / "sparse").is_dir() and (out / "images").is_dir():
            art.close()
            return out
        with tempfile.TemporaryDirectory(
            dir=out.parent if out.parent.exists() else None
        ) as td:
            td = Path(td)
            if art is not None:  # the artifact holds the model: only undistort again
                root = art.root()
                art.close()
                model_dir = td / "model"
                model_dir.mkdir()
                for name in ("cameras", "images", "points3D", "rigs", "frames"):
                    if f"model_{name}" in root:
                        (model_dir / f"{name}.bin").write_bytes(
                            root[f"model_{name}"].tobytes()
                        )
                _stage_photos(photos, td / "input")
                _materialise(model_dir, td / "input", out, scene, config.test_fraction)
                return out
            log.info(
                "SfM on %d photos in %s (cached under %s)",
                len(photos),
                photo_folder,
                key[:12],
            )
            result = run_sfm(photo_folder, td, config)
            report = result["report"]
            _materialise(
                result["model_dir"], result["staged"], out, scene, config.test_fraction
            )
            datasets = {"report_json": json_dataset(report)}
            for f in sorted(Path(result["model_dir"]).glob("*.bin")):
                datasets[f"model_{f.stem}"] = np.frombuffer(
                    f.read_bytes(), np.uint8
                ).copy()
            attrs = dict(
                provenance(),
                version=VERSION,
                scene=scene,
                config_json=json_dataset(dataclasses.asdict(config)).tobytes().decode(),
                inputs_json="{}",
            )
            writer = store.writer(scene, NAME, key, attrs)
            writer.write_root(datasets)
            writer.finish().close()
            log.info(
                "SfM: registered %d of %d photos (%s pairing) in %.1f s -> %s",
                report["registered"],
                report["photos"],
                report["pairing"],
                sum(report["seconds"].values()),
                out,
            )
    return out
