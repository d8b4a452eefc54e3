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
STANDIN_VERSIONS = (1, 2, 3, 4, 5)


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


def standin_version(vocabulary: dict | None) -> int:
    """Which stand-in a synthetic scene's vocabulary was written for (1 to 5)."""
    v = (vocabulary or {}).get("version", 1)
    if v not in STANDIN_VERSIONS:
        raise ValueError(
            f"unknown stand-in version {v!r} in the vocabulary (1, 2, 3, 4 or 5)"
        )
    return int(v)


def synthetic_encoder(vocabulary=None) -> Encoder:
    """The stand-in for CLIP of a synthetic scene, by its vocabulary's version.

    Args:
        vocabulary: path to vocabulary.json, its dict, or None (version 1, generic
            phrases only). Version 1 is `encoders.synthetic`; versions 2 and 3
            (issue 41) `encoders.synthetic_v2`; version 4 `encoders.synthetic_v4`;
            version 5 `encoders.synthetic_v5`.
    """
    import json
    from pathlib import Path

    from ptovs.encoders.synthetic import SyntheticEncoder

    vocab = vocabulary
    if vocabulary is not None and not isinstance(vocabulary, dict):
        path = Path(vocabulary)
        if not path.is_file():
            raise FileNotFoundError(f"vocabulary {path} not found")
        vocab = json.loads(path.read_text())
    version = standin_version(vocab)
    if version == 5:
        from ptovs.encoders import synthetic_v5

        return synthetic_v5.SyntheticEncoderV5(vocab)
    if version == 4:
        from ptovs.encoders import synthetic_v4

        return synthetic_v4.SyntheticEncoderV4(vocab)
    if version in (2, 3):
        from ptovs.encoders import synthetic_v2

        if version == 3:
            return synthetic_v2.SyntheticEncoderV3(vocab)
        return synthetic_v2.SyntheticEncoderV2(vocab)
    return SyntheticEncoder(vocab)


def get_encoder(name: str, **kwargs) -> Encoder:
    """Build an encoder by name.

    Args:
        name: "synthetic" (the stand-in of docs/standin.md; kwargs: vocabulary=path
            or dict) or "openclip" (OpenCLIP from a local checkpoint, extra
            `[clip]`; kwargs: model=, checkpoint=, device=, batch_size=; "clip"
            is accepted as an alias).
        **kwargs: passed to the encoder.

    Returns:
        The encoder.
    """
    if name == "synthetic":
        return synthetic_encoder(kwargs.get("vocabulary"))
    if name in ("openclip", "clip"):
        from ptovs.encoders.openclip import OpenClipEncoder

        return OpenClipEncoder(**kwargs)
    raise ValueError(f"unknown encoder {name!r}; choose from {list(ENCODERS)}")


__all__ = [
    "ENCODERS",
    "Encoder",
    "get_encoder",
    "prepare_crop",
    "standin_version",
    "synthetic_encoder",
]
