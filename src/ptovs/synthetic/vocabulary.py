"""The stand-in encoder's vocabulary of a synthetic scene, and its styles."""

from __future__ import annotations

import numpy as np

from ptovs.synthetic.presets import N_STYLES, STYLES, Preset, _rng, _world
from ptovs.synthetic.world import (
    World,
    part_swatch,
    random_texture,
    sky_swatch,
)


def scene_vocabulary(
    world: World, preset: Preset, distractors: list[str], standin: int = 1
) -> dict:
    """The stand-in encoder's vocabulary: phrase -> canonical swatch description.

    `standin` 5 adds what that version of the stand-in renders its text side
    from: the world ("world") and each part phrase's part ids ("parts")."""
    from ptovs.encoders.synthetic import generic_vocabulary

    phrases: dict[str, dict] = {}
    for part in world.parts:
        sw = part_swatch(world, part, preset.swatch_px)
        phrases[part.query] = sw
        phrases.setdefault(part.name.title(), sw)
    phrases["sky"] = sky_swatch()
    ground = {
        "kind": "texture",
        "texture": world.ground.to_dict(),
        "origin": [0.0, 0.0, 0.0],
        "e1": [1.0, 0.0, 0.0],
        "e2": [0.0, 1.0, 0.0],
        "extent": 6.0,
        "light": part_swatch(world, world.parts[0], 1)["light"],
        "gamma": 2.2,
        "render_px": preset.swatch_px,
    }
    phrases["ground"] = ground
    # a distractor looks like something real that is not in the scene
    for k, phrase in enumerate(distractors):
        rng = np.random.default_rng(
            [int.from_bytes(phrase.encode()[:8].ljust(8, b"\0"), "little"), k]
        )
        tex = random_texture(rng, 3.0)
        phrases[phrase] = dict(
            ground, texture=tex.to_dict(), e2=[0.0, 0.0, -1.0], extent=3.0
        )
    out = {
        "version": 1,
        "phrases": phrases,
        "generic": generic_vocabulary(sky=phrases["sky"], ground=ground),
    }
    if standin == 5:
        parts: dict[str, list[int]] = {}
        for part in world.parts:
            parts.setdefault(part.query, []).append(part.id)
        for part in world.parts:  # a part's name, where it is no one's query
            name = part.name.title()
            if name in phrases and name not in {q.query for q in world.parts}:
                parts.setdefault(name, []).append(part.id)
        out.update(version=standin, world=world.to_dict(), parts=parts)
    elif standin != 1:
        raise ValueError(f"standin must be 1 or 5, got {standin!r}")
    return out


STYLE_AZIMUTHS = (-40.0, 0.0, 40.0)
"""Viewpoints (degrees around the front) a style's look is photographed from."""
STYLE_PX = 128


def landmark_look(world: World) -> list[dict]:
    """A landmark's whole look (a style's text side), as an equal-weight mixture.

    Three swatches of kind "landmark": the whole landmark rendered under the
    neutral daylight from the front and 40 degrees to either side
    (`world.landmark_camera`), masked to the landmark and cropped as a segment
    crop is. The stand-in encoder embeds a style as the normalised mean of the
    three views' content vectors, so a style matches photos of the landmark it
    was drawn from, under any light, and no single part of it. Part names are
    blanked in the stored world: only geometry and textures define the look.
    (Version 1 mixed the parts' own swatches weighted by size squared; the
    encoder could not tell landmarks apart through it: 42 % of bench photos and
    70 % of tiny photos picked their own landmark's style, against 82 % and 89 %
    with the rendered views; work measured in docs/findings.md.)
    """
    d = world.to_dict()
    for p in d["parts"]:
        p["name"] = p["query"] = ""
    w = round(1.0 / len(STYLE_AZIMUTHS), 6)
    return [
        {
            "weight": w,
            "swatch": {"kind": "landmark", "world": d, "azimuth": az, "px": STYLE_PX},
        }
        for az in STYLE_AZIMUTHS
    ]


def scene_styles(preset: Preset, seed: int, world: World) -> tuple[str, dict]:
    """(true style, {candidate style: mixture}) of a seed's landmark.

    Five names are drawn from STYLES (own random stream, so worlds, cameras and
    labels of existing seeds are unchanged); the first is this landmark's style,
    bound to its look (`landmark_look`); each other one is bound to the look of
    the landmark of another seed of the same preset (seed + 7919·k), a
    distractor that looks like a real landmark that is not this one. The
    vocabulary lists the candidates sorted by name, so nothing in it says which
    is true; truth/parts.json does.
    """
    worlds = style_worlds(preset, seed, world)
    styles = {name: landmark_look(w) for name, w in worlds.items()}
    return next(iter(worlds)), dict(sorted(styles.items()))


def style_worlds(preset: Preset, seed: int, world: World) -> dict[str, World]:
    """{style name: the landmark whose look defines it}, the true style first
    (`scene_styles`)."""
    rng = _rng(seed, 8)
    names = [STYLES[i] for i in rng.permutation(len(STYLES))[:N_STYLES]]
    out = {names[0]: world}
    for k, name in enumerate(names[1:], start=1):
        out[name] = _world(preset, seed + 7919 * k)
    return out
