"""Working resolution, image decoding and per-pixel maps at a view's size."""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ptovs.errors import InputError, MissingInputError

logger = logging.getLogger(__name__)


RESIZE_KINDS = ("nearest", "area", "linear")


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
    r = check_downscale(downscale)
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


def check_downscale(downscale: Any) -> int:
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


_warned_alpha: set[str] = set()


def report_alpha(path: Path | str, alpha: np.ndarray) -> None:
    """Say (once a file) that a photo's transparency is not used: ptovs reads the
    colour stored under transparent pixels as if it were seen. An opaque alpha
    channel is silent."""
    if str(path) in _warned_alpha:
        return
    full = np.iinfo(alpha.dtype).max if alpha.dtype.kind in "ui" else 1.0
    clear = alpha < full
    if clear.any():
        _warned_alpha.add(str(path))
        logger.warning(
            "image %s has transparent pixels (%.0f %% of it); ptovs reads RGB only, "
            "so the colour stored under them is used as if seen. Flatten the photo "
            "onto its background, or leave it out if the transparent part is not "
            "the scene",
            path,
            100 * float(clear.mean()),
        )


def load_image(view: Any) -> np.ndarray:  # view: a ptovs.scene.View
    """Decode a view's image at working size.

    Args:
        view: the view (its `image_path`, full and working sizes).

    Returns:
        RGB float32 [H, W, 3] in [0, 1] at (view.height, view.width), resized by
        `resize_photo`. Grayscale is replicated to 3 channels, alpha dropped
        (reported once a file when it is not opaque: `report_alpha`), 16-bit scaled
        by 1/65535; float samples clipped, NaN and -inf read as 0, +inf as 1.
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
        report_alpha(path, img[:, :, 1])
        img = np.repeat(img[:, :, :1], 3, axis=2)
    elif c in (3, 4):
        if c == 4:
            report_alpha(path, img[:, :, 3])
        img = img[:, :, 2::-1]  # BGR(A) -> RGB, alpha dropped (reported)
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
    if scale == 1.0:  # a float TIFF or EXR may hold NaN, inf or values past 1
        out = np.clip(np.nan_to_num(out, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    if (view.width, view.height) != (w, h):
        out = resize_photo(out, (view.width, view.height))
    return np.ascontiguousarray(out)  # [H, W, 3]


def resize_photo(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resize a photo by area averaging, its samples kept in [0, 1].

    cv2's INTER_AREA at a factor that is not an integer weighs each source pixel by
    float32 fractions whose sum is not exactly 1, so a saturated region comes back
    at 1 + 1.2e-7 (a white 3072x2048 photo at 614x410: 189,420 of its samples); the
    clip restores the range every consumer of a photo relies on (PhotoStack refuses
    anything else).

    Args:
        img: [H, W, C] float photo in [0, 1].
        size: target (width, height), cv2 order.

    Returns:
        [height, width, C] float32 in [0, 1].
    """
    src = np.asarray(img, np.float32)
    out = cv2.resize(src, (int(size[0]), int(size[1])), interpolation=cv2.INTER_AREA)
    out = out.reshape(out.shape[0], out.shape[1], *src.shape[2:])  # cv2 drops C = 1
    return np.clip(out, 0.0, 1.0, out=out)


class PhotoStack(Sequence[np.ndarray]):
    """Decoded photos held as 16-bit samples, given back as float32 on access.

    A collection's photos at working size are reconstruct's one store that grows with
    the photo count (763 photos of PT-OVS's size are 3.0 GB as float32). Each sample
    in [0, 1] is kept as round(x · 65535) (half of float32's bytes) and read back as
    that / 65535: at most 0.5 / 65535 (7.6e-6) from the decoded value, which is 1/128
    of an 8-bit photo's own step.

    Args:
        images: RGB float32 [H, W, 3] in [0, 1] (`load_image`'s output).
    """

    SCALE = 65535.0

    def __init__(self, images: Iterable[np.ndarray]) -> None:
        self._q: list[np.ndarray] = []
        for img in images:
            if img.ndim != 3 or img.shape[2] != 3:
                raise ValueError(f"a photo is [H, W, 3]; got shape {img.shape}")
            if not np.isfinite(img).all() or img.min() < 0.0 or img.max() > 1.0:
                raise ValueError("a photo's samples must be finite and in [0, 1]")
            q = np.rint(img.astype(np.float32) * np.float32(self.SCALE))
            self._q.append(q.astype(np.uint16))

    def __len__(self) -> int:
        return len(self._q)

    def __getitem__(self, i):  # type: ignore[override]
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
        return self._q[i].astype(np.float32) / np.float32(self.SCALE)

    @property
    def shapes(self) -> list[tuple[int, int, int]]:
        """[H, W, 3] of every photo, without decoding."""
        return [tuple(q.shape) for q in self._q]

    @property
    def nbytes(self) -> int:
        return sum(q.nbytes for q in self._q)


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


def check_size(arr: np.ndarray, view: Any, what: str) -> None:  # a View
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
