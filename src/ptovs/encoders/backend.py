"""Encoder backends: what extract-features builds from its config, and what
preflight checks before a chain starts, behind one interface.

A backend is one subclass of `EncoderBackend` in one module, named by one line of
ENCODER_BACKENDS ("module:class", imported only when asked for):

    backend = get_encoder_backend("openclip")
    backend.check(config)                  # preflight: one line naming file and fix
    encoder = backend.build(config, scene_root)
    spec = backend.spec(config)            # what query needs to embed texts

Each backend says which extract-features fields it reads (`config_keys`) and
which pip extra installs its package (`extra`). The config's `encoder` choices
are "auto" and the registry's names, in its order.
"""

from __future__ import annotations

import importlib
from pathlib import Path
from typing import Any

from ptovs.errors import InputError

ENCODER_BACKENDS: dict[str, str] = {
    "synthetic": "ptovs.encoders:Standin",
    "openclip": "ptovs.encoders.openclip_backend:OpenClipBackend",
}
"""Each encoder: "module:class". A new encoder is one module and one line here."""

ENCODER_CHOICES = ("auto", *ENCODER_BACKENDS)

AUTO_ENCODER = {True: "synthetic", False: "openclip"}
"""encoder "auto": the stand-in on a synthetic scene (True), else OpenCLIP."""


class EncoderBackend:
    """One encoder as extract-features and preflight see it (defaults: no
    config, no checks, the encoder's name as its spec)."""

    name = ""
    extra = ""
    """The pip extra that installs its package ("": none needed)."""
    config_keys: tuple[str, ...] = ()
    """The extract-features config fields it reads."""

    def build(self, config: Any, scene_root: Path | None) -> Any:
        """The `Encoder` of `config` (`scene_root`: the scene's folder, where known)."""
        raise NotImplementedError

    def spec(self, config: Any) -> dict:
        """What query needs to embed texts in the features' space (kept in
        levels_json as `encoder_spec`)."""
        return {"name": self.name}

    def check(self, config: Any) -> None:
        """Preflight, before any scene is read: raise an InputError (or
        MissingInputError) of one line naming the file and the fix."""

    def check_scene(self, config: Any, scene: Any) -> None:
        """Preflight once the scene is read (what only the scene decides)."""


def get_encoder_backend(name: str) -> EncoderBackend:
    """The backend named `name` (one of ENCODER_BACKENDS)."""
    if name not in ENCODER_BACKENDS:
        raise InputError(
            f"extract-features.encoder = {name!r}: choose from {list(ENCODER_CHOICES)}"
        )
    module, cls = ENCODER_BACKENDS[name].split(":")
    return getattr(importlib.import_module(module), cls)()


def encoder_name(choice: str, synthetic: bool) -> str:
    """extract-features' encoder: "auto" is the stand-in on synthetic scenes."""
    return AUTO_ENCODER[bool(synthetic)] if choice == "auto" else choice


def build_encoder(config: Any, synthetic: bool, scene_root: Path | None = None) -> Any:
    """The encoder extract-features' `config` names, built by its backend."""
    name = encoder_name(config.encoder, synthetic)
    return get_encoder_backend(name).build(config, scene_root)


def encoder_spec(config: Any, encoder: Any) -> dict:
    """What query needs to embed texts in the features' space: the encoder's
    name, and what its backend adds (OpenCLIP: the model and checkpoint)."""
    if encoder.name not in ENCODER_BACKENDS:  # e.g. the stand-in's version 5
        return {"name": encoder.name}
    return get_encoder_backend(encoder.name).spec(config)


__all__ = [
    "AUTO_ENCODER",
    "ENCODER_BACKENDS",
    "ENCODER_CHOICES",
    "EncoderBackend",
    "build_encoder",
    "encoder_name",
    "encoder_spec",
    "get_encoder_backend",
]
