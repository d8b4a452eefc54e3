"""Image/text encoders that play CLIP's role, and the LangSplat crop recipe.

Stages use only this module: `get_encoder(name, **kwargs)` returns an `Encoder`,
and `prepare_crop` turns an image and a segment mask into the crop it encodes.

    enc = get_encoder("synthetic", vocabulary=scene / "synthetic/vocabulary.json")
    crops = np.stack([prepare_crop(image, m) for m in masks])  # [B, 224, 224, 3]
    feats = enc.encode_images(crops)  # [B, 512] unit rows
    q = enc.encode_texts(["Column", "object"])  # [Q, 512] unit rows

extract-features builds its encoder through the encoder's backend
(`ptovs.encoders.backend`); the stand-in's, `Standin`, is below.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from ptovs.crop import prepare_crop  # the encoders' input, defined below them
from ptovs.encoders.backend import EncoderBackend
from ptovs.errors import MissingInputError

logger = logging.getLogger(__name__)

ENCODERS = ("synthetic", "openclip")
STANDIN_VERSIONS = (1, 5)
RETIRED_STANDINS = (2, 3, 4)  # scenes written for them must be regenerated


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


def standin_version(vocabulary: dict | None, source: object = None) -> int:
    """Which stand-in a synthetic scene's vocabulary was written for (1 or 5).

    `source` names where the vocabulary came from (its file), for the error a
    retired or unknown version raises."""
    v = (vocabulary or {}).get("version", 1)
    if v in STANDIN_VERSIONS:
        return int(v)
    where = f"{source}: " if source is not None else ""
    if v in RETIRED_STANDINS:
        raise ValueError(
            f"{where}stand-in version {v} is no longer supported (only 1 and 5 "
            "are); regenerate the scene with `ptovs synth-scene --standin 1` or "
            "`--standin 5`"
        )
    raise ValueError(
        f"{where}unknown stand-in version {v!r} (1 or 5); regenerate the scene "
        "with `ptovs synth-scene --standin 1` or `--standin 5`"
    )


def synthetic_encoder(vocabulary=None) -> Encoder:
    """The stand-in for CLIP of a synthetic scene, by its vocabulary's version.

    Args:
        vocabulary: path to vocabulary.json, its dict, or None (version 1, generic
            phrases only). Version 1 is `encoders.synthetic`, version 5
            `encoders.synthetic_v5`.
    """
    vocab, source = vocabulary, None
    if vocabulary is not None and not isinstance(vocabulary, dict):
        source = Path(vocabulary)
        if not source.is_file():
            raise FileNotFoundError(f"vocabulary {source} not found")
        vocab = json.loads(source.read_text())
    if standin_version(vocab, source) == 5:
        from ptovs.encoders.synthetic_v5 import SyntheticEncoderV5

        return SyntheticEncoderV5(vocab)
    from ptovs.encoders.synthetic import SyntheticEncoder

    return SyntheticEncoder(vocab)


def scene_encoder(scene_dir: str | Path) -> Encoder:
    """The stand-in encoder of a synthetic scene (reads synthetic/vocabulary.json):
    version 1 or 5, as the vocabulary says."""
    path = Path(scene_dir) / "synthetic" / "vocabulary.json"
    if not path.is_file():
        raise FileNotFoundError(
            f"{path} not found; the synthetic encoder needs a scene made by "
            "`ptovs synth-scene`"
        )
    return synthetic_encoder(path)


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


def vocabulary_file(scene_root: str | Path | None) -> Path | None:
    """A scene's synthetic/vocabulary.json, None where it has none."""
    if scene_root is None:
        return None
    path = Path(scene_root) / "synthetic" / "vocabulary.json"
    return path if path.is_file() else None


class Standin(EncoderBackend):
    """The stand-in for CLIP of a synthetic scene (docs/standin.md)."""

    name = "synthetic"

    def build(self, config, scene_root: Path | None) -> Encoder:
        # the image side needs no phrases, only the scene's stand-in version
        return get_encoder("synthetic", vocabulary=vocabulary_file(scene_root))

    def check_scene(self, config, scene) -> None:
        """Only a synthetic scene has the vocabulary the stand-in reads."""
        if not (Path(scene.root) / "synthetic" / "vocabulary.json").is_file():
            raise MissingInputError(
                f"encoder 'synthetic' (the stand-in) needs {scene.root}/synthetic/"
                "vocabulary.json, which only synthetic scenes have; set "
                'extract-features.encoder = "openclip" and clip_checkpoint for real '
                "photos"
            )


__all__ = [
    "ENCODERS",
    "Encoder",
    "Standin",
    "get_encoder",
    "prepare_crop",
    "scene_encoder",
    "standin_version",
    "synthetic_encoder",
    "vocabulary_file",
]
