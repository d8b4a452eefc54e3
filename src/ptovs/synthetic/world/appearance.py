"""Per-photo appearance: sky, sun, exposure, tint and film filter."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ptovs.synthetic.world.constants import FILTERS


@dataclass(frozen=True)
class Appearance:
    """Per-image lighting and camera processing.

    Colours are display space; light arrives from `sun_dir` (unit, towards the
    light) with `sun_strength` and `sun_color`, plus `ambient` * `ambient_color`.
    The camera multiplies by 2**exposure and the per-channel `tint`, applies the
    filter (none, bw, sepia), clips, and encodes with 1/gamma.
    """

    sky: str
    sun_dir: tuple[float, float, float]
    sun_strength: float
    sun_color: tuple[float, float, float]
    ambient: float
    ambient_color: tuple[float, float, float]
    sky_zenith: tuple[float, float, float]
    sky_horizon: tuple[float, float, float]
    tint: tuple[float, float, float]
    exposure: float
    gamma: float
    filter: str = "none"

    def to_dict(self) -> dict:
        out = {}
        for k, v in self.__dict__.items():
            out[k] = (
                [float(x) for x in v]
                if isinstance(v, tuple)
                else (v if isinstance(v, str) else float(v))
            )
        return out

    @classmethod
    def from_dict(cls, d: dict) -> Appearance:
        kw = {
            k: (tuple(float(x) for x in v) if isinstance(v, list) else v)
            for k, v in d.items()
            if k != "hard"
        }
        return cls(**kw)

    @property
    def hard(self) -> bool:
        """Night, a colour filter, a strong tint or a strong exposure change."""
        tint = np.log(np.asarray(self.tint))
        return (
            self.sky == "night"
            or self.filter != "none"
            or float(tint.max() - tint.min()) > 0.45
            or abs(self.exposure) > 0.75
        )


def _unit(v) -> tuple[float, float, float]:
    v = np.asarray(v, float)
    v = v / np.linalg.norm(v)
    return tuple(round(float(x), 9) for x in v)


def _sun(az_deg: float, el_deg: float) -> tuple[float, float, float]:
    a, e = math.radians(az_deg), math.radians(el_deg)
    return _unit([math.sin(a) * math.cos(e), -math.cos(a) * math.cos(e), math.sin(e)])


def neutral_appearance() -> Appearance:
    """Fixed daylight from the front left, no tint, no filter, gamma 2.2."""
    return Appearance(
        sky="day",
        sun_dir=_sun(-35.0, 50.0),
        sun_strength=0.55,
        sun_color=(1.0, 1.0, 1.0),
        ambient=0.5,
        ambient_color=(1.0, 1.0, 1.0),
        sky_zenith=(0.35, 0.55, 0.9),
        sky_horizon=(0.72, 0.8, 0.92),
        tint=(1.0, 1.0, 1.0),
        exposure=0.0,
        gamma=2.2,
    )


def neutral_light() -> float:
    """Linear light factor of a front face (normal -y) under the neutral appearance."""
    app = neutral_appearance()
    return app.ambient + app.sun_strength * max(0.0, -app.sun_dir[1])


def _r(x: float) -> float:
    return round(float(x), 6)


def sample_appearance(rng: np.random.Generator, hard: bool = False) -> Appearance:
    """A random appearance as in an unconstrained photo collection.

    Args:
        rng: random generator.
        hard: draw from the hard conditions only (night, black-and-white or
            sepia, strong colour temperature, strong over/under exposure).

    Returns:
        The appearance.
    """
    kind = None
    if hard:
        kind = str(rng.choice(["night", "bw", "sepia", "tint", "exposure"]))
    sky = (
        "night"
        if kind == "night"
        else str(
            rng.choice(["day", "dusk", "overcast", "night"], p=[0.52, 0.18, 0.2, 0.1])
        )
    )
    if hard and sky == "night" and kind != "night":
        sky = "day"
    az = rng.uniform(-180.0, 180.0)
    if sky == "day":
        sun = _sun(az, rng.uniform(25.0, 70.0))
        strength, ambient = rng.uniform(0.4, 0.75), rng.uniform(0.3, 0.55)
        sun_c, amb_c = (
            (1.0, rng.uniform(0.95, 1.0), rng.uniform(0.88, 0.98)),
            (rng.uniform(0.9, 1.0), rng.uniform(0.95, 1.0), 1.0),
        )
        zen, hor = (0.3, 0.5, 0.88), (0.7, 0.8, 0.93)
    elif sky == "overcast":
        sun = _sun(az, rng.uniform(30.0, 70.0))
        strength, ambient = rng.uniform(0.0, 0.15), rng.uniform(0.6, 0.9)
        sun_c, amb_c = (1.0, 1.0, 1.0), (0.97, 0.98, 1.0)
        g = rng.uniform(0.6, 0.82)
        zen, hor = (g, g + 0.01, g + 0.03), (g + 0.08, g + 0.08, g + 0.09)
    elif sky == "dusk":
        sun = _sun(az, rng.uniform(3.0, 15.0))
        strength, ambient = rng.uniform(0.45, 0.85), rng.uniform(0.2, 0.35)
        sun_c, amb_c = (
            (1.0, rng.uniform(0.55, 0.7), rng.uniform(0.3, 0.45)),
            (0.75, 0.7, 0.95),
        )
        zen, hor = (0.25, 0.22, 0.45), (1.0, rng.uniform(0.5, 0.65), 0.35)
    else:  # night: floodlights from low in front, dark sky
        sun = _sun(rng.uniform(-60.0, 60.0), rng.uniform(-5.0, 15.0))
        strength, ambient = rng.uniform(0.5, 0.9), rng.uniform(0.03, 0.1)
        sun_c, amb_c = (
            (1.0, rng.uniform(0.7, 0.8), rng.uniform(0.4, 0.5)),
            (0.5, 0.6, 1.0),
        )
        zen, hor = (0.01, 0.015, 0.04), (0.05, 0.05, 0.09)
    temp = rng.normal(0.0, 0.1)
    if kind == "tint":
        temp = rng.choice([-1.0, 1.0]) * rng.uniform(0.3, 0.5)
    green = rng.normal(0.0, 0.04)
    tint = np.exp(
        temp * np.array([1.0, 0.0, -1.0]) + green * np.array([-0.5, 1.0, -0.5])
    )
    exposure = float(np.clip(rng.normal(0.0, 0.28), -0.7, 0.7))
    if kind == "exposure":
        exposure = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.8, 1.3))
    if sky == "night":
        exposure += 0.3
    filt = "none"
    if kind in ("bw", "sepia"):
        filt = kind
    elif not hard:
        filt = str(rng.choice(FILTERS, p=[0.9, 0.06, 0.04]))
    return Appearance(
        sky=sky,
        sun_dir=sun,
        sun_strength=_r(strength),
        sun_color=tuple(_r(c) for c in sun_c),
        ambient=_r(ambient),
        ambient_color=tuple(_r(c) for c in amb_c),
        sky_zenith=tuple(_r(c) for c in zen),
        sky_horizon=tuple(_r(c) for c in hor),
        tint=tuple(_r(c) for c in tint),
        exposure=_r(exposure),
        gamma=_r(rng.uniform(1.9, 2.5)),
        filter=filt,
    )
