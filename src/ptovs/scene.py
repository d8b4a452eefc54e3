"""Scene I/O: COLMAP-posed photo collections, split files, images and ISAT labels.

Every later stage reads its scene through this module, so the rules below hold for
the whole pipeline (PAPER_SPEC.md §1 and §9).

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

import functools
import json
import logging
import struct
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pycolmap

from ptovs.errors import InputError, MissingInputError

logger = logging.getLogger(__name__)

pycolmap.logging.minloglevel = 2  # otherwise every read prints glog lines

PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
# Perspective models that are exactly pinhole when their extra parameters are 0.
ZERO_DISTORTION_MODELS = (
    "SIMPLE_RADIAL",
    "RADIAL",
    "OPENCV",
    "FULL_OPENCV",
    "SIMPLE_DIVISION",
    "DIVISION",
)
DISTORTION_MODES = ("refuse", "ignore")
GT_RESIZE_MODES = ("nearest", "bilinear")
RESIZE_KINDS = ("nearest", "area", "linear")
MODEL_FILES = ("cameras", "images", "points3D")
MODEL_FILES_V4 = ("rigs", "frames")

_UNDISTORT_FIX = (
    "undistort the images first, e.g. `colmap image_undistorter --image_path IMAGES "
    "--input_path SPARSE --output_path OUT` or `pycolmap.undistort_images(OUT, "
    "SPARSE, IMAGES)`, and point ptovs at OUT (its images/ and sparse/)"
)


# --------------------------------------------------------------------------- views


@dataclass(frozen=True, eq=False)
class View:
    """One registered image of a scene, with its camera at working resolution."""

    name: str
    """Image file name as in the COLMAP model, e.g. "15080601_1551250100.jpg"."""
    stem: str
    """`name` without its extension: the key of labels and per-view artifacts."""
    image_id: int
    """COLMAP image id."""
    image_path: Path
    split: str
    """"train" or "test"."""
    K: np.ndarray  # [3, 3] float64, at working size
    cam_from_world: np.ndarray  # [4, 4] float64
    width: int
    """Working width (after the downscale r)."""
    height: int
    full_width: int
    """Width of the COLMAP camera (the image file on disk)."""
    full_height: int
    has_label: bool = False
    """Whether `<labels_dir>/<stem>.json` exists."""

    @property
    def size(self) -> tuple[int, int]:
        """Working size as (H, W), numpy order."""
        return (self.height, self.width)


@dataclass
class Scene:
    """A loaded scene: views sorted by name, sparse points, where labels live."""

    root: Path
    name: str
    downscale: int
    views: list[View]
    points_xyz: np.ndarray  # [P, 3] float64
    points_rgb: np.ndarray  # [P, 3] uint8
    points_error: np.ndarray  # [P] float64
    points_track_len: np.ndarray  # [P] int64
    labels_dir: Path | None
    split_file: Path | None
    synthetic: bool
    points_id: np.ndarray = field(
        default_factory=lambda: np.zeros(0, np.int64)
    )  # [P] int64, COLMAP point3D ids
    layout: str = "colmap"
    """"phototourism" or "colmap"."""
    images_dir: Path | None = None
    model_dir: Path | None = None
    model_files: list[Path] = field(default_factory=list)
    _index: dict[str, View] = field(init=False, repr=False, default_factory=dict)

    def __post_init__(self) -> None:
        self._index = {}
        for v in self.views:
            self._index[v.name] = v
        for v in self.views:
            self._index.setdefault(v.stem, v)

    def train_views(self) -> list[View]:
        """Views of the train split, in name order."""
        return [v for v in self.views if v.split == "train"]

    def test_views(self) -> list[View]:
        """Views of the test split, in name order."""
        return [v for v in self.views if v.split == "test"]

    def labelled_views(self) -> list[View]:
        """Views with a label JSON, in name order."""
        return [v for v in self.views if v.has_label]

    def view(self, name_or_stem: str) -> View:
        """The view with this image name or stem.

        Raises:
            KeyError: no such view (the message lists a few names).
        """
        try:
            return self._index[name_or_stem]
        except KeyError:
            some = ", ".join(v.name for v in self.views[:5])
            raise KeyError(
                f"no view {name_or_stem!r} in scene {self.name} "
                f"({len(self.views)} views, e.g. {some})"
            ) from None

    def load_image(self, view: View | str) -> np.ndarray:
        """`load_image` for a view of this scene (or its name or stem)."""
        if isinstance(view, str):
            view = self.view(view)
        return load_image(view)

    def fingerprint_files(self) -> list[Path]:
        """The files whose content defines the scene.

        Returns:
            Model files, the split file (if any), the views' label JSONs and the
            views' images, in that order.
        """
        files = list(self.model_files)
        if self.split_file is not None:
            files.append(self.split_file)
        if self.labels_dir is not None:
            files += [
                self.labels_dir / f"{v.stem}.json" for v in self.views if v.has_label
            ]
        files += [v.image_path for v in self.views]
        return files


# ------------------------------------------------------------------- resolution


def working_size(width: int, height: int, downscale: int) -> tuple[int, int]:
    """Working image size for the downscale factor r.

    Args:
        width, height: full size (COLMAP camera).
        downscale: integer r >= 1.

    Returns:
        (width, height) = (round(W/r), round(H/r)), at least 1 each. Python's
        round (halves to even) as in the authors' 3DGS loader, so that our pixel
        grid equals theirs on the real scenes (an odd width 97 at r=2 gives 48).
    """
    r = _check_downscale(downscale)
    return max(1, round(width / r)), max(1, round(height / r))


def scale_intrinsics(
    K: np.ndarray,  # [3, 3]
    full_size: tuple[int, int],
    new_size: tuple[int, int],
) -> np.ndarray:
    """Scale a pinhole K from one image size to another.

    Args:
        K: intrinsics at `full_size`, pixel centres at +0.5 (COLMAP convention).
        full_size, new_size: (width, height).

    Returns:
        K at `new_size` [3, 3] float64: fx, cx times newW/W; fy, cy times newH/H.
    """
    sx = new_size[0] / full_size[0]
    sy = new_size[1] / full_size[1]
    out = np.array(K, dtype=np.float64, copy=True)
    out[0, :] *= sx
    out[1, :] *= sy
    return out


def _check_downscale(downscale: Any) -> int:
    if isinstance(downscale, str) and downscale.strip().isdigit():
        downscale = int(downscale.strip())
    if isinstance(downscale, bool) or not isinstance(downscale, int | np.integer):
        raise InputError(
            f"downscale must be 'auto' or an integer >= 1, got {downscale!r}; "
            "e.g. --set scene.downscale=2"
        )
    if downscale < 1:
        raise InputError(
            f"downscale must be an integer >= 1, got {downscale}; "
            "e.g. --set scene.downscale=2"
        )
    return int(downscale)


# ---------------------------------------------------------------------- layout


@dataclass(frozen=True)
class _Layout:
    kind: str  # "phototourism" | "colmap"
    images_dir: Path
    sparse_dir: Path


def _detect_layout(root: Path) -> _Layout:
    if not root.exists():
        raise MissingInputError(
            f"scene folder {root} does not exist; pass the folder that holds "
            "dense/images + dense/sparse (PhotoTourism) or images + sparse (COLMAP)"
        )
    if not root.is_dir():
        raise InputError(f"scene path {root} is not a folder; pass the scene folder")
    if (root / "dense").is_dir():
        kind, base = "phototourism", root / "dense"
    elif (root / "images").is_dir() or (root / "sparse").is_dir():
        kind, base = "colmap", root
    else:
        raise InputError(
            f"{root} is not a scene folder: looked for {root / 'dense'}/ "
            f"(PhotoTourism: dense/images + dense/sparse) and {root / 'images'}/ + "
            f"{root / 'sparse'}/ (COLMAP), found neither"
        )
    images_dir, sparse_dir = base / "images", base / "sparse"
    for what, d in (("images", images_dir), ("sparse model", sparse_dir)):
        if not d.is_dir():
            raise MissingInputError(
                f"{kind} scene {root} has no {what} folder {d}; "
                "put the COLMAP images and model there"
            )
    return _Layout(kind, images_dir, sparse_dir)


def _find_model(sparse_dir: Path) -> tuple[Path, str]:
    """The folder holding the model and its format ("bin" or "txt")."""
    for d in (sparse_dir, sparse_dir / "0"):
        for ext in ("bin", "txt"):
            if (d / f"cameras.{ext}").is_file():
                missing = [
                    d / f"{n}.{ext}"
                    for n in MODEL_FILES
                    if not (d / f"{n}.{ext}").is_file()
                ]
                if missing:
                    raise MissingInputError(
                        f"incomplete COLMAP model in {d}: missing "
                        f"{', '.join(str(m) for m in missing)}; a model needs "
                        f"cameras, images and points3D (.{ext})"
                    )
                others = sorted(
                    p.name for p in sparse_dir.iterdir() if p.is_dir() and p.name != "0"
                )
                if d != sparse_dir and others:
                    logger.warning(
                        "%s holds several models; using 0 and ignoring %s",
                        sparse_dir,
                        others,
                    )
                return d, ext
    raise MissingInputError(
        f"no COLMAP model in {sparse_dir} or {sparse_dir / '0'}: looked for "
        "cameras/images/points3D .bin or .txt; run COLMAP (and image_undistorter) "
        "and put the model there"
    )


# ------------------------------------------------------------------ model read


@functools.cache
def _camera_num_params() -> dict[int, int]:
    table = {}
    for name, mid in pycolmap.CameraModelId.__members__.items():
        if name == "INVALID":
            continue
        cam = pycolmap.Camera.create_from_model_id(1, mid, 1.0, 2, 2)
        table[int(mid.value)] = len(cam.params)
    return table


def _walk_bin(model_dir: Path) -> None:
    """Check that the model's .bin files are structurally complete.

    pycolmap silently reads some truncated files, and loops for minutes or forever
    on others (a garbage track length or sensor count), so each record is walked
    (lengths only) and the walk must end exactly at the end of the file. Layouts
    as in COLMAP's reconstruction_io_binary.cc.
    """
    num_params = _camera_num_params()
    u64 = struct.Struct("<Q").unpack_from
    u32 = struct.Struct("<I").unpack_from
    i32 = struct.Struct("<i").unpack_from

    def corrupt(path: Path, why: str) -> InputError:
        return InputError(
            f"COLMAP model file {path} is corrupt or truncated ({why}); "
            "re-export the model (COLMAP model_converter) or restore the file"
        )

    for name in MODEL_FILES + MODEL_FILES_V4:
        path = model_dir / f"{name}.bin"
        if name in MODEL_FILES_V4 and not path.is_file():
            continue  # classic 3-file model
        buf = path.read_bytes()
        size = len(buf)
        if size < 8:
            raise corrupt(path, f"{size} bytes, no record count")
        (n,) = u64(buf, 0)
        off = 8
        try:
            for _ in range(n):
                if name == "cameras":  # id, model, width, height, params
                    (model_id,) = i32(buf, off + 4)
                    if model_id not in num_params:
                        raise corrupt(path, f"unknown camera model id {model_id}")
                    off += 24 + 8 * num_params[model_id]
                elif name == "images":  # id, pose, camera, name\0, points2D
                    end = buf.index(b"\0", off + 64)
                    (n2d,) = u64(buf, end + 1)
                    off = end + 9 + 24 * n2d
                elif name == "points3D":  # id, xyz, rgb, error, track
                    (track_len,) = u64(buf, off + 43)
                    off += 51 + 8 * track_len
                elif name == "frames":  # id, rig, pose, data ids
                    (n_data,) = u32(buf, off + 64)
                    off += 68 + 16 * n_data
                else:  # rigs: id, n sensors, ref sensor, other sensors
                    (n_sensors,) = u32(buf, off + 4)
                    off += 8 + 8 * (n_sensors > 0)
                    for _ in range(max(n_sensors - 1, 0)):
                        has_pose = buf[off + 8]
                        off += 9 + 56 * (has_pose != 0)
                        if off > size:
                            break
                if off > size:
                    break
        except InputError:
            raise
        except (struct.error, ValueError, IndexError):
            raise corrupt(path, "a record runs past the end of the file") from None
        if off != size:
            raise corrupt(path, f"{n} record(s) do not fill its {size} bytes")


def _read_model(model_dir: Path, ext: str) -> pycolmap.Reconstruction:
    if ext == "bin":
        _walk_bin(model_dir)
    try:
        rec = pycolmap.Reconstruction()
        # explicit format: a folder may hold both .bin and .txt copies
        if ext == "bin":
            rec.read_binary(str(model_dir))
        else:
            rec.read_text(str(model_dir))
    except Exception as exc:  # pycolmap raises ValueError/IndexError/RuntimeError
        raise InputError(
            f"could not read the COLMAP model in {model_dir}: {exc}; check that "
            "the cameras/images/points3D (and rigs/frames) files come from one "
            "COLMAP export and are complete"
        ) from exc
    return rec


def _model_files(model_dir: Path, ext: str) -> list[Path]:
    names = MODEL_FILES + MODEL_FILES_V4
    return [
        model_dir / f"{n}.{ext}" for n in names if (model_dir / f"{n}.{ext}").is_file()
    ]


def _pinhole_K(
    cam: pycolmap.Camera, cam_id: int, image_name: str, model_dir: Path, distortion: str
) -> tuple[np.ndarray, bool]:
    """The camera's pinhole K [3, 3] and whether distortion was dropped.

    Raises InputError for unsupported models and, with distortion="refuse", for
    non-zero distortion.
    """
    model = cam.model.name
    params = np.asarray(cam.params, dtype=np.float64)
    where = f"camera {cam_id} ({model}, used by image {image_name!r}) in {model_dir}"
    if model not in PINHOLE_MODELS + ZERO_DISTORTION_MODELS:
        raise InputError(
            f"{where}: the {model} camera model is not supported (ptovs needs pinhole "
            f"cameras: {', '.join(PINHOLE_MODELS)}, or a perspective model with zero "
            f"distortion); {_UNDISTORT_FIX}"
        )
    if cam.width <= 0 or cam.height <= 0:
        raise InputError(f"{where} has invalid size {cam.width}x{cam.height}")
    focal = params[list(cam.focal_length_idxs())]
    if not np.all(np.isfinite(params)) or np.any(focal <= 0):
        raise InputError(f"{where} has invalid parameters {params.tolist()}")
    names = [n.strip() for n in cam.params_info.split(",")]
    extra = list(cam.extra_params_idxs())
    dist = {names[i]: float(params[i]) for i in extra if params[i] != 0}
    if dist and distortion == "refuse":
        raise InputError(
            f"{where} has non-zero lens distortion {dist}; {_UNDISTORT_FIX}; "
            "or pass distortion='ignore' (--set scene.distortion=ignore) to drop "
            "it as the authors' code does"
        )
    return np.asarray(cam.calibration_matrix(), dtype=np.float64), bool(dist)


# ----------------------------------------------------------------------- split


def _resolve_split_file(root: Path, layout: str, split_file: Any) -> Path | None:
    """The TSV to read, or None for all-train."""
    if split_file is None:
        split_file = "auto"
    if isinstance(split_file, str) and split_file == "all-train":
        return None
    if isinstance(split_file, str) and split_file == "auto":
        tsvs = sorted(p for p in root.glob("*.tsv") if p.is_file())
        if len(tsvs) > 1:
            raise InputError(
                f"several split files in {root}: {', '.join(p.name for p in tsvs)}; "
                "keep one, or pass split_file=<path> (--set scene.split_file=...)"
            )
        if tsvs:
            return tsvs[0]
        if layout == "phototourism":
            raise InputError(
                f"no split file (*.tsv) in {root}; add a NeRF-W style TSV "
                "(columns filename, id, split, dataset) or pass "
                'split_file="all-train" (--set scene.split_file=all-train)'
            )
        logger.info("no *.tsv in %s: every image is a train view", root)
        return None
    path = Path(split_file).expanduser()
    if not path.is_absolute() and not path.is_file() and (root / path).is_file():
        path = root / path
    if not path.is_file():
        raise MissingInputError(
            f"split file {path} does not exist; pass an existing TSV, 'auto' or "
            "'all-train'"
        )
    return path


def read_split_tsv(path: str | Path) -> dict[str, str]:
    """Read a NeRF-W style split file.

    Args:
        path: tab-separated file with a header holding at least `filename` and
            `split` (other columns are ignored).

    Returns:
        {filename: "train" | "test"}; any split other than "train" is "test".
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(f"split file {path} is not UTF-8 text ({exc})") from exc
    lines = [(i, ln) for i, ln in enumerate(text.splitlines(), 1) if ln.strip()]
    if not lines:
        raise InputError(
            f"split file {path} is empty; it needs a tab-separated header "
            "'filename<TAB>id<TAB>split<TAB>dataset' and one row per image"
        )
    head = lines[0][1].split("\t")
    header = [h.strip().lower() for h in head]
    missing = [c for c in ("filename", "split") if c not in header]
    if missing:
        raise InputError(
            f"split file {path} lacks column(s) {missing} in its header {head}; "
            "it must be tab-separated with at least 'filename' and 'split'"
        )
    i_name, i_split = header.index("filename"), header.index("split")
    out: dict[str, str] = {}
    for lineno, line in lines[1:]:
        row = line.split("\t")
        if len(row) <= max(i_name, i_split):
            raise InputError(
                f"split file {path}, line {lineno}: {len(row)} field(s) {row}, "
                f"expected at least {max(i_name, i_split) + 1} tab-separated fields"
            )
        name, split = row[i_name].strip(), row[i_split].strip()
        if not name:
            raise InputError(f"split file {path}, line {lineno}: empty filename")
        split = "train" if split == "train" else "test"
        if out.get(name, split) != split:
            raise InputError(
                f"split file {path}, line {lineno}: {name!r} is listed as both "
                "train and test; keep one row per image"
            )
        out[name] = split
    return out


def _preview(names: Iterable[str], n: int = 5) -> str:
    names = list(names)
    more = f", ... ({len(names)} in all)" if len(names) > n else ""
    return ", ".join(names[:n]) + more


# ------------------------------------------------------------------ load_scene


def load_scene(
    path: str | Path,
    *,
    downscale: int | str = "auto",
    split_file: str | Path = "auto",
    labels_dir: str | Path | None = None,
    distortion: str = "refuse",
) -> Scene:
    """Load a PhotoTourism or COLMAP scene (no image is decoded).

    Args:
        path: the scene folder.
        downscale: "auto" (1 for synthetic scenes, else 2) or an integer r >= 1.
        split_file: "auto" (the single *.tsv in the scene root), "all-train", or a
            path to a TSV.
        labels_dir: folder of ISAT JSONs; None looks for
            `<path>/../label/<scene name>/`.
        distortion: "refuse" (non-zero lens distortion is an error) or "ignore"
            (drop it with a warning).

    Returns:
        The Scene, views sorted by name.
    """
    root = Path(path).expanduser()
    if distortion not in DISTORTION_MODES:
        raise InputError(
            f"distortion must be one of {DISTORTION_MODES}, got {distortion!r}"
        )
    layout = _detect_layout(root)
    synthetic = (root / "synthetic").is_dir()
    r = (
        (2 if not synthetic else 1)
        if isinstance(downscale, str) and downscale == "auto"
        else _check_downscale(downscale)
    )
    model_dir, ext = _find_model(layout.sparse_dir)
    rec = _read_model(model_dir, ext)

    tsv = _resolve_split_file(root, layout.kind, split_file)
    splits = read_split_tsv(tsv) if tsv is not None else None

    reg_ids = sorted(int(i) for i in rec.reg_image_ids())
    if not reg_ids:
        raise InputError(f"the COLMAP model in {model_dir} has no registered images")
    n_unreg = rec.num_images() - len(reg_ids)
    if n_unreg:
        logger.info("%s: %d unregistered image(s) ignored", model_dir, n_unreg)
    try:
        by_name = {rec.images[i].name: i for i in reg_ids}
    except UnicodeDecodeError as exc:
        raise InputError(
            f"the COLMAP model in {model_dir} has an image name that is not UTF-8 "
            f"({exc}); the images file is corrupt, or rename the image"
        ) from exc
    if len(by_name) != len(reg_ids):
        raise InputError(
            f"the COLMAP model in {model_dir} registers the same image name twice; "
            "the model is corrupt"
        )

    if splits is not None:
        lower = {n.lower(): n for n in by_name}
        chosen: dict[str, str] = {}
        unknown = []
        for name, split in splits.items():
            key = name if name in by_name else lower.get(name.lower())
            if key is None:
                unknown.append(name)
            else:
                chosen[key] = split
        if unknown:
            logger.warning(
                "%s: %d name(s) in the split file are not registered in the model "
                "(skipped): %s",
                tsv,
                len(unknown),
                _preview(unknown),
            )
        unlisted = sorted(set(by_name) - set(chosen))
        if unlisted:
            logger.warning(
                "%s: %d registered image(s) are not in the split file and are left "
                "out: %s",
                tsv,
                len(unlisted),
                _preview(unlisted),
            )
        if not chosen:
            raise InputError(
                f"split file {tsv} lists none of the {len(by_name)} registered images "
                f"of {model_dir} (e.g. {_preview(sorted(by_name), 3)}); fix the "
                "filename column or pass split_file='all-train'"
            )
    else:
        chosen = dict.fromkeys(by_name, "train")

    labels = _resolve_labels_dir(root, labels_dir)

    cam_K: dict[int, np.ndarray] = {}
    dropped: list[str] = []
    views: list[View] = []
    stems: dict[str, str] = {}
    for name in sorted(chosen):
        image = rec.images[by_name[name]]
        cam_id = int(image.camera_id)
        cam = rec.cameras[cam_id]
        if cam_id not in cam_K:
            cam_K[cam_id], lossy = _pinhole_K(cam, cam_id, name, model_dir, distortion)
            if lossy:
                dropped.append(f"{cam_id} ({cam.model.name})")
        image_path = layout.images_dir / name
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
    if dropped:
        logger.warning(
            "%s: ignoring non-zero lens distortion of camera(s) %s "
            "(distortion='ignore'); projections are off by the distortion, most near "
            "the image borders",
            model_dir,
            _preview(dropped),
        )
    labelled_test = [v.name for v in views if v.has_label and v.split != "train"]
    if labelled_test:
        logger.warning(
            "%d labelled view(s) are in the test split (PT-OVS evaluates train "
            "views): %s",
            len(labelled_test),
            _preview(labelled_test),
        )
    if labels is not None:
        orphans = sorted({p.stem for p in labels.glob("*.json")} - set(stems))
        if orphans:
            logger.warning(
                "%s: %d label file(s) match no view of the scene: %s",
                labels,
                len(orphans),
                _preview(orphans),
            )

    ids, xyz, rgb, err, tlen = _points_arrays(rec)
    scene = Scene(
        root=root,
        name=root.resolve().name,
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
        model_files=_model_files(model_dir, ext),
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


def _points_arrays(
    rec: pycolmap.Reconstruction,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    pts = rec.points3D
    n = len(pts)
    ids = np.empty(n, np.int64)
    xyz = np.empty((n, 3), np.float64)
    rgb = np.empty((n, 3), np.uint8)
    err = np.empty(n, np.float64)
    tlen = np.empty(n, np.int64)
    for i, (pid, p) in enumerate(sorted(pts.items())):
        ids[i] = pid
        xyz[i] = p.xyz
        rgb[i] = p.color
        err[i] = p.error
        tlen[i] = p.track.length()
    return ids, xyz, rgb, err, tlen


def _resolve_labels_dir(root: Path, labels_dir: str | Path | None) -> Path | None:
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


# ---------------------------------------------------------------------- images


_warned_truncated: set[str] = set()


def jpeg_truncated(path: Path) -> bool:
    """True for a JPEG whose data does not end with the end-of-image marker.

    libjpeg decodes such a file with a warning on stderr that names no file and
    fills the missing rows with grey; ptovs checks the marker itself to say which.
    """
    path = Path(path)
    if path.suffix.lower() not in (".jpg", ".jpeg"):
        return False
    with open(path, "rb") as fh:
        head = fh.read(2)
        fh.seek(0, 2)
        size = fh.tell()
        fh.seek(max(0, size - 64))
        tail = fh.read().rstrip(b"\x00")
    return head == b"\xff\xd8" and not tail.endswith(b"\xff\xd9")


def load_image(view: View) -> np.ndarray:
    """Decode a view's image at working size.

    Args:
        view: the view (its `image_path`, full and working sizes).

    Returns:
        RGB float32 [H, W, 3] in [0, 1] at (view.height, view.width). Grayscale is
        replicated to 3 channels, alpha dropped, 16-bit scaled by 1/65535.
    """
    path = view.image_path
    if not path.is_file():
        raise MissingInputError(f"image {path} does not exist; restore it")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(
            f"could not decode image {path} (corrupt or unsupported format); "
            "replace it with a readable JPEG or PNG"
        )
    if str(path) not in _warned_truncated and jpeg_truncated(path):
        _warned_truncated.add(str(path))
        logger.warning(
            "image %s is a truncated JPEG (no end-of-image marker): the decoder fills "
            "the missing rows with grey; used as is (replace the file to fix it)",
            path,
        )
    if img.dtype == np.uint8:
        scale = 1.0 / 255.0
    elif img.dtype == np.uint16:
        scale = 1.0 / 65535.0
    elif img.dtype in (np.float32, np.float64):
        scale = 1.0
    else:
        raise InputError(
            f"image {path} has unsupported sample type {img.dtype}; "
            "convert it to 8- or 16-bit JPEG/PNG"
        )
    if img.ndim == 2:
        img = img[:, :, None]
    c = img.shape[2]
    if c == 1:
        img = np.repeat(img, 3, axis=2)
    elif c == 2:  # gray + alpha
        img = np.repeat(img[:, :, :1], 3, axis=2)
    elif c in (3, 4):
        img = img[:, :, 2::-1]  # BGR(A) -> RGB, alpha dropped
    else:
        raise InputError(f"image {path} has {c} channels; expected 1, 2, 3 or 4")
    h, w = img.shape[:2]
    if (w, h) != (view.full_width, view.full_height):
        raise InputError(
            f"image {path} is {w}x{h} but its COLMAP camera is "
            f"{view.full_width}x{view.full_height}; the images must be the ones the "
            "model was built from (e.g. the undistorted images/ that "
            "image_undistorter wrote next to the model)"
        )
    out = img.astype(np.float32) * np.float32(scale)
    if scale == 1.0:
        out = np.clip(out, 0.0, 1.0)
    if (view.width, view.height) != (w, h):
        out = cv2.resize(out, (view.width, view.height), interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(out)  # [H, W, 3]


# ------------------------------------------------------------------ pixel maps


def resize_map(
    arr: np.ndarray,  # [H, W] or [H, W, C]
    size: tuple[int, int],
    *,
    kind: str = "nearest",
) -> np.ndarray:
    """Resize a per-pixel map.

    Args:
        arr: [H, W] or [H, W, C], any C.
        size: target (H, W), numpy order.
        kind: "nearest" (any dtype; pixel-centre sampling src = floor((x + 0.5) *
            H/H'), exact for label and id maps), "area" (cv2.INTER_AREA) or
            "linear" (cv2.INTER_LINEAR); the last two need a float or bool map and
            return float32 (float64 stays float64).

    Returns:
        [H', W'] or [H', W', C], same dtype for "nearest".
    """
    if kind not in RESIZE_KINDS:
        raise ValueError(f"kind must be one of {RESIZE_KINDS}, got {kind!r}")
    arr = np.asarray(arr)
    if arr.ndim not in (2, 3):
        raise ValueError(f"resize_map needs [H, W] or [H, W, C], got {arr.shape}")
    th, tw = int(size[0]), int(size[1])
    if th < 1 or tw < 1:
        raise ValueError(f"target size must be positive (H, W), got {size}")
    h, w = arr.shape[:2]
    if (h, w) == (th, tw):
        return arr.copy()
    if kind == "nearest":
        rows = np.minimum(((np.arange(th) + 0.5) * (h / th)).astype(np.int64), h - 1)
        cols = np.minimum(((np.arange(tw) + 0.5) * (w / tw)).astype(np.int64), w - 1)
        return arr[rows[:, None], cols[None, :]]
    if arr.dtype != np.bool_ and not np.issubdtype(arr.dtype, np.floating):
        raise ValueError(
            f"kind={kind!r} interpolates values; use a float map, not {arr.dtype} "
            "(use kind='nearest' for labels and ids)"
        )
    if arr.dtype not in (np.float32, np.float64):  # bool, float16: cv2 wants f32
        arr = arr.astype(np.float32)
    interp = cv2.INTER_AREA if kind == "area" else cv2.INTER_LINEAR
    if arr.ndim == 2:
        return cv2.resize(arr, (tw, th), interpolation=interp)
    # cv2 handles at most 4 channels for INTER_AREA: resize in groups of 4
    parts = [
        cv2.resize(arr[:, :, i : i + 4], (tw, th), interpolation=interp).reshape(
            th, tw, -1
        )
        for i in range(0, arr.shape[2], 4)
    ]
    return np.concatenate(parts, axis=2)


def check_size(arr: np.ndarray, view: View, what: str) -> None:
    """Raise InputError unless a per-pixel map is at the view's working size.

    Args:
        arr: [H, W, ...] map.
        view: the view it belongs to.
        what: what the map is, for the message (e.g. "u_t of extract-features").
    """
    shape = tuple(np.shape(arr))
    if len(shape) < 2 or shape[:2] != (view.height, view.width):
        raise InputError(
            f"{what} for view {view.name} has shape {shape}, but the working size "
            f"is (H, W) = ({view.height}, {view.width}); it was made at another "
            "downscale factor: rerun the stage that wrote it with the scene's "
            "downscale"
        )


# ---------------------------------------------------------------------- labels


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
        out.append((cat, verts))
    return {"name": name, "width": wh[0], "height": wh[1], "objects": out}


def load_labels(
    source: Scene | str | Path,
    view: View | str,
    size: tuple[int, int] | None = None,
    *,
    gt_resize: str = "nearest",
) -> dict[str, np.ndarray]:
    """Ground-truth masks of one labelled view (PAPER_SPEC §1.2, §9).

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
    label = read_label_json(path)
    if Path(label["name"]).stem != Path(stem).name:
        raise InputError(
            f"label file {path} has info.name {label['name']!r}, which is not the "
            f"image {stem!r}; rename the file or fix info.name"
        )
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
