"""A backend is one class plus one registry line: a toy encoder and a toy
segmenter, defined here and registered by one line each, are checked by
preflight (a failing check stops it with the toy's own one-line message, a
passing one lets it through) and built by extract-features' builders."""

from __future__ import annotations

import dataclasses
import typing
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ptovs.encoders.backend import ENCODER_BACKENDS, EncoderBackend, encoder_spec
from ptovs.errors import InputError, MissingInputError
from ptovs.segment import Level
from ptovs.segment.backend import SEGMENTER_BACKENDS, SegmenterBackend
from ptovs.stages import extract_features as ef


class ToyEncoder:
    """Every crop's mean colour, padded to `dim` and made a unit row."""

    name = "toy"
    dim = 4

    def encode_images(self, crops: np.ndarray) -> np.ndarray:
        x = np.asarray(crops, np.float32).mean(axis=(1, 2))
        x = np.concatenate([x, np.ones((len(x), 1), np.float32)], 1)
        return x / np.linalg.norm(x, axis=1, keepdims=True)

    def encode_texts(self, texts: list[str]) -> np.ndarray:
        return np.tile(np.eye(self.dim, dtype=np.float32)[:1], (len(texts), 1))


class ToyEncoderBackend(EncoderBackend):
    """The whole backend: its config, its build, its preflight check."""

    name = "toy"
    extra = "toy"
    config_keys = ("clip_checkpoint",)  # reuses a field: a file it must find

    def build(self, config: Any, scene_root: Path | None) -> ToyEncoder:
        return ToyEncoder()

    def check(self, config: Any) -> None:
        if not Path(config.clip_checkpoint).is_file():
            raise MissingInputError(
                f"encoder 'toy' needs clip_checkpoint {config.clip_checkpoint}; "
                "--set extract-features.clip_checkpoint=FILE"
            )


class ToySegmenter:
    """Halves at every level: left and right."""

    name = "halves"

    def __init__(self, levels: tuple[str, ...]):
        self.levels = levels

    def segment(self, image: np.ndarray) -> list[Level]:
        h, w = image.shape[:2]
        labels = np.zeros((h, w), np.int32)
        labels[:, w // 2 :] = 1
        return [Level(labels.copy()) for _ in self.levels]


class ToySegmenterBackend(SegmenterBackend):
    name = "halves"
    config_keys = ("graph_min_size",)

    def build(self, config: Any, levels: tuple, scene_root: Path | None):
        return ToySegmenter(levels)

    def check(self, config: Any) -> None:
        if config.graph_min_size < 1:
            raise InputError(
                f"segmenter 'halves': graph_min_size {config.graph_min_size} < 1; "
                "--set extract-features.graph_min_size=100"
            )

    def extra_key(self, config: Any) -> dict[str, str]:
        return {"halves": "1"}

    def empty_causes(self, config: Any) -> list[str]:
        return ["the toy never finds nothing"]


@pytest.fixture
def toys(monkeypatch):
    """Register both toys: one line each, as a new backend module would."""
    monkeypatch.setitem(ENCODER_BACKENDS, "toy", f"{__name__}:ToyEncoderBackend")
    monkeypatch.setitem(SEGMENTER_BACKENDS, "halves", f"{__name__}:ToySegmenterBackend")


def _config(**kw) -> ef.Config:
    return dataclasses.replace(ef.Config(), encoder="toy", segmenter="halves", **kw)


def test_preflight_runs_the_toys_checks(toys, tmp_path):
    from ptovs.preflight import check_extract_config

    with pytest.raises(MissingInputError) as e:
        check_extract_config(_config(clip_checkpoint=str(tmp_path / "toy.pt")))
    msg = str(e.value)
    assert msg.startswith("encoder 'toy' needs clip_checkpoint ")
    assert str(tmp_path / "toy.pt") in msg and "clip_checkpoint=FILE" in msg
    (tmp_path / "toy.pt").write_bytes(b"weights")
    check_extract_config(_config(clip_checkpoint=str(tmp_path / "toy.pt")))  # passes
    with pytest.raises(InputError, match=r"graph_min_size 0 < 1; --set extract"):
        check_extract_config(
            _config(clip_checkpoint=str(tmp_path / "toy.pt"), graph_min_size=0)
        )
    # an imported feature folder needs neither backend: nothing is checked
    check_extract_config(_config(import_dir=str(tmp_path), graph_min_size=0))


def test_the_builders_build_the_toys(toys):
    config = _config()
    enc = ef.build_encoder(config, synthetic=False)
    seg = ef.build_segmenter(config)
    assert isinstance(enc, ToyEncoder) and isinstance(seg, ToySegmenter)
    assert seg.levels == ("s", "m", "l")  # the config's levels, checked
    image = np.zeros((8, 8, 3), np.uint8)
    image[:, 4:] = 255  # the right half white
    f = ef.image_features(image, seg, enc, crop_size=16)
    f.validate()
    assert f.counts.tolist() == [2, 2, 2]  # two halves at each of the 3 levels
    rows = np.asarray(f.table, np.float32).reshape(3, 2, enc.dim)
    np.testing.assert_allclose(np.linalg.norm(rows, axis=-1), 1, atol=1e-2)
    assert (rows == rows[0]).all()  # a mask that recurs is encoded once
    left, right = rows[0]
    assert right[0] > left[0]  # the white half's crop is the brighter
    assert encoder_spec(config, enc) == {"name": "toy"}  # the default spec
    # the stage asks the segmenter's backend for its key and its causes
    key = ef.extra_key(_config(import_dir=""), _NoScene())
    assert key == {"halves": "1"}
    assert ef.empty_causes(config, (8, 8)).startswith("the toy never finds nothing; ")


def test_every_backend_names_config_fields_that_exist():
    from ptovs.encoders.backend import get_encoder_backend
    from ptovs.segment.backend import get_segmenter_backend

    fields = {f.name for f in dataclasses.fields(ef.Config)}
    backends = [get_encoder_backend(n) for n in ENCODER_BACKENDS]
    backends += [get_segmenter_backend(n) for n in SEGMENTER_BACKENDS]
    for b in backends:
        assert set(b.config_keys) <= fields, (b.name, set(b.config_keys) - fields)
    hints = typing.get_type_hints(ef.Config)
    assert typing.get_args(hints["segmenter"]) == tuple(SEGMENTER_BACKENDS)
    assert typing.get_args(hints["encoder"]) == ("auto", *ENCODER_BACKENDS)


def test_an_unknown_backend_is_refused_naming_the_choices():
    from ptovs.encoders.backend import get_encoder_backend

    with pytest.raises(InputError, match=r"choose from \['auto', 'synthetic'"):
        get_encoder_backend("dino")


class _NoScene:
    def load(self):  # extra_key reads the scene only for the stand-in
        raise AssertionError("the scene was read")
