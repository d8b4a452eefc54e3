"""Solid procedural textures: a base colour, an accent and a pattern, faded to
the pattern's mean where a pixel covers many periods.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ptovs.synthetic.world.constants import PATTERNS

_INV_SQRT2 = 1.0 / math.sqrt(2.0)


# Mean pattern value per pattern: the colour a texture fades to when a pixel
# covers many periods (a cheap mip-map, see `_fade`).
_PATTERN_MEAN = {
    "stripes": 0.5,
    "checker": 0.5,
    "bricks": 1.0 - (1.0 - 0.14) * (1.0 - 0.07),
    "dots": math.pi * 0.09,
    "noise": 0.5,
}


@dataclass(frozen=True)
class Texture:
    """A solid procedural texture: `base + (accent - base) * pattern(p)`.

    Colours are display-space RGB in [0, 1]. `freq` is in cycles per world unit,
    `angle` (radians) orients stripes in the (horizontal, vertical) plane, and
    `offset` shifts the pattern so that parts do not line up.
    """

    pattern: str
    base: tuple[float, float, float]
    accent: tuple[float, float, float]
    freq: float
    angle: float = 0.0
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    seed: int = 0

    def __post_init__(self) -> None:
        if self.pattern not in PATTERNS:
            raise ValueError(
                f"unknown pattern {self.pattern!r}; choose from {PATTERNS}"
            )

    def to_dict(self) -> dict:
        return {
            "pattern": self.pattern,
            "base": [float(c) for c in self.base],
            "accent": [float(c) for c in self.accent],
            "freq": float(self.freq),
            "angle": float(self.angle),
            "offset": [float(c) for c in self.offset],
            "seed": int(self.seed),
        }

    @classmethod
    def from_dict(cls, d: dict) -> Texture:
        return cls(
            pattern=d["pattern"],
            base=tuple(float(c) for c in d["base"]),
            accent=tuple(float(c) for c in d["accent"]),
            freq=float(d["freq"]),
            angle=float(d.get("angle", 0.0)),
            offset=tuple(float(c) for c in d.get("offset", (0.0, 0.0, 0.0))),
            seed=int(d.get("seed", 0)),
        )


def _hash3(ix: np.ndarray, iy: np.ndarray, iz: np.ndarray, seed: int) -> np.ndarray:
    """Integer lattice hash to [0, 1): exact and platform independent."""
    with np.errstate(over="ignore"):
        h = ix.astype(np.uint64) * np.uint64(0x9E3779B97F4A7C15)
        h ^= iy.astype(np.uint64) * np.uint64(0xC2B2AE3D27D4EB4F)
        h ^= iz.astype(np.uint64) * np.uint64(0x165667B19E3779F9)
        h ^= np.uint64((seed * 0x27D4EB2F165667C5) & 0xFFFFFFFFFFFFFFFF)
        h ^= h >> np.uint64(33)
        h *= np.uint64(0xFF51AFD7ED558CCD)
        h ^= h >> np.uint64(33)
        h *= np.uint64(0xC4CEB9FE1A85EC53)
        h ^= h >> np.uint64(33)
    return (h >> np.uint64(11)).astype(np.float64) * (1.0 / 2.0**53)


def _value_noise(p: np.ndarray, seed: int) -> np.ndarray:
    """Trilinear value noise in [0, 1] with smoothstep weights; p [N, 3]."""
    i = np.floor(p)
    f = p - i
    i = i.astype(np.int64)
    u = f * f * (3.0 - 2.0 * f)
    out = np.zeros(len(p))
    for dx in (0, 1):
        wx = u[:, 0] if dx else 1.0 - u[:, 0]
        for dy in (0, 1):
            wy = u[:, 1] if dy else 1.0 - u[:, 1]
            for dz in (0, 1):
                wz = u[:, 2] if dz else 1.0 - u[:, 2]
                h = _hash3(i[:, 0] + dx, i[:, 1] + dy, i[:, 2] + dz, seed)
                out += wx * wy * wz * h
    return out


def smooth_step(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def pattern_value(tex: Texture, p: np.ndarray) -> np.ndarray:
    """Pattern value in [0, 1] of a solid texture at world points.

    Args:
        tex: the texture.
        p: world points, [N, 3].

    Returns:
        [N] float64: 0 is the base colour, 1 the accent colour.
    """
    q = p + np.asarray(tex.offset)
    f = tex.freq
    h = (
        q[:, 0] + q[:, 1]
    ) * _INV_SQRT2  # a horizontal coordinate seen on x and y faces
    z = q[:, 2]
    if tex.pattern == "stripes":
        s = math.cos(tex.angle) * h + math.sin(tex.angle) * z
        return 0.5 + 0.5 * np.tanh(4.0 * np.sin(2.0 * math.pi * f * s))
    if tex.pattern == "checker":
        k = np.floor(f * q[:, 0]) + np.floor(f * q[:, 1]) + np.floor(f * z)
        return np.mod(k, 2.0)
    if tex.pattern == "bricks":
        rz = 2.0 * f * z
        row = np.floor(rz)
        col = f * h + 0.5 * np.mod(row, 2.0)
        mortar = (rz - row < 0.14) | (col - np.floor(col) < 0.07)
        return mortar.astype(np.float64)
    if tex.pattern == "dots":
        a = f * h
        b = f * z
        a = a - np.floor(a) - 0.5
        b = b - np.floor(b) - 0.5
        return (a * a + b * b < 0.09).astype(np.float64)
    n = 0.65 * _value_noise(q * f, tex.seed) + 0.35 * _value_noise(
        q * (2.7 * f), tex.seed + 1
    )
    return smooth_step(0.32, 0.68, n)


def _fade(tex: Texture, footprint: np.ndarray | float) -> np.ndarray | float:
    """Weight of the mean colour: 0 when a pixel covers < 1/4 period, 1 from 1/2."""
    return smooth_step(0.25, 0.5, np.asarray(footprint) * tex.freq)


def texture_albedo(
    tex: Texture, p: np.ndarray, footprint: np.ndarray | float | None = None
) -> np.ndarray:
    """Display-space albedo of a texture at world points.

    Args:
        tex: the texture.
        p: world points, [N, 3].
        footprint: world size of a pixel at each point ([N] or scalar); where a
            pixel covers many periods the pattern fades to its mean colour.
            None gives the clean (unfiltered) texture.

    Returns:
        [N, 3] float64 in [0, 1].
    """
    t = pattern_value(tex, p)
    if footprint is not None:
        w = _fade(tex, footprint)
        t = t + (_PATTERN_MEAN[tex.pattern] - t) * w
    base = np.asarray(tex.base)
    return base + (np.asarray(tex.accent) - base) * t[:, None]
