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

Choices (measured on the bench preset, docs/benchmarks.md):
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
  docs/benchmarks.md). The structure-less registration fallback is off (it took
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
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np

from ptovs.artifacts import Store, json_dataset
from ptovs.atomic import atomic_dir
from ptovs.errors import InputError, MissingInputError
from ptovs.pipeline import IMAGE_EXTS
from ptovs.scene import jpeg_truncated
from ptovs.scene.images import report_alpha

log = logging.getLogger(__name__)

NAME = "sfm"
VERSION = 3  # 2: EXIF-rotated JPEGs are staged upright; 3: repeated features dropped
MIN_REGISTERED = 3
PAIR_SECONDS = 0.2  # exhaustive matching of two 4096-feature photos on 2 cores


@dataclass(frozen=True)
class SfmConfig:
    """How unposed photos are posed (config section `[sfm]`)."""

    max_image_size: int = 1024
    max_num_features: int = 4096
    """SIFT keypoint locations kept per photo. COLMAP gives a location up to two
    orientations, so a photo holds up to twice this many features (5,866 on the
    3072×2048 fountain_p11 photos, docs/benchmarks.md)."""
    peak_threshold: float = 0.0067
    """SIFT detection threshold (COLMAP's default); lower finds more on flat images."""
    min_num_matches: int = 10
    """Minimum verified inliers for a pair, and matches for the mapper (COLMAP: 15;
    10 registers more of the small bench photos once repeated texture is dropped)."""
    pairing: Literal["auto", "exhaustive", "retrieval", "vocabtree", "sequential"] = (
        "auto"
    )
    """"auto": exhaustive while its estimated cost fits exhaustive_budget_s, else
    retrieval."""
    exhaustive_budget_s: float = 300.0
    """Estimated exhaustive matching time allowed under "auto": pairs x 0.2 s x
    (mean features / 4096)² (0.16-0.23 s per pair of real 4096-feature photos
    here), i.e. about 55 real photos, or hundreds of small synthetic ones."""
    retrieval_k: int = 30
    """Nearest photos matched per photo by the retrieval pairing."""
    vocab_tree: str = ""
    """A COLMAP vocabulary-tree file for pairing = "vocabtree" (none can be downloaded)."""
    camera_mode: Literal["per_image", "single", "auto"] = "per_image"
    test_fraction: float = 0.1
    """Share of registered photos held out as the test split."""
    repeat_threshold: float = 0.35
    """Drop a photo's SIFT features whose descriptor lies within this distance (unit
    descriptors, 0..2) of another feature of the same photo at another place:
    repeated texture (tiles, checkers, stripes) that matching cannot tell apart and
    that verifies wrong pairs. 0 keeps every feature."""
    min_pose_inliers: int = 12
    """Inlier 2D-3D matches needed to register a photo (COLMAP's
    abs_pose_min_num_inliers, 30 there; a 250-px photo keeps ~260 features)."""
    pixel_scale: float = 0.0
    """COLMAP's pixel thresholds (4 px for two-view geometry, triangulation and
    filtering; 12 px for registering a photo) are tuned for ~1,000-px photos and
    are multiplied by this. 0: automatic, the median long side the features are
    found at (photo size, at most max_image_size) / 1024, clamped to 0.25..1, so
    photos of 1,024 px or more keep COLMAP's thresholds."""
    structure_less: bool = False
    """COLMAP's structure-less registration fallback (slow on hard photos)."""
    seed: int = 0


# ------------------------------------------------------------------ detection


def photo_dir(path: Path) -> Path | None:
    """The photo folder if `path` is an unposed collection, else None."""
    path = Path(path)
    if (path / "dense").is_dir() or (path / "sparse").is_dir():
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


def _retrieval_pairs(db_path: Path, k: int, seed: int) -> list[tuple[str, str]]:
    """Each photo with its k most similar photos (bag of words on its own SIFT)."""
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    try:
        images = db.read_all_images()
        descs = {}
        for im in images:
            d = db.read_descriptors(im.image_id)
            d = np.asarray(getattr(d, "data", d), np.float32)
            descs[im.name] = d
    finally:
        db.close()
    names = sorted(descs)
    rng = np.random.default_rng(seed)
    sample = np.concatenate(
        [
            d[rng.choice(len(d), min(len(d), 200), replace=False)]
            for d in descs.values()
            if len(d)
        ]
    )
    n_words = int(min(512, max(8, len(sample) // 20)))
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 20, 1.0)
    cv2.setRNGSeed(seed)
    _, _, centers = cv2.kmeans(
        sample, n_words, None, criteria, 1, cv2.KMEANS_PP_CENTERS
    )
    hist = np.zeros((len(names), n_words), np.float32)
    for i, n in enumerate(names):
        d = descs[n]
        if len(d):
            d2 = (d**2).sum(1)[:, None] - 2 * d @ centers.T + (centers**2).sum(1)[None]
            hist[i] = np.bincount(d2.argmin(1), minlength=n_words)
    idf = np.log(len(names) / (1.0 + (hist > 0).sum(0)))
    tfidf = hist * idf
    tfidf /= np.linalg.norm(tfidf, axis=1, keepdims=True).clip(1e-9)
    sim = tfidf @ tfidf.T
    np.fill_diagonal(sim, -np.inf)
    pairs = set()
    for i in range(len(names)):
        for j in np.argsort(-sim[i])[:k]:
            a, b = sorted((names[i], names[int(j)]))
            pairs.add((a, b))
    return sorted(pairs)


def _extract_features(
    db: Path, staged: Path, names: list[str], config: SfmConfig, n_threads: int
) -> None:
    """SIFT features of the staged photos into a fresh COLMAP database `db`."""
    import pycolmap

    db.unlink(missing_ok=True)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_RADIAL"
    ext = pycolmap.FeatureExtractionOptions()
    ext.num_threads = n_threads
    ext.max_image_size = config.max_image_size
    ext.sift.max_num_features = config.max_num_features
    ext.sift.peak_threshold = config.peak_threshold
    mode = {
        "per_image": pycolmap.CameraMode.PER_IMAGE,
        "single": pycolmap.CameraMode.SINGLE,
        "auto": pycolmap.CameraMode.AUTO,
    }[config.camera_mode]
    pycolmap.extract_features(
        db,
        staged,
        image_names=names,
        camera_mode=mode,
        reader_options=reader,
        extraction_options=ext,
        device=pycolmap.Device.cpu,
    )


def _repeat_mask(
    xy: np.ndarray, scale: np.ndarray, desc: np.ndarray, threshold: float
) -> np.ndarray:
    """True for features to keep: no feature at another place within `threshold`.

    xy [n, 2] pixel positions, scale [n] feature sizes (px), desc [n, d] descriptors
    (any non-negative type; compared as unit vectors). Two features are at the same
    place (the two orientations COLMAP gives one location, or one blob found at
    neighbouring scales) when closer than max(3 px, twice the larger size).
    """
    n = len(xy)
    keep = np.ones(n, bool)
    if n < 2 or threshold <= 0:
        return keep
    d = desc.astype(np.float32)
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    xy = xy.astype(np.float32)
    scale = scale.astype(np.float32)
    chunk = max(1, 2_000_000 // n)  # [chunk, n] float32 blocks of ~8 MB
    for lo in range(0, n, chunk):
        hi = min(n, lo + chunk)
        close = (d[lo:hi] @ d.T) > 1.0 - 0.5 * threshold * threshold  # |a-b| < t
        rows, cols = np.nonzero(close)
        sep = np.linalg.norm(xy[lo + rows] - xy[cols], axis=1)
        near = np.maximum(3.0, 2.0 * np.maximum(scale[lo + rows], scale[cols]))
        elsewhere = rows[sep >= near]
        keep[lo + elsewhere] = False
    return keep


def _drop_repeated_features(db: Path, threshold: float) -> tuple[int, int]:
    """Remove repeated-texture features from every photo of database `db` (see
    SfmConfig.repeat_threshold); returns (features before, after)."""
    import pycolmap

    handle = pycolmap.Database.open(str(db))
    try:
        kept = {}
        before = after = 0
        for im in handle.read_all_images():
            kp = np.asarray(handle.read_keypoints(im.image_id))
            desc = handle.read_descriptors(im.image_id)
            data = np.asarray(desc.data)
            # COLMAP keypoints: x, y, a11, a12, a21, a22 (the affine shape)
            scale = np.sqrt(np.abs(kp[:, 2] * kp[:, 5] - kp[:, 3] * kp[:, 4]))
            keep = _repeat_mask(kp[:, :2], scale, data, threshold)
            before += len(kp)
            after += int(keep.sum())
            kept[im.image_id] = (
                np.ascontiguousarray(kp[keep]),
                pycolmap.FeatureDescriptors(
                    desc.type, np.ascontiguousarray(data[keep])
                ),
            )
        handle.clear_keypoints()
        handle.clear_descriptors()
        for image_id, (kp, desc) in kept.items():
            handle.write_keypoints(image_id, kp)
            handle.write_descriptors(image_id, desc)
    finally:
        handle.close()
    return before, after


def _pixel_scale(db: Path, config: SfmConfig) -> float:
    """The factor on COLMAP's pixel thresholds (SfmConfig.pixel_scale), from the
    photo sizes the database's cameras record."""
    import pycolmap

    if config.pixel_scale > 0:
        return float(config.pixel_scale)
    handle = pycolmap.Database.open(str(db))
    try:
        sides = [max(c.width, c.height) for c in handle.read_all_cameras()]
    finally:
        handle.close()
    if not sides:
        return 1.0
    side = min(float(np.median(sides)), float(config.max_image_size))
    return float(np.clip(side / 1024.0, 0.25, 1.0))


def _match_features(
    db: Path,
    workdir: Path,
    names: list[str],
    config: SfmConfig,
    n_threads: int,
    scale: float = 1.0,
) -> str:
    """Match and verify the photo pairs the pairing chooses; returns the pairing used
    ("auto" becomes exhaustive when its estimated time fits the budget)."""
    import pycolmap

    verify = pycolmap.TwoViewGeometryOptions()
    verify.min_num_inliers = config.min_num_matches
    verify.ransac.max_error = 4.0 * scale
    match = pycolmap.FeatureMatchingOptions()
    match.num_threads = n_threads
    pairing = config.pairing
    n_pairs = len(names) * (len(names) - 1) // 2
    db_handle = pycolmap.Database.open(str(db))
    try:
        mean_kp = db_handle.num_keypoints() / max(1, db_handle.num_images())
    finally:
        db_handle.close()
    est = n_pairs * PAIR_SECONDS * (mean_kp / 4096.0) ** 2
    if pairing == "auto":
        pairing = "exhaustive" if est <= config.exhaustive_budget_s else "retrieval"
    log.info(
        "%d photos, %.0f SIFT features each (cap: %d locations, up to 2 "
        "orientations each): exhaustive matching ~%.0f s -> %s",
        len(names),
        mean_kp,
        config.max_num_features,
        est,
        pairing,
    )
    if pairing == "exhaustive":
        pycolmap.match_exhaustive(
            db,
            matching_options=match,
            verification_options=verify,
            device=pycolmap.Device.cpu,
        )
    elif pairing == "sequential":
        pycolmap.match_sequential(
            db,
            matching_options=match,
            verification_options=verify,
            device=pycolmap.Device.cpu,
        )
    elif pairing == "vocabtree":
        if not config.vocab_tree or not Path(config.vocab_tree).is_file():
            raise MissingInputError(
                f"sfm.vocab_tree = {config.vocab_tree!r} is not a file; pairing = "
                "'vocabtree' needs a COLMAP vocabulary-tree file you provide (none can "
                "be downloaded here), or use pairing = 'retrieval'"
            )
        opts = pycolmap.VocabTreePairingOptions()
        opts.vocab_tree_path = str(config.vocab_tree)
        pycolmap.match_vocabtree(
            db,
            matching_options=match,
            pairing_options=opts,
            verification_options=verify,
            device=pycolmap.Device.cpu,
        )
    else:
        pairs = _retrieval_pairs(db, config.retrieval_k, config.seed)
        pair_file = workdir / "pairs.txt"
        pair_file.write_text("".join(f"{a} {b}\n" for a, b in pairs))
        opts = pycolmap.ImportedPairingOptions()
        opts.match_list_path = str(pair_file)
        pycolmap.match_image_pairs(
            db,
            matching_options=match,
            pairing_options=opts,
            verification_options=verify,
            device=pycolmap.Device.cpu,
        )
    return pairing


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
    _extract_features(db, staged, names, config, n_threads)
    if config.repeat_threshold > 0:
        before, after = _drop_repeated_features(db, config.repeat_threshold)
        log.info(
            "repeated texture: %d of %d SIFT features dropped (repeat_threshold %.2f)",
            before - after,
            before,
            config.repeat_threshold,
        )
    t_extract = time.perf_counter() - t0
    t1 = time.perf_counter()
    scale = _pixel_scale(db, config)
    pairing = _match_features(db, workdir, names, config, n_threads, scale)
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
    photos: list[Path], folder: Path, cache: Path, config: SfmConfig
) -> str:
    from ptovs.artifacts import artifact_key, fingerprint_files

    digest = fingerprint_files(photos, folder, cache)  # cached by size and mtime
    return artifact_key(NAME, VERSION, dataclasses.asdict(config), {"photos": digest})


def sfm_location(
    photo_folder: Path, scene: str, work_dir: Path, config: SfmConfig
) -> tuple[list[Path], str, Store, Path]:
    """(the photos, the sfm key, the store, the posed scene folder
    `<work>/<scene>/sfm/<key12>/`) of a photo folder; nothing is read but the
    photos' fingerprints."""
    photos = list_photos(photo_folder)
    key = _photos_key(
        photos, photo_folder, Path(work_dir) / scene / ".fingerprints.json", config
    )
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
