"""`load_scene`: a scene folder → a `Scene` (no image decoded)."""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import numpy as np

from ptovs.errors import InputError, MissingInputError
from ptovs.scene.colmap import (
    DISTORTION_MODES,
    detect_layout,
    find_model,
    model_files,
    pinhole_K,
    points_arrays,
    read_model,
    registered_images,
)
from ptovs.scene.images import check_downscale, scale_intrinsics, working_size
from ptovs.scene.labels import resolve_labels_dir
from ptovs.scene.split import (
    assign_splits,
    preview,
    read_split_tsv,
    resolve_split_file,
)
from ptovs.scene.views import Scene, View

logger = logging.getLogger(__name__)


def _check_labels(views: list, labels: Path) -> None:
    """Parse every label file of a labelled view (format, finite and sane
    coordinates, the image it names): cheap, no polygon is filled."""
    from ptovs.scene.labels import read_label_of

    for v in views:
        if v.has_label:
            read_label_of(labels / f"{v.stem}.json", v.stem)


def load_scene(
    path: str | Path,
    *,
    downscale: int | str = "auto",
    split_file: str | Path = "auto",
    labels_dir: str | Path | None = None,
    distortion: str = "refuse",
    name: str | None = None,
) -> Scene:
    """Load a PhotoTourism or COLMAP scene (no image is decoded).

    Args:
        path: the scene folder.
        downscale: "auto" (the smallest r that brings the median long side to
            at most AUTO_LONG_SIDE px) or an integer r >= 1.
        split_file: "auto" (the single *.tsv in the scene root), "all-train", or a
            path to a TSV.
        labels_dir: folder of ISAT JSONs; None looks for
            `<path>/../label/<scene name>/`.
        distortion: "refuse" (non-zero lens distortion is an error) or "ignore"
            (drop it with a warning).
        name: the scene's name in logs and messages (default: the folder's; a
            folder posed by SfM is named by the photo folder the user gave).

    Returns:
        The Scene, views sorted by name.
    """
    root = Path(path).expanduser()
    if distortion not in DISTORTION_MODES:
        raise InputError(
            f"distortion must be one of {DISTORTION_MODES}, got {distortion!r}"
        )
    layout = detect_layout(root)
    synthetic = (root / "synthetic").is_dir()
    model_dir, ext = find_model(layout.sparse_dir)
    rec = read_model(model_dir, ext)

    tsv = resolve_split_file(root, layout.kind, split_file)
    splits = read_split_tsv(tsv) if tsv is not None else None

    by_name = registered_images(rec, model_dir)

    chosen = assign_splits(by_name, splits, tsv, model_dir)
    auto = isinstance(downscale, str) and downscale == "auto"
    r = auto_downscale(rec, by_name, chosen) if auto else check_downscale(downscale)

    labels = resolve_labels_dir(root, labels_dir)

    views, stems, dropped = _make_views(
        rec, by_name, chosen, layout.images_dir, model_dir, r, distortion, labels
    )
    _warn(views, stems, dropped, labels, model_dir)
    if labels is not None:  # broken label files fail now, not after the training
        _check_labels(views, Path(labels))

    ids, xyz, rgb, err, tlen = points_arrays(rec)
    scene = Scene(
        root=root,
        name=name or root.resolve().name,
        downscale=r,
        views=views,
        points_xyz=xyz,
        points_rgb=rgb,
        points_error=err,
        points_track_len=tlen,
        labels_dir=labels,
        split_file=tsv,
        synthetic=synthetic,
        points_id=ids,
        layout=layout.kind,
        images_dir=layout.images_dir,
        model_dir=model_dir,
        model_files=model_files(model_dir, ext),
    )
    logger.info(
        "scene %s: %d views (%d train, %d test, %d labelled), %d points, r=%d",
        scene.name,
        len(views),
        len(scene.train_views()),
        len(scene.test_views()),
        sum(v.has_label for v in views),
        len(xyz),
        r,
    )
    return scene


AUTO_LONG_SIDE = 1000
"""downscale = "auto": the smallest r that brings the photos' median long side to at
most this many pixels (12 MP photos, 4000 px: r = 4, 1000 px; 3072 px: r = 4, 768
px; PhotoTourism's ~1000–1600 px: r = 2 as in the paper; small photos: r = 1)."""


def auto_downscale(rec: Any, by_name: dict[str, int], chosen: dict[str, str]) -> int:
    """The downscale factor "auto" resolves to for the chosen images (no decoding:
    sizes come from the model's cameras)."""
    sides = [
        max(int(cam.width), int(cam.height))
        for cam in (rec.cameras[rec.images[by_name[n]].camera_id] for n in chosen)
    ]
    if not sides:
        return 1
    return max(1, math.ceil(float(np.median(sides)) / AUTO_LONG_SIDE))


def _make_views(
    rec: Any,
    by_name: dict[str, int],
    chosen: dict[str, str],
    images_dir: Path,
    model_dir: Path,
    r: int,
    distortion: str,
    labels: Path | None,
) -> tuple[list[View], dict[str, str], list[str]]:
    """(views in name order, {stem: name}, cameras whose distortion was dropped)."""
    cam_K: dict[int, np.ndarray] = {}
    dropped: list[str] = []
    views: list[View] = []
    stems: dict[str, str] = {}
    for name in sorted(chosen):
        image = rec.images[by_name[name]]
        cam_id = int(image.camera_id)
        cam = rec.cameras[cam_id]
        if cam_id not in cam_K:
            cam_K[cam_id], lossy = pinhole_K(cam, cam_id, name, model_dir, distortion)
            if lossy:
                dropped.append(f"{cam_id} ({cam.model.name})")
        image_path = images_dir / name
        if not image_path.is_file():
            raise MissingInputError(
                f"image {image_path} (listed in the model {model_dir}) does not "
                f"exist; restore it or remove the image from the model"
            )
        stem = str(Path(name).with_suffix("").as_posix())
        if stem in stems:
            raise InputError(
                f"images {stems[stem]!r} and {name!r} in {model_dir} share the stem "
                f"{stem!r}; ptovs keys views (and labels) by stem, rename one"
            )
        stems[stem] = name
        full = (int(cam.width), int(cam.height))
        w, h = working_size(*full, r)
        K = scale_intrinsics(cam_K[cam_id], full, (w, h))
        T = np.eye(4)
        T[:3, :4] = np.asarray(image.cam_from_world().matrix(), dtype=np.float64)
        K.setflags(write=False)
        T.setflags(write=False)
        views.append(
            View(
                name=name,
                stem=stem,
                image_id=int(image.image_id),
                image_path=image_path,
                split=chosen[name],
                K=K,
                cam_from_world=T,
                width=w,
                height=h,
                full_width=full[0],
                full_height=full[1],
                has_label=labels is not None and (labels / f"{stem}.json").is_file(),
            )
        )
    return views, stems, dropped


def _warn(
    views: list[View],
    stems: dict[str, str],
    dropped: list[str],
    labels: Path | None,
    model_dir: Path,
) -> None:
    """Warnings about what was loaded: dropped distortion, labelled test views,
    label files that match no view."""
    if dropped:
        logger.warning(
            "%s: ignoring non-zero lens distortion of camera(s) %s "
            "(distortion='ignore'); projections are off by the distortion, most near "
            "the image borders",
            model_dir,
            preview(dropped),
        )
    labelled_test = [v.name for v in views if v.has_label and v.split != "train"]
    if labelled_test:
        logger.warning(
            "%d labelled view(s) are in the test split (PT-OVS evaluates train "
            "views): %s",
            len(labelled_test),
            preview(labelled_test),
        )
    if labels is not None:
        orphans = sorted({p.stem for p in labels.glob("*.json")} - set(stems))
        if orphans:
            logger.warning(
                "%s: %d label file(s) match no view of the scene: %s",
                labels,
                len(orphans),
                preview(orphans),
            )
