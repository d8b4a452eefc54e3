"""Scene I/O: COLMAP-posed photo collections, split files, images and ISAT labels.

The package face; the rooms: `views` (Scene, View), `load` (load_scene), `colmap`
(layouts, model reading, intrinsics), `split` (the TSV), `images` (resolution,
decoding, per-pixel maps) and `labels` (ISAT JSONs).

Every later stage reads its scene through this module, so the rules below hold for
the whole pipeline (docs/method.md §1 and §9).

Layouts (detected by `load_scene`):
- PhotoTourism: `<scene>/dense/images/`, `<scene>/dense/sparse/` (the model directly
  in there, or in `sparse/0`), and a NeRF-W style split `<scene>/<short>.tsv`.
- plain COLMAP: `<scene>/images/` and `<scene>/sparse/0/` (or `<scene>/sparse/`).
Models are read with pycolmap: classic 3-file models and COLMAP-4 5-file models
(rigs, frames), binary or text. Binary files are walked once before pycolmap sees
them, because pycolmap hangs on some truncated `points3D.bin` files.

Resolution: one integer factor r per scene ("auto": 1 when `<scene>/synthetic/`
exists, else 2). The working size is (round(W/r), round(H/r)) (Python round), and the
intrinsics are scaled by newW/W (fx, cx) and newH/H (fy, cy); with pixel centres
at +0.5 this scaling of continuous coordinates is exact. Python's round takes
halves to even (97/2 -> 48), exactly as the authors' 3DGS loader does, so our
pixel grid equals theirs. `View.K`, `View.width` and `View.height` are at working size;
every per-pixel map must be at that size (`check_size`, `resize_map`).

Cameras (decision): PINHOLE and SIMPLE_PINHOLE are used as they are. SIMPLE_RADIAL,
RADIAL, OPENCV, FULL_OPENCV, SIMPLE_DIVISION and DIVISION are accepted as pinhole
when all their distortion parameters are exactly 0. Non-zero distortion is refused
by default (`distortion="refuse"`, an InputError that names the camera and the fix:
undistort with `colmap image_undistorter` or `pycolmap.undistort_images`); with
`distortion="ignore"` it is dropped with a warning, as the authors' code silently
does for SIMPLE_RADIAL. Fisheye and other models are always refused, because
dropping their parameters does not give a pinhole camera.

Split (decision): `split_file="auto"` takes the single `*.tsv` in the scene root.
Without one, a PhotoTourism scene is an error (add a TSV or pass "all-train") and a
COLMAP scene is all train. In the TSV only `filename` and `split` are read; any split
other than "train" is test. Registered model images that the TSV does not list are
LEFT OUT with a warning (the authors' code uses only listed images); TSV names that
the model lacks are warned about and skipped.

Labels: ISAT JSONs at `<scene>/../label/<scene name>/<stem>.json`. Polygons are
filled at the JSON's original size, OR-ed per category (verbatim, case-sensitive:
they are the query texts) and resized to the working size with nearest sampling
(ptovs default) or the authors' bilinear resize of the uint8 0/1 mask.

Images are decoded only on request (`load_image`); EXIF orientation is ignored, as
COLMAP ignores it, and a decoded size that differs from the camera's is an error.
"""

from __future__ import annotations

from ptovs.scene.colmap import DISTORTION_MODES, MODEL_FILES, PINHOLE_MODELS
from ptovs.scene.images import (
    RESIZE_KINDS,
    PhotoStack,
    check_size,
    jpeg_truncated,
    load_image,
    resize_map,
    scale_intrinsics,
    working_size,
)
from ptovs.scene.labels import (
    GT_RESIZE_MODES,
    label_categories,
    labels_digest,
    load_labels,
    read_label_json,
)
from ptovs.scene.load import load_scene
from ptovs.scene.split import read_split_tsv
from ptovs.scene.views import Scene, View

__all__ = [
    "DISTORTION_MODES",
    "GT_RESIZE_MODES",
    "MODEL_FILES",
    "PINHOLE_MODELS",
    "PhotoStack",
    "RESIZE_KINDS",
    "Scene",
    "View",
    "check_size",
    "jpeg_truncated",
    "label_categories",
    "labels_digest",
    "load_image",
    "load_labels",
    "load_scene",
    "read_label_json",
    "read_split_tsv",
    "resize_map",
    "scale_intrinsics",
    "working_size",
]
