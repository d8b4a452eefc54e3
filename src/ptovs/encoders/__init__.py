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

import numpy as np

from ptovs.crop import prepare_crop  # the encoders' input, defined below them

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
