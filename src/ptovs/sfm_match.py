"""SfM's settings (config section `[sfm]`) and COLMAP's work on the photos before
mapping: SIFT extraction, dropping repeated texture, choosing the pairs and
matching them (pycolmap 4.x, CPU).

`ptovs.sfm` stages the photos, calls these in order, then maps and undistorts;
the module docstring there says why each choice was made.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from ptovs.errors import MissingInputError

log = logging.getLogger(__name__)

PAIR_SECONDS = 0.2  # exhaustive matching of two 4096-feature photos on 2 cores


@dataclass(frozen=True)
class SfmConfig:
    """How unposed photos are posed (config section `[sfm]`)."""

    max_image_size: int = 1024
    max_num_features: int = 4096
    """SIFT keypoint locations kept per photo. COLMAP gives a location up to two
    orientations, so a photo holds up to twice this many features (5,866 on the
    3072×2048 fountain_p11 photos, docs/findings.md)."""
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


# ------------------------------------------------------------------ features and matching


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


def extract_features(
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


def drop_repeated_features(db: Path, threshold: float) -> tuple[int, int]:
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


def pixel_scale(db: Path, config: SfmConfig) -> float:
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


def match_features(
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
