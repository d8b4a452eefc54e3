"""Image/text encoders that play CLIP's role, and the LangSplat crop recipe.

Stages use only this module: `get_encoder(name, **kwargs)` returns an `Encoder`,
and `prepare_crop` turns an image and a segment mask into the crop it encodes.

    enc = get_encoder("synthetic", vocabulary=scene / "synthetic/vocabulary.json")
    crops = np.stack([prepare_crop(image, m) for m in masks])  # [B, 224, 224, 3]
    feats = enc.encode_images(crops)  # [B, 512] unit rows
    q = enc.encode_texts(["Column", "object"])  # [Q, 512] unit rows
"""

from __future__ import annotations

import logging
from typing import Protocol, runtime_checkable

import cv2
import numpy as np

logger = logging.getLogger(__name__)

ENCODERS = ("synthetic", "openclip")


@runtime_checkable
class Encoder(Protocol):
    """What extract-features and query need from CLIP."""

    name: str
    dim: int  # 512

    def encode_images(self, crops: np.ndarray) -> np.ndarray:
        """Embed crops [B, S, S, 3] float32 RGB in [0, 1]; returns [B, dim] float32 unit rows."""
        ...

    def encode_texts(self, texts: list[str]) -> np.ndarray:
        """Embed raw phrases (no prompt template); returns [Q, dim] float32 unit rows."""
        ...


def prepare_crop(image: np.ndarray, mask: np.ndarray, size: int = 224) -> np.ndarray:
    """The LangSplat crop of one segment (PAPER_SPEC 4).

    Pixels outside the mask are zeroed, the mask's bounding box is cut out, padded
    to a centred black square and resized to size x size with cv2.resize
    (bilinear). Departure: the bounding box is inclusive of its last row and
    column (LangSplat's SAM xywh box drops them).

    Args:
        image: [H, W, 3] uint8 RGB, or float in [0, 1].
        mask: [H, W] bool (anything non-zero is inside).
        size: output side.

    Returns:
        [size, size, 3] float32 RGB in [0, 1].
    """
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image must be [H, W, 3], got {image.shape}")
    if mask.shape != image.shape[:2]:
        raise ValueError(f"mask {mask.shape} does not match image {image.shape[:2]}")
    if size < 1:
        raise ValueError(f"size must be >= 1, got {size}")
    m = mask.astype(bool)
    rows = np.flatnonzero(m.any(axis=1))
    cols = np.flatnonzero(m.any(axis=0))
    if len(rows) == 0:
        raise ValueError("empty mask: nothing to crop")
    y0, y1, x0, x1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
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
    out = cv2.resize(pad, (size, size), interpolation=cv2.INTER_LINEAR)
    if out.dtype == np.uint8:
        return out.astype(np.float32) / np.float32(255.0)
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def get_encoder(name: str, **kwargs) -> Encoder:
    """Build an encoder by name.

    Args:
        name: "synthetic" (the stand-in of SYNTHETIC.md; kwargs: vocabulary=path
            or dict) or "openclip" (OpenCLIP from a local checkpoint, extra
            `[clip]`; kwargs: model=, checkpoint=, device=, batch_size=; "clip"
            is accepted as an alias).
        **kwargs: passed to the encoder.

    Returns:
        The encoder.
    """
    if name == "synthetic":
        from ptovs.encoders.synthetic import SyntheticEncoder

        return SyntheticEncoder(**kwargs)
    if name in ("openclip", "clip"):
        from ptovs.encoders.openclip import OpenClipEncoder

        return OpenClipEncoder(**kwargs)
    raise ValueError(f"unknown encoder {name!r}; choose from {list(ENCODERS)}")


__all__ = ["ENCODERS", "Encoder", "get_encoder", "prepare_crop"]
