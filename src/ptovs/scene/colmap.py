"""COLMAP models: the two folder layouts, reading a model with pycolmap (binary files
walked first), pinhole intrinsics and the sparse points.
"""

from __future__ import annotations

import functools
import logging
import struct
from dataclasses import dataclass
from pathlib import Path

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
MODEL_FILES = ("cameras", "images", "points3D")
MODEL_FILES_V4 = ("rigs", "frames")

_UNDISTORT_FIX = (
    "undistort the images first, e.g. `colmap image_undistorter --image_path IMAGES "
    "--input_path SPARSE --output_path OUT` or `pycolmap.undistort_images(OUT, "
    "SPARSE, IMAGES)`, and point ptovs at OUT (its images/ and sparse/)"
)


@dataclass(frozen=True)
class Layout:
    kind: str  # "phototourism" | "colmap"
    images_dir: Path
    sparse_dir: Path


def detect_layout(root: Path) -> Layout:
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
    return Layout(kind, images_dir, sparse_dir)


def count_registered(model: Path, ext: str) -> int:
    """How many images a COLMAP model registers (its images file's count)."""
    path = model / f"images.{ext}"
    try:
        if ext == "bin":
            with path.open("rb") as fh:
                head = fh.read(8)
            return int.from_bytes(head, "little") if len(head) == 8 else 0
        lines = [ln for ln in path.read_text().splitlines() if not ln.startswith("#")]
        return len(lines) // 2
    except OSError:
        return 0


def _best_model(sparse_dir: Path) -> Path | None:
    """Of several models sparse/0, sparse/1, ..., the one that registers the most
    images (COLMAP's mapper numbers them by when they were made, not by size)."""
    models = []
    for d in sorted(p for p in sparse_dir.iterdir() if p.is_dir()):
        for ext in ("bin", "txt"):
            if (d / f"cameras.{ext}").is_file():
                models.append((count_registered(d, ext), d))
                break
    if len(models) < 2:
        return None
    n, best = max(models, key=lambda m: (m[0], -models.index(m)))
    logger.warning(
        "%s holds %d models (%s); using %s, which registers the most images",
        sparse_dir,
        len(models),
        ", ".join(f"{d.name}: {k} images" for k, d in models),
        best.name,
    )
    return best


def find_model(sparse_dir: Path) -> tuple[Path, str]:
    """The folder holding the model and its format ("bin" or "txt"): sparse/
    itself, else the numbered model that registers the most images."""
    direct = any((sparse_dir / f"cameras.{e}").is_file() for e in ("bin", "txt"))
    best = None if direct or not sparse_dir.is_dir() else _best_model(sparse_dir)
    for d in (sparse_dir, best or sparse_dir / "0"):
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
                return d, ext
    raise MissingInputError(
        f"no COLMAP model in {sparse_dir} or {sparse_dir / '0'}: looked for "
        "cameras/images/points3D .bin or .txt; run COLMAP (and image_undistorter) "
        "and put the model there"
    )


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


def read_model(model_dir: Path, ext: str) -> pycolmap.Reconstruction:
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


def model_files(model_dir: Path, ext: str) -> list[Path]:
    names = MODEL_FILES + MODEL_FILES_V4
    return [
        model_dir / f"{n}.{ext}" for n in names if (model_dir / f"{n}.{ext}").is_file()
    ]


def pinhole_K(
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


def points_arrays(
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


def registered_images(rec: pycolmap.Reconstruction, model_dir: Path) -> dict[str, int]:
    """{image name: image id} of the model's registered images (refusing none,
    names that are not UTF-8 and a name registered twice)."""
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
    return by_name
