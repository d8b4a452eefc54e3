"""ISAT label JSONs: where they live, reading them and filling the masks per category."""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ptovs.errors import InputError, MissingInputError
from ptovs.scene.images import resize_map
from ptovs.scene.views import Scene, View

logger = logging.getLogger(__name__)


GT_RESIZE_MODES = ("nearest", "bilinear")


def _label_path(source: Scene | str | Path, stem: str) -> Path:
    if isinstance(source, Scene):
        if source.labels_dir is None:
            raise MissingInputError(
                f"scene {source.name} has no labels folder "
                f"({source.root.parent / 'label' / source.name} does not exist); "
                "put the ISAT JSONs there or pass labels_dir"
            )
        d = source.labels_dir
    else:
        d = Path(source)
    path = d / f"{stem}.json"
    if not path.is_file():
        raise MissingInputError(
            f"label file {path} does not exist; labels are ISAT JSONs named "
            "<image stem>.json"
        )
    return path


def labels_digest(scene: Scene) -> str:
    """sha256 over the scene's label files (stem and content), or "none": the key
    of what the stages that read labels (query, evaluate) read."""
    import hashlib

    files = scene.label_files()
    if not files:
        return "none"
    h = hashlib.sha256()
    for path in files:
        h.update(path.stem.encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


def read_label_json(path: str | Path) -> dict[str, Any]:
    """Read and validate one ISAT label JSON.

    Args:
        path: the JSON file.

    Returns:
        {"name": info.name, "width": W, "height": H, "objects": [(category,
        vertices [V, 2] float64), ...]} in file order.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(
            f"label file {path} is not valid JSON ({exc}); fix it"
        ) from exc

    def bad(why: str) -> InputError:
        return InputError(
            f"label file {path}: {why}; expected ISAT format "
            '{"info": {"name", "width", "height"}, "objects": [{"category", '
            '"segmentation": [[x, y], ...]}]}'
        )

    if not isinstance(data, dict):
        raise bad("top level is not an object")
    info = data.get("info")
    if not isinstance(info, dict):
        raise bad("missing 'info' object")
    name = info.get("name")
    if not isinstance(name, str) or not name:
        raise bad("info.name is missing or not a string")
    wh = []
    for key in ("width", "height"):
        v = info.get(key)
        if (
            isinstance(v, bool)
            or not isinstance(v, int | float)
            or v != int(v)
            or v < 1
        ):
            raise bad(f"info.{key} = {v!r} is not a positive integer")
        wh.append(int(v))
    objects = data.get("objects")
    if not isinstance(objects, list):
        raise bad("missing 'objects' list")
    out = []
    for i, obj in enumerate(objects):
        if not isinstance(obj, dict):
            raise bad(f"objects[{i}] is not an object")
        cat = obj.get("category")
        if not isinstance(cat, str) or not cat:
            raise bad(f"objects[{i}].category = {cat!r} is not a non-empty string")
        seg = obj.get("segmentation")
        try:
            verts = np.asarray(seg, dtype=np.float64)
        except (TypeError, ValueError):
            verts = None
        if verts is None or verts.ndim != 2 or verts.shape[1] != 2:
            raise bad(f"objects[{i}].segmentation is not a list of [x, y] points")
        if len(verts) < 3:
            raise bad(
                f"objects[{i}] ({cat!r}) has a polygon with {len(verts)} point(s), "
                "at least 3 are needed"
            )
        if not np.all(np.isfinite(verts)):
            raise bad(f"objects[{i}] ({cat!r}) has non-finite vertices")
        w, h = wh
        lo, hi = verts.min(0), verts.max(0)
        if lo[0] < -w or lo[1] < -h or hi[0] > 2 * w or hi[1] > 2 * h:
            raise bad(
                f"objects[{i}] ({cat!r}) has vertices far outside the {w}x{h} image "
                f"(x {lo[0]:.4g}..{hi[0]:.4g}, y {lo[1]:.4g}..{hi[1]:.4g}); are they "
                "pixel coordinates of this image?"
            )
        if lo[0] < -1 or lo[1] < -1 or hi[0] > w + 1 or hi[1] > h + 1:
            logger.warning(
                "label file %s: objects[%d] (%r) reaches outside the %dx%d image; "
                "the polygon is clipped to it", path, i, cat, w, h,
            )  # fmt: skip
        out.append((cat, verts))
    return {"name": name, "width": wh[0], "height": wh[1], "objects": out}


def read_label_of(path: Path, stem: str) -> dict[str, Any]:
    """`read_label_json`, and the label must name the image `stem`."""
    label = read_label_json(path)
    if Path(label["name"]).stem != Path(stem).name:
        raise InputError(
            f"label file {path} has info.name {label['name']!r}, which is not the "
            f"image {stem!r}; rename the file or fix info.name"
        )
    return label


def load_labels(
    source: Scene | str | Path,
    view: View | str,
    size: tuple[int, int] | None = None,
    *,
    gt_resize: str = "nearest",
) -> dict[str, np.ndarray]:
    """Ground-truth masks of one labelled view (docs/method.md §1.2, §9).

    Args:
        source: the Scene (its `labels_dir`) or a labels folder.
        view: the View, or an image stem.
        size: target (H, W), numpy order; default the view's working size (the
            JSON's own size when `view` is a stem).
        gt_resize: "nearest" (ptovs default) or "bilinear" (the authors' cv2
            bilinear resize of the uint8 0/1 mask, which rounds at 0.5).

    Returns:
        {category (verbatim): bool mask [H, W]}, in order of first appearance.
    """
    if gt_resize not in GT_RESIZE_MODES:
        raise InputError(
            f"gt_resize must be one of {GT_RESIZE_MODES}, got {gt_resize!r}"
        )
    stem = view.stem if isinstance(view, View) else str(view)
    path = _label_path(source, stem)
    label = read_label_of(path, stem)
    W, H = label["width"], label["height"]
    if isinstance(view, View) and (W, H) != (view.full_width, view.full_height):
        # labels drawn on a resized copy are fine when the aspect matches
        if abs(W * view.full_height - H * view.full_width) > max(W, H):
            raise InputError(
                f"label file {path} is {W}x{H} but image {view.name} is "
                f"{view.full_width}x{view.full_height}; the labels belong to another "
                "image or crop"
            )
        logger.warning(
            "label %s is %dx%d, image %s is %dx%d: masks are rescaled",
            path,
            W,
            H,
            view.name,
            view.full_width,
            view.full_height,
        )
    if size is None:
        size = view.size if isinstance(view, View) else (H, W)
    masks: dict[str, np.ndarray] = {}
    for cat, verts in label["objects"]:
        m = masks.get(cat)
        if m is None:
            m = masks[cat] = np.zeros((H, W), np.uint8)
        # the authors cast vertices to int32 (truncation) and fill at full size
        cv2.fillPoly(m, [verts.astype(np.int32).reshape(-1, 1, 2)], 1)
    if not masks:
        logger.warning("label file %s has no objects", path)
    th, tw = int(size[0]), int(size[1])
    out = {}
    for cat, m in masks.items():
        if (th, tw) != (H, W):
            if gt_resize == "nearest":
                m = resize_map(m, (th, tw), kind="nearest")
            else:
                m = cv2.resize(m, (tw, th), interpolation=cv2.INTER_LINEAR)
        out[cat] = m.astype(bool)
    return out


def label_categories(
    source: Scene | str | Path, view: View | str | None = None
) -> list[str]:
    """Categories (query texts, verbatim) of one label or of all of them.

    Args:
        source: the Scene or a labels folder.
        view: a View or stem; None takes every labelled view of the Scene (or
            every JSON of the folder, by name).

    Returns:
        Categories in order of first appearance, without duplicates.
    """
    if view is not None:
        stems = [view.stem if isinstance(view, View) else str(view)]
    elif isinstance(source, Scene):
        stems = [v.stem for v in source.labelled_views()]
    else:
        stems = sorted(p.stem for p in Path(source).glob("*.json"))
    cats: dict[str, None] = {}
    for stem in stems:
        for cat, _ in read_label_json(_label_path(source, stem))["objects"]:
            cats.setdefault(cat)
    return list(cats)


def resolve_labels_dir(root: Path, labels_dir: str | Path | None) -> Path | None:
    if labels_dir is None:
        guess = root.resolve().parent / "label" / root.resolve().name
        return guess if guess.is_dir() else None
    path = Path(labels_dir).expanduser()
    if not path.is_dir():
        raise MissingInputError(
            f"labels folder {path} does not exist; pass the folder holding the "
            "ISAT <image stem>.json files, or leave labels_dir unset"
        )
    return path
