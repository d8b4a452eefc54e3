"""The landmark itself: named parts with their textures and primitives, and
`build_world`, a random landmark as a pure function of a generator's state.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from ptovs.synthetic.world.constants import PATTERNS
from ptovs.synthetic.world.primitives import Primitive
from ptovs.synthetic.world.textures import Texture


@dataclass
class Part:
    """A named part of the landmark: one texture, one or more primitives."""

    id: int
    name: str
    query: str
    texture: Texture
    size: float  # characteristic extent (world units), the swatch's side


@dataclass
class World:
    """The landmark (parts and primitives), its ground texture and bounds."""

    parts: list[Part]
    prims: list[Primitive]
    ground: Texture
    center: np.ndarray  # [3] centre of the bounding sphere
    radius: float

    def part_of(self, prim_idx: np.ndarray) -> np.ndarray:
        """Part id per primitive index (-1 for ground and sky)."""
        lut = np.array([p.part for p in self.prims] + [-1, -1], dtype=np.int16)
        return lut[np.where(prim_idx < 0, len(self.prims) - prim_idx - 1, prim_idx)]

    def to_dict(self) -> dict:
        return {
            "parts": [
                {
                    "id": p.id,
                    "name": p.name,
                    "query": p.query,
                    "texture": p.texture.to_dict(),
                    "size": float(p.size),
                    "primitive": [q.to_dict() for q in self.prims if q.part == p.id],
                }
                for p in self.parts
            ],
            "ground": self.ground.to_dict(),
            "center": [float(c) for c in self.center],
            "radius": float(self.radius),
        }

    @classmethod
    def from_dict(cls, d: dict) -> World:
        parts = [
            Part(
                id=int(p["id"]),
                name=p["name"],
                query=p["query"],
                texture=Texture.from_dict(p["texture"]),
                size=float(p["size"]),
            )
            for p in d["parts"]
        ]
        prims = [Primitive.from_dict(q) for p in d["parts"] for q in p["primitive"]]
        return cls(
            parts=parts,
            prims=prims,
            ground=Texture.from_dict(d["ground"]),
            center=np.asarray(d["center"], float),
            radius=float(d["radius"]),
        )


PART_QUERIES = {
    "wall": ("Wall", "Stone Wall", "Brick Facade"),
    "column": ("Column", "Ionic Column", "Corinthian Column", "Doric Column"),
    "dome": ("Dome", "Onion Dome", "Copper Dome"),
    "pediment": ("Pediment", "Triangular Pediment"),
    "roof": ("Roof", "Eave", "Tiled Roof"),
    "door": ("Door", "Bronze Door", "Arched Doorway"),
    "window": ("Window", "Rose Window", "Jali Windows"),
    "stairs": ("Stairs", "Marble Steps"),
    "tower": ("Tower", "Bell Tower", "Minaret"),
    "statue": ("Statue", "Bronze Sculpture", "Winged Horses"),
}


DISTRACTORS = (
    "Obelisk of the Pantheon",
    "Iron Cross",
    "Last Judgment",
    "Fountain of Neptune",
    "Clock Tower",
)


# The parts a small landmark draws its third part from (big enough at ~96 px).
_BIG_PARTS = ("dome", "tower", "pediment", "roof")


_INSTANCE_PRIMS = {"column": 1, "window": 1, "tower": 2, "statue": 3}


_OPTIONAL = ("dome", "pediment", "door", "window", "stairs", "tower", "statue", "roof")


def _hsv(h: float, s: float, v: float) -> tuple[float, float, float]:
    h = (h % 360.0) / 60.0
    i = int(h)
    f = h - i
    p, q, t = v * (1 - s), v * (1 - s * f), v * (1 - s * (1 - f))
    return [(v, t, p), (q, v, p), (p, v, t), (p, q, v), (t, p, v), (v, p, q)][i % 6]


def random_texture(
    rng: np.random.Generator,
    size: float,
    hue: float | None = None,
    pattern: str | None = None,
    sat: tuple[float, float] = (0.3, 0.65),
    val: tuple[float, float] = (0.5, 0.85),
) -> Texture:
    """A texture with 2.5 to 6 periods across `size` world units.

    Args:
        rng: random generator.
        size: the extent the texture is seen over (a part's size).
        hue: base hue in degrees, random if None.
        pattern: one of PATTERNS, random if None.
        sat: range of the base saturation.
        val: range of the base value.

    Returns:
        The texture.
    """
    hue = float(rng.uniform(0, 360)) if hue is None else hue
    pattern = str(rng.choice(PATTERNS)) if pattern is None else pattern
    s, v = rng.uniform(*sat), rng.uniform(*val)
    base = _hsv(hue, s, v)
    if pattern == "bricks":
        m = rng.uniform(0.72, 0.85)
        accent = (m, m * 0.98, m * 0.94)
    elif rng.random() < 0.5:
        accent = _hsv(
            hue + rng.uniform(-20, 20),
            s * rng.uniform(0.6, 1.0),
            v * rng.uniform(0.45, 0.65),
        )
    else:
        accent = _hsv(
            hue + rng.uniform(-20, 20),
            s * rng.uniform(0.4, 0.8),
            min(1.0, v * rng.uniform(1.2, 1.4)),
        )
    periods = rng.uniform(2.5, 6.0)
    return Texture(
        pattern=pattern,
        base=tuple(round(c, 6) for c in base),
        accent=tuple(round(c, 6) for c in accent),
        freq=round(periods / size, 6),
        angle=round(
            float(rng.choice([0.0, math.pi / 2, math.pi / 4, -math.pi / 4])), 6
        ),
        offset=tuple(round(float(c), 6) for c in rng.uniform(-10, 10, 3)),
        seed=int(rng.integers(0, 2**31 - 1)),
    )


def build_world(rng: np.random.Generator, n_parts: int) -> World:
    """A random landmark with `n_parts` parts (3 to 10), wall and columns always.

    The world is one random stream, drawn in a fixed order: the parts, the
    building's frame, each part's geometry, the parts' textures, the ground.

    Args:
        rng: random generator (the world is a pure function of its state).
        n_parts: number of parts.

    Returns:
        The world.
    """
    names = _choose_parts(rng, n_parts)
    geom = _part_geometry(rng, names)
    parts, prims = _dress_parts(rng, names, geom)
    ground = random_texture(
        rng,
        4.0,
        hue=float(rng.uniform(20, 60)),
        pattern=str(rng.choice(["checker", "noise"])),
        sat=(0.05, 0.18),
        val=(0.45, 0.65),
    )
    ground = replace(ground, freq=round(float(rng.uniform(0.6, 1.2)), 6))
    lo = np.min([p.lo for p in prims], axis=0)
    hi = np.max([p.hi for p in prims], axis=0)
    center = (lo + hi) / 2
    radius = float(np.linalg.norm(hi - lo) / 2)
    return World(parts=parts, prims=prims, ground=ground, center=center, radius=radius)


def _choose_parts(rng: np.random.Generator, n_parts: int) -> list[str]:
    """Wall, columns and `n_parts - 2` optional parts, in `_OPTIONAL`'s order."""
    if not 3 <= n_parts <= 2 + len(_OPTIONAL):
        raise ValueError(f"n_parts must be in [3, {2 + len(_OPTIONAL)}], got {n_parts}")
    if n_parts == 3:
        names = ["wall", "column", str(rng.choice(_BIG_PARTS))]
    else:
        extra = list(rng.choice(_OPTIONAL, size=n_parts - 2, replace=False))
        names = ["wall", "column"] + [str(e) for e in extra]
    return ["wall", "column"] + [n for n in _OPTIONAL if n in names]  # stable order


@dataclass(frozen=True)
class _Frame:
    """The building's main dimensions, which every part is placed against."""

    W: float  # width (x)
    D: float  # depth (y)
    Hb: float  # height of the main block
    yf: float  # y of the front face
    span: float  # half the width the columns span
    base_z: float  # floor height (raised by stairs)
    ent_h: float  # entablature height
    col_top: float  # top of the columns


Geometry = dict[str, list[tuple[str, dict]]]


def _part_geometry(rng: np.random.Generator, names: list[str]) -> Geometry:
    """Each part's primitives, as (kind, parameters), placed on a random frame."""
    has = set(names)
    n_parts = len(names)
    W = float(rng.uniform(6.0, 9.0))
    D = float(rng.uniform(3.5, 5.0))
    Hb = float(rng.uniform(3.2, 4.5))
    yf = -D / 2  # front face
    p_depth = float(rng.uniform(1.1, 1.6))  # portico depth
    n_col = 4 if n_parts <= 4 else int(rng.choice([4, 6]))
    col_r = float(rng.uniform(0.2, 0.3))
    ent_h = 0.4
    f = _Frame(
        W=W,
        D=D,
        Hb=Hb,
        yf=yf,
        span=0.8 * W / 2,
        base_z=0.45 if "stairs" in has else 0.0,
        ent_h=ent_h,
        col_top=Hb - ent_h if "pediment" in has else Hb,
    )
    y_col = yf - p_depth + 0.4

    geom: Geometry = {n: [] for n in names}
    geom["wall"].append(("box", {"lo": [-W / 2, yf, 0.0], "hi": [W / 2, D / 2, Hb]}))
    for x in np.linspace(-f.span, f.span, n_col):
        geom["column"].append(
            (
                "cylinder",
                {
                    "center": [float(x), y_col],
                    "radius": col_r,
                    "z0": f.base_z,
                    "z1": f.col_top,
                },
            )
        )
    front = y_col - col_r - 0.3  # front-most y of the portico
    front = _portico(rng, has, f, front, geom)
    _openings(rng, has, f, geom)
    _roof_and_dome(rng, has, f, geom)
    _flanks(rng, has, f, front, geom)
    return geom


def _portico(
    rng: np.random.Generator, has: set[str], f: _Frame, front: float, geom: Geometry
) -> float:
    """Pediment and stairs; returns the portico's new front-most y."""
    if "pediment" in has:
        xw = f.span + 0.5
        hp = float(rng.uniform(0.9, 1.4))
        geom["pediment"].append(
            (
                "box",
                {"lo": [-xw, front, f.col_top], "hi": [xw, f.yf, f.col_top + f.ent_h]},
            )
        )
        geom["pediment"].append(
            (
                "prism",
                {
                    "axis": "y",
                    "lo": front,
                    "hi": f.yf + 0.01,
                    "tri": [[-xw, f.Hb], [xw, f.Hb], [0.0, f.Hb + hp]],
                },
            )
        )
    if "stairs" in has:
        ws = f.span + 0.6
        for k in range(3):
            geom["stairs"].append(
                (
                    "box",
                    {
                        "lo": [-ws, front - 0.45 * (k + 1), 0.0],
                        "hi": [ws, f.yf, 0.45 - 0.15 * k],
                    },
                )
            )
        front -= 1.35
    return front


def _openings(
    rng: np.random.Generator, has: set[str], f: _Frame, geom: Geometry
) -> None:
    """Door and windows, thin panels on the walls."""
    if "door" in has:
        wd, hd = (
            float(rng.uniform(0.9, 1.2)),
            float(rng.uniform(1.8, min(2.6, 0.7 * f.Hb))),
        )
        geom["door"].append(
            (
                "box",
                {
                    "lo": [-wd / 2, f.yf - 0.06, f.base_z],
                    "hi": [wd / 2, f.yf + 0.01, f.base_z + hd],
                },
            )
        )
    if "window" in has:
        z0, z1 = 0.55 * f.Hb, 0.82 * f.Hb
        ww = float(rng.uniform(0.6, 0.9))
        for x in (-0.7 * f.W / 2, -0.35 * f.W / 2, 0.35 * f.W / 2, 0.7 * f.W / 2):
            geom["window"].append(
                (
                    "box",
                    {
                        "lo": [x - ww / 2, f.yf - 0.06, z0],
                        "hi": [x + ww / 2, f.yf + 0.01, z1],
                    },
                )
            )
        for sx in (-1, 1):
            x = sx * f.W / 2
            geom["window"].append(
                (
                    "box",
                    {
                        "lo": [min(x, x + sx * 0.06), -0.35 * f.D, z0],
                        "hi": [max(x, x + sx * 0.06), 0.0, z1],
                    },
                )
            )


def _roof_and_dome(
    rng: np.random.Generator, has: set[str], f: _Frame, geom: Geometry
) -> None:
    """A pitched roof, or a flat one under a dome; the dome on top."""
    W, D, Hb, yf = f.W, f.D, f.Hb, f.yf
    top = Hb
    if "roof" in has:
        if "dome" in has:
            roof_t = 0.3
            geom["roof"].append(
                (
                    "box",
                    {
                        "lo": [-W / 2 - 0.15, yf - 0.15, Hb],
                        "hi": [W / 2 + 0.15, D / 2 + 0.15, Hb + roof_t],
                    },
                )
            )
            top = Hb + roof_t
        else:
            hr = float(rng.uniform(1.0, 1.8))
            geom["roof"].append(
                (
                    "prism",
                    {
                        "axis": "x",
                        "lo": -W / 2 - 0.15,
                        "hi": W / 2 + 0.15,
                        "tri": [[yf - 0.2, Hb], [D / 2 + 0.2, Hb], [0.0, Hb + hr]],
                    },
                )
            )
    if "dome" in has:
        rd = float(rng.uniform(0.32, 0.42) * min(W, D))
        hd = float(rng.uniform(0.3, 0.8))
        geom["dome"].append(
            (
                "cylinder",
                {"center": [0.0, 0.0], "radius": 0.92 * rd, "z0": top, "z1": top + hd},
            )
        )
        geom["dome"].append(
            ("sphere", {"center": [0.0, 0.0, top + hd], "radius": rd, "zmin": top + hd})
        )


def _flanks(
    rng: np.random.Generator, has: set[str], f: _Frame, front: float, geom: Geometry
) -> None:
    """Towers at the sides, statues in front of the portico."""
    if "tower" in has:
        rt = float(rng.uniform(0.5, 0.8))
        ht = f.Hb + float(rng.uniform(1.5, 3.0))
        hs = float(rng.uniform(1.2, 2.2))
        for sx in (-1, 1):
            cx = sx * (f.W / 2 + rt * 0.9)
            geom["tower"].append(
                ("cylinder", {"center": [cx, 0.0], "radius": rt, "z0": 0.0, "z1": ht})
            )
            geom["tower"].append(
                (
                    "cone",
                    {"center": [cx, 0.0], "radius": rt * 1.1, "z0": ht, "z1": ht + hs},
                )
            )
    if "statue" in has:
        for sx in (-1, 1):
            x, y = sx * (f.span + 0.2), front - 1.3
            geom["statue"].append(
                (
                    "box",
                    {"lo": [x - 0.45, y - 0.45, 0.0], "hi": [x + 0.45, y + 0.45, 1.2]},
                )
            )
            geom["statue"].append(
                ("cone", {"center": [x, y], "radius": 0.38, "z0": 1.2, "z1": 2.7})
            )
            geom["statue"].append(
                ("sphere", {"center": [x, y, 2.75], "radius": 0.22, "zmin": None})
            )


def _dress_parts(
    rng: np.random.Generator, names: list[str], geom: Geometry
) -> tuple[list[Part], list[Primitive]]:
    """The parts (distinct hue slots, patterns spread over them) and their primitives."""
    hues = rng.permutation(8) * 45.0 + rng.uniform(-12, 12)
    patterns = [
        PATTERNS[i % len(PATTERNS)] for i in rng.permutation(max(len(names), 5))
    ]
    parts, prims = [], []
    for k, name in enumerate(names):
        # the swatch side: the largest extent of one instance of the part
        inst = geom[name][: _INSTANCE_PRIMS.get(name, len(geom[name]))]
        lo = np.min([Primitive(kd, k, pr).lo for kd, pr in inst], axis=0)
        hi = np.max([Primitive(kd, k, pr).hi for kd, pr in inst], axis=0)
        size = float(max((hi - lo).max(), 0.5))
        tex = random_texture(rng, size, hue=float(hues[k % 8]), pattern=patterns[k])
        query = str(rng.choice(PART_QUERIES[name]))
        parts.append(
            Part(id=k, name=name, query=query, texture=tex, size=round(size, 6))
        )
        prims += [Primitive(kd, k, _round_params(pr)) for kd, pr in geom[name]]
    return parts, prims


def _round_params(p: dict) -> dict:
    def r(v):
        if isinstance(v, (list, tuple)):
            return [r(x) for x in v]
        if isinstance(v, (float, np.floating)):
            return round(float(v), 9)
        return v

    return {k: r(v) for k, v in p.items()}
