"""The text side of the stand-in for CLIP, version 5: a phrase is a category, not
one instance's template.

A part's phrase embeds as the normalised mean content of its part rendered alone
(masked and cut as a segment crop, `part_crops`) from its TEXT_VIEWS best views,
under N_DAYLIGHT ordinary daylight appearances, in its own texture and
N_INSTANCES variants of the same pattern (other colours, frequencies and offsets).
"building", one of the pipeline's canonical phrases, is the *average word* of the
scene's part phrases (LERF chose its canonical phrases as "average" words for
the queries users make, so that a relevancy of 0.5 means "as relevant as an
average word"). Generic phrases, "sky", styles and unknown phrases behave as in
version 1, on this image side.

`CategoryEncoder` holds these rules over an image side (`image_side`): the
plain reading of `standin_stats.content`, with which the generator screens the
queries of version-5 worlds; `synthetic_v5.SyntheticEncoderV5` is the same text
rules over version 5's image side.
"""

from __future__ import annotations

import functools
import hashlib
import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from ptovs.crop import prepare_crop
from ptovs.encoders import synthetic as v1
from ptovs.encoders.standin_stats import DIM, SEED, content
from ptovs.synthetic.world import (
    World,
    neutral_appearance,
    render,
    render_swatch,
    sky_swatch,
)
from ptovs.synthetic.world.appearance import Appearance, sample_appearance
from ptovs.synthetic.world.swatches import landmark_camera
from ptovs.synthetic.world.textures import Texture

TEXT_AZIMUTHS = tuple(range(-150, 181, 30))
TEXT_VIEWS = 3  # the part's best views (most pixels) among TEXT_AZIMUTHS
TEXT_PX = 256
N_INSTANCES = 3  # the part's own texture and this many variants
N_DAYLIGHT = 3


@functools.lru_cache(maxsize=1)
def daylight_appearances() -> tuple[Appearance, ...]:
    """The text side's ordinary lights: neutral and N_DAYLIGHT - 1 fixed draws."""
    rng = np.random.default_rng(SEED + 5)
    out = [neutral_appearance()]
    while len(out) < N_DAYLIGHT:
        a = sample_appearance(rng)
        if a.sky in ("day", "overcast") and not a.hard:
            out.append(a)
    return tuple(out)


def instances(tex: Texture, part_id: int) -> list[Texture]:
    """The part's texture and N_INSTANCES variants of the same pattern."""
    rng = np.random.default_rng([SEED + 6, part_id])
    out = [tex]
    for k in range(N_INSTANCES):
        jit = rng.uniform(0.8, 1.2, 3) * rng.uniform(0.85, 1.15)
        out.append(
            replace(
                tex,
                base=tuple(
                    float(np.clip(c * j, 0.02, 1.0))
                    for c, j in zip(tex.base, jit, strict=True)
                ),
                accent=tuple(
                    float(np.clip(c * j, 0.02, 1.0))
                    for c, j in zip(tex.accent, jit[::-1], strict=True)
                ),
                freq=float(tex.freq * rng.uniform(0.8, 1.25)),
                offset=tuple(float(x) for x in rng.uniform(0.0, 3.0, 3)),
                seed=int(tex.seed) + 101 * (k + 1),
            )
        )
    return out


AVERAGE_WORDS = ("building",)
"""The canonical phrases that embed as the average of the part phrases."""

_PART_CONTENT: dict[str, np.ndarray] = {}  # bounded: cleared past 256 entries


def part_content(world: World, part_id: int, fn=None) -> np.ndarray:
    """Mean content of `part_crops` under the image side `fn` (default: the
    plain reading, `standin_stats.content`), cached by what those crops depend on: the world's
    geometry and this part's texture (other parts' textures never show in this
    part's pixels), so a screen that redraws one part re-renders one."""
    fn = content if fn is None else fn
    d = world.to_dict()
    for q in d["parts"]:
        if q["id"] != part_id:
            q.pop("texture", None)
            q["name"] = q["query"] = ""
    tag = [fn.__module__, fn.__qualname__]
    key = hashlib.sha256(
        json.dumps([d, part_id, *tag, TEXT_PX], sort_keys=True).encode()
    ).hexdigest()
    if key not in _PART_CONTENT:
        if len(_PART_CONTENT) >= 256:
            _PART_CONTENT.clear()
        out = fn(np.stack(part_crops(world, part_id))).mean(axis=0)
        out.flags.writeable = False
        _PART_CONTENT[key] = out
    return _PART_CONTENT[key]


def part_crops(world: World, part_id: int) -> list[np.ndarray]:
    """The part alone, as segment crops: best views x daylight x instances."""
    views = []
    for az in TEXT_AZIMUTHS:
        cam = landmark_camera(world, float(az), TEXT_PX)
        v = render(world, cam, neutral_appearance(), aa=1, shadows=False)
        n = int((v.part_id == part_id).sum())
        if n >= 16:
            views.append((n, az, cam))
    views = sorted(views, key=lambda t: (-t[0], t[1]))[:TEXT_VIEWS]
    part = next(p for p in world.parts if p.id == part_id)
    crops = []
    for tex in instances(part.texture, part_id):
        w = replace(
            world,
            parts=[
                replace(p, texture=tex) if p.id == part_id else p for p in world.parts
            ],
        )
        for _, _, cam in views:
            for app in daylight_appearances():
                v = render(w, cam, app, aa=1)
                m = v.part_id == part_id
                img = np.maximum(v.image.astype(np.float32) / 255.0, 1.0 / 255.0)
                crops.append(prepare_crop(img, m))
    return crops


class CategoryEncoder(v1.SyntheticEncoder):
    """The stand-in's category text rules (module docstring) over `image_side`.
    The vocabulary is version 1's plus "world" (the World dict) and "parts"
    ({phrase: [part ids]}): a listed phrase embeds as its parts' category
    description (`part_crops`)."""

    name = "synthetic-category"
    image_side = staticmethod(content)  # crops [B, S, S, 3] -> unit [B, 512]
    average_words = AVERAGE_WORDS

    def __init__(self, vocabulary: str | Path | dict | None = None) -> None:
        super().__init__(vocabulary)
        vocab = self._vocab
        self._world = World.from_dict(vocab["world"]) if "world" in vocab else None
        self._parts: dict[str, list[int]] = {
            k.strip().lower(): list(v) for k, v in vocab.get("parts", {}).items()
        }

    def encode_images(self, crops: np.ndarray) -> np.ndarray:
        crops = np.asarray(crops)
        if crops.ndim != 4 or crops.shape[-1] != 3:
            raise ValueError(f"crops must be [B, S, S, 3], got {crops.shape}")
        if len(crops) == 0:
            return np.zeros((0, DIM), np.float32)
        return v1._embed(self.image_side(crops), 0)

    def _text_content(self, phrase: str) -> np.ndarray:
        key = phrase.strip().lower()
        if key in AVERAGE_WORDS and self._world is not None and self._parts:
            return self._average_word(key)
        return self._phrase_content(phrase)

    def _phrase_content(self, phrase: str) -> np.ndarray:
        """A phrase's content without the average-word rule."""
        key = phrase.strip().lower()
        if self._world is not None and key in self._parts:
            acc = sum(
                part_content(self._world, pid, self.image_side)
                for pid in self._parts[key]
            )
            return v1._normalise(acc)
        if key == "sky" or key in self._generic or key in self._lower:
            return self._category_swatch(phrase)
        return super()._text_content(phrase)

    def _category_swatch(self, phrase: str) -> np.ndarray:
        key = phrase.strip()
        desc = self._phrases.get(key, self._lower.get(key.lower()))
        items = (
            [{"weight": 1.0, "swatch": desc}]
            if desc is not None
            else self._generic.get(
                key.lower(), [{"weight": 1.0, "swatch": sky_swatch()}]
            )
        )
        acc = np.zeros(DIM)
        for it in items:
            key = json.dumps(it["swatch"], sort_keys=True)
            acc = acc + float(it["weight"]) * _swatch_content(key, self.image_side)
        return v1._normalise(acc)

    def _average_word(self, key: str) -> np.ndarray:
        """m + sqrt(1 - |m|^2) n: m the mean content of the part phrases, n a fixed
        seeded unit vector orthogonal to m. Its cosine with any content c is
        c.m (the mean of the part phrases' cosines with c) plus n's chance
        cosine with c, about N(0, (1 - |m|^2) / 512)."""
        parts = sorted(self._parts)
        m = np.mean([self._phrase_content(p) for p in parts], axis=0)
        n = np.random.default_rng([SEED + 7, *key.encode()]).standard_normal(DIM)
        mm = float(m @ m)
        if mm > 0:
            n = n - (n @ m) / mm * m
        n = n / np.sqrt(n @ n)
        return m + np.sqrt(max(0.0, 1.0 - mm)) * n


@functools.lru_cache(maxsize=1024)
def _swatch_content(key: str, fn=content) -> np.ndarray:
    """Content under the image side `fn` of a swatch (its description as
    canonical JSON), shared by every encoder of the process, as in version 1."""
    out = fn(render_swatch(json.loads(key))[None])[0]
    out.flags.writeable = False
    return out
