"""The LangSplat crop of one segment: what an encoder embeds (docs/method.md §4).

Below the encoders and the synthetic world alike: extract-features crops segments
with it, the synthetic world's screen crops truth masks with it, and
`ptovs.encoders` re-exports it beside the encoders that embed its output.
"""

from __future__ import annotations

import cv2
import numpy as np


def prepare_crop(
    image: np.ndarray, mask: np.ndarray, size: int = 224, resample: str | None = None
) -> np.ndarray:
    """The LangSplat crop of one segment (docs/method.md §4).

    Pixels outside the mask are zeroed, the mask's bounding box is cut out, padded
    to a centred black square and resized to size x size: with cv2.resize
    (bilinear, no antialiasing) by default, or, with `resample`, as open_clip's
    eval transform resizes that square (a PIL resize of the uint8 image with the
    pretrained tag's interpolation, antialiased; every resize mode is that one
    call on a square). Departure: the bounding box is inclusive of its last row
    and column (LangSplat's SAM xywh box drops them).

    Args:
        image: [H, W, 3] uint8 RGB, or float in [0, 1] (rounded to uint8 first
            when `resample` is given, as a PIL image holds it).
        mask: [H, W] bool (anything non-zero is inside).
        size: output side.
        resample: None (cv2), "bilinear" or "bicubic" (PIL, as open_clip); an
            OpenCLIP encoder's `resample` attribute names its tag's.

    Returns:
        [size, size, 3] float32 RGB in [0, 1].
    """
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image must be [H, W, 3], got {image.shape}")
    if mask.shape != image.shape[:2]:
        raise ValueError(f"mask {mask.shape} does not match image {image.shape[:2]}")
    if size < 1:
        raise ValueError(f"size must be >= 1, got {size}")
    if resample not in (None, "bilinear", "bicubic"):
        raise ValueError(
            f"resample must be None, bilinear or bicubic, got {resample!r}"
        )
    m = mask.astype(bool)
    rows = np.flatnonzero(m.any(axis=1))
    cols = np.flatnonzero(m.any(axis=0))
    if len(rows) == 0:
        raise ValueError("empty mask: nothing to crop")
    y0, y1, x0, x1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    if resample is not None and image.dtype != np.uint8:
        image = np.clip(np.rint(image[y0:y1, x0:x1] * 255.0), 0, 255).astype(np.uint8)
        m, y0, y1, x0, x1 = m[y0:y1, x0:x1], 0, y1 - y0, 0, x1 - x0
    if image.dtype == np.uint8:
        img = image[y0:y1, x0:x1].copy()
    else:
        img = image[y0:y1, x0:x1].astype(np.float32)
    img[~m[y0:y1, x0:x1]] = 0
    h, w = img.shape[:2]
    side = max(h, w)
    pad = np.zeros((side, side, 3), img.dtype)
    top, left = (side - h) // 2, (side - w) // 2
    pad[top : top + h, left : left + w] = img
    if resample is not None:
        from PIL import Image

        how = (
            Image.Resampling.BICUBIC
            if resample == "bicubic"
            else Image.Resampling.BILINEAR
        )
        out = np.asarray(Image.fromarray(pad).resize((size, size), how))
    else:
        out = cv2.resize(pad, (size, size), interpolation=cv2.INTER_LINEAR)
    if out.dtype == np.uint8:
        return out.astype(np.float32) / np.float32(255.0)
    return np.clip(out, 0.0, 1.0).astype(np.float32)


__all__ = ["prepare_crop"]
