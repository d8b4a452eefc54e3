"""Procedural landmark world: primitives, textures, appearance, ray casting.

The synthetic test bed of SYNTHETIC.md. A landmark is a union of analytic
primitives (convex polytopes: boxes, triangular prisms and thin panels; vertical
cylinders and cones; spheres clipped into domes), each belonging to a named part
with a solid procedural texture. Around it: a ground plane (z = 0) and a sky.
Images are rendered by exact, vectorised numpy ray casting, never by the Gaussian
rasterizer, so the ground truth is independent of the code under test.

Frames: the world is z up and the landmark's front faces -y. A camera looks down
+z with x right and y down; pixel (i, j) has its centre at (u, v) = (j + .5, i + .5)
and u = fx * x / z + cx. A primary ray is `C + t * d` with d = R^T K^-1 [u, v, 1],
so its parameter t is the camera-space depth z of the hit.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

logger = logging.getLogger(__name__)

NO_HIT = -1
GROUND = -2
PATTERNS = ("stripes", "checker", "bricks", "dots", "noise")
SKIES = ("day", "dusk", "overcast", "night")
FILTERS = ("none", "bw", "sepia")
SHAPES = ("person", "umbrella", "vehicle", "sign")

_EPS = 1e-7
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
# AA sample offsets inside a pixel; the first one is the pixel centre (the truth).
_AA_OFFSETS = {
    1: ((0.5, 0.5),),
    5: ((0.5, 0.5), (0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)),
}
_LUMA = np.array([0.299, 0.587, 0.114])
_SEPIA = np.array([1.07, 0.74, 0.43])


# ----------------------------------------------------------------- textures --


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


def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
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
    return _smoothstep(0.32, 0.68, n)


def _fade(tex: Texture, footprint: np.ndarray | float) -> np.ndarray | float:
    """Weight of the mean colour: 0 when a pixel covers < 1/4 period, 1 from 1/2."""
    return _smoothstep(0.25, 0.5, np.asarray(footprint) * tex.freq)


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


# --------------------------------------------------------------- primitives --


def _polytope_planes(kind: str, params: dict) -> tuple[np.ndarray, np.ndarray]:
    """Half-spaces n . x <= d of a box or a triangular prism."""
    if kind == "box":
        lo = np.asarray(params["lo"], float)
        hi = np.asarray(params["hi"], float)
        n = np.concatenate([np.eye(3), -np.eye(3)])
        return n, np.concatenate([hi, -lo])
    # prism: a triangle in the (u, z) plane extruded along `axis`; u is the
    # other horizontal axis.
    ax = 0 if params["axis"] == "x" else 1
    ua = 1 - ax
    tri = np.asarray(params["tri"], float)  # [3, 2] (u, z)
    if (tri[1, 0] - tri[0, 0]) * (tri[2, 1] - tri[0, 1]) - (tri[1, 1] - tri[0, 1]) * (
        tri[2, 0] - tri[0, 0]
    ) < 0:
        tri = tri[::-1]  # counter-clockwise in (u, z)
    normals, ds = [], []
    e = np.zeros(3)
    e[ax] = 1.0
    normals += [e, -e]
    ds += [float(params["hi"]), -float(params["lo"])]
    for k in range(3):
        a, b = tri[k], tri[(k + 1) % 3]
        nu, nz = b[1] - a[1], -(b[0] - a[0])  # outward for a CCW triangle
        norm = math.hypot(nu, nz)
        nrm = np.zeros(3)
        nrm[ua], nrm[2] = nu / norm, nz / norm
        normals.append(nrm)
        ds.append(float(nrm[ua] * a[0] + nrm[2] * a[1]))
    return np.asarray(normals), np.asarray(ds)


@dataclass
class Primitive:
    """One analytic solid of the landmark.

    kinds and params (JSON-ready):
      box      {"lo": [3], "hi": [3]}
      prism    {"axis": "x"|"y", "lo": a0, "hi": a1, "tri": [[u, z] x 3]}
      cylinder {"center": [x, y], "radius": r, "z0": z0, "z1": z1}   (vertical)
      cone     {"center": [x, y], "radius": r, "z0": z0, "z1": z1}   (apex at z1)
      sphere   {"center": [3], "radius": r, "zmin": z or None}       (dome if clipped)
    """

    kind: str
    part: int
    params: dict
    planes: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)
    lo: np.ndarray = field(default=None, repr=False)  # type: ignore[assignment]
    hi: np.ndarray = field(default=None, repr=False)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        p = self.params
        if self.kind in ("box", "prism"):
            self.planes = _polytope_planes(self.kind, p)
        if self.kind == "box":
            self.lo, self.hi = np.asarray(p["lo"], float), np.asarray(p["hi"], float)
        elif self.kind == "prism":
            ax = 0 if p["axis"] == "x" else 1
            tri = np.asarray(p["tri"], float)
            lo, hi = np.zeros(3), np.zeros(3)
            lo[ax], hi[ax] = p["lo"], p["hi"]
            lo[1 - ax], hi[1 - ax] = tri[:, 0].min(), tri[:, 0].max()
            lo[2], hi[2] = tri[:, 1].min(), tri[:, 1].max()
            self.lo, self.hi = lo, hi
        elif self.kind in ("cylinder", "cone"):
            cx, cy = p["center"]
            r = p["radius"]
            self.lo = np.array([cx - r, cy - r, p["z0"]], float)
            self.hi = np.array([cx + r, cy + r, p["z1"]], float)
        elif self.kind == "sphere":
            c = np.asarray(p["center"], float)
            r = float(p["radius"])
            self.lo, self.hi = c - r, c + r
            if p.get("zmin") is not None:
                self.lo[2] = max(self.lo[2], float(p["zmin"]))
        else:
            raise ValueError(f"unknown primitive kind {self.kind!r}")

    def to_dict(self) -> dict:
        return {"kind": self.kind, "part": int(self.part), "params": self.params}

    @classmethod
    def from_dict(cls, d: dict) -> Primitive:
        return cls(kind=d["kind"], part=int(d["part"]), params=d["params"])

    def corners(self) -> np.ndarray:
        """The 8 corners of the axis-aligned bounding box, [8, 3]."""
        g = np.array(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij")).reshape(3, -1)
        return np.where(g.T == 0, self.lo, self.hi)

    def intersect(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First entry hit of rays from outside the solid.

        Args:
            o: ray origins, [3] (shared) or [R, 3].
            d: ray directions (any length), [R, 3].

        Returns:
            t [R] (np.inf where missed) and outward unit normals [R, 3].
        """
        if self.kind in ("box", "prism"):
            return _hit_planes(self.planes[0], self.planes[1], o, d)
        if self.kind == "cylinder":
            return _hit_cylinder(self.params, o, d)
        if self.kind == "cone":
            return _hit_cone(self.params, o, d)
        return _hit_sphere(self.params, o, d)


def _dot3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    # explicit sums, not BLAS: bitwise stable whatever the thread count
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _hit_planes(
    normals: np.ndarray, ds: np.ndarray, o: np.ndarray, d: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    nv = (
        d[:, 0:1] * normals[:, 0]
        + d[:, 1:2] * normals[:, 1]
        + d[:, 2:3] * normals[:, 2]
    )  # [R, m]
    o2 = o if o.ndim == 2 else o[None, :]
    no = (
        o2[:, 0:1] * normals[:, 0]
        + o2[:, 1:2] * normals[:, 1]
        + o2[:, 2:3] * normals[:, 2]
    )
    num = ds - no
    with np.errstate(divide="ignore", invalid="ignore"):
        tt = num / nv
    t_enter_all = np.where(nv < 0, tt, -np.inf)
    which = np.argmax(t_enter_all, axis=1)
    t_enter = np.take_along_axis(t_enter_all, which[:, None], 1)[:, 0]
    t_exit = np.where(nv > 0, tt, np.inf).min(axis=1)
    outside = ((nv == 0) & (num < 0)).any(axis=1)
    hit = (t_enter <= t_exit) & ~outside & (t_enter > _EPS)
    return np.where(hit, t_enter, np.inf), normals[which]


def _quadratic_roots(a, b, c) -> tuple[np.ndarray, np.ndarray]:
    """Both real roots (nan where none) of a t^2 + b t + c, stable form."""
    disc = b * b - 4.0 * a * c
    sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
    qq = -0.5 * (b + np.where(b >= 0, sq, -sq))
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = qq / a
        r2 = c / qq
        lin = np.abs(a) < 1e-14  # degenerate: b t + c = 0
        r1 = np.where(lin, -c / b, r1)
        r2 = np.where(lin, np.nan, r2)
    return r1, r2


def _take_first(
    cands: list[tuple[np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray]:
    """Smallest positive valid candidate t, and which candidate it was."""
    ts = np.stack([np.where(ok & (t > _EPS), t, np.inf) for t, ok in cands])
    k = np.argmin(ts, axis=0)
    return np.take_along_axis(ts, k[None], 0)[0], k


def _hit_cylinder(
    p: dict, o: np.ndarray, d: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    cx, cy = p["center"]
    r, z0, z1 = p["radius"], p["z0"], p["z1"]
    o2 = np.broadcast_to(o, d.shape)
    ox, oy, oz = o2[:, 0] - cx, o2[:, 1] - cy, o2[:, 2]
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    r1, r2 = _quadratic_roots(
        dx * dx + dy * dy, 2 * (ox * dx + oy * dy), ox * ox + oy * oy - r * r
    )
    cands = []
    for t in (r1, r2):
        z = oz + t * dz
        cands.append((t, (z >= z0) & (z <= z1)))
    with np.errstate(divide="ignore", invalid="ignore"):
        for zc in (z0, z1):
            t = (zc - oz) / dz
            x, y = ox + t * dx, oy + t * dy
            cands.append((t, x * x + y * y <= r * r))
    t, k = _take_first(cands)
    hx, hy = ox + t * dx, oy + t * dy
    n = np.zeros(d.shape)
    side = k < 2
    with np.errstate(invalid="ignore"):
        n[:, 0] = np.where(side, hx / r, 0.0)
        n[:, 1] = np.where(side, hy / r, 0.0)
    n[:, 2] = np.where(k == 2, -1.0, np.where(k == 3, 1.0, 0.0))
    return t, n


def _hit_cone(p: dict, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    cx, cy = p["center"]
    r, z0, z1 = p["radius"], p["z0"], p["z1"]
    k = r / (z1 - z0)
    o2 = np.broadcast_to(o, d.shape)
    ox, oy, oz = o2[:, 0] - cx, o2[:, 1] - cy, o2[:, 2]
    dx, dy, dz = d[:, 0], d[:, 1], d[:, 2]
    w0 = z1 - oz
    k2 = k * k
    a = dx * dx + dy * dy - k2 * dz * dz
    b = 2.0 * (ox * dx + oy * dy) + 2.0 * k2 * w0 * dz
    c = ox * ox + oy * oy - k2 * w0 * w0
    r1, r2 = _quadratic_roots(a, b, c)
    cands = []
    for t in (r1, r2):
        z = oz + t * dz
        cands.append((t, (z >= z0) & (z <= z1)))
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (z0 - oz) / dz
        x, y = ox + t * dx, oy + t * dy
        cands.append((t, x * x + y * y <= r * r))
    t, which = _take_first(cands)
    hx, hy = ox + t * dx, oy + t * dy
    rho = np.sqrt(hx * hx + hy * hy)
    side = which < 2
    with np.errstate(divide="ignore", invalid="ignore"):
        n = np.stack([hx / rho, hy / rho, np.full_like(rho, k)], axis=1) / math.sqrt(
            1 + k2
        )
    n = np.where(side[:, None], np.nan_to_num(n), np.array([0.0, 0.0, -1.0]))
    return t, n


def _hit_sphere(p: dict, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    c = np.asarray(p["center"], float)
    r = float(p["radius"])
    zmin = p.get("zmin")
    o2 = np.broadcast_to(o, d.shape)
    oc = o2 - c
    r1, r2 = _quadratic_roots(_dot3(d, d), 2.0 * _dot3(oc, d), _dot3(oc, oc) - r * r)
    cands = []
    for t in (r1, r2):
        z = o2[:, 2] + t * d[:, 2]
        cands.append((t, np.ones_like(t, bool) if zmin is None else z >= zmin))
    if zmin is not None:
        rc2 = r * r - (zmin - c[2]) ** 2
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (zmin - o2[:, 2]) / d[:, 2]
            x, y = oc[:, 0] + t * d[:, 0], oc[:, 1] + t * d[:, 1]
            cands.append((t, x * x + y * y <= rc2))
    t, which = _take_first(cands)
    with np.errstate(invalid="ignore"):
        n = (oc + t[:, None] * d) / r
    n = np.where((which < 2)[:, None], np.nan_to_num(n), np.array([0.0, 0.0, -1.0]))
    return t, n


# -------------------------------------------------------------------- world --


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

    Args:
        rng: random generator (the world is a pure function of its state).
        n_parts: number of parts.

    Returns:
        The world.
    """
    if not 3 <= n_parts <= 2 + len(_OPTIONAL):
        raise ValueError(f"n_parts must be in [3, {2 + len(_OPTIONAL)}], got {n_parts}")
    if n_parts == 3:
        names = ["wall", "column", str(rng.choice(_BIG_PARTS))]
    else:
        extra = list(rng.choice(_OPTIONAL, size=n_parts - 2, replace=False))
        names = ["wall", "column"] + [str(e) for e in extra]
    names = ["wall", "column"] + [n for n in _OPTIONAL if n in names]  # stable order
    has = set(names)

    W = float(rng.uniform(6.0, 9.0))
    D = float(rng.uniform(3.5, 5.0))
    Hb = float(rng.uniform(3.2, 4.5))
    yf = -D / 2  # front face
    p_depth = float(rng.uniform(1.1, 1.6))  # portico depth
    n_col = 4 if n_parts <= 4 else int(rng.choice([4, 6]))
    col_r = float(rng.uniform(0.2, 0.3))
    span = 0.8 * W / 2
    base_z = 0.45 if "stairs" in has else 0.0
    ent_h = 0.4
    col_top = Hb - ent_h if "pediment" in has else Hb
    y_col = yf - p_depth + 0.4
    roof_t = 0.3 if ("roof" in has and "dome" in has) else 0.0

    geom: dict[str, list[tuple[str, dict]]] = {n: [] for n in names}
    geom["wall"].append(("box", {"lo": [-W / 2, yf, 0.0], "hi": [W / 2, D / 2, Hb]}))
    for x in np.linspace(-span, span, n_col):
        geom["column"].append(
            (
                "cylinder",
                {
                    "center": [float(x), y_col],
                    "radius": col_r,
                    "z0": base_z,
                    "z1": col_top,
                },
            )
        )
    front = y_col - col_r - 0.3  # front-most y of the portico
    if "pediment" in has:
        xw = span + 0.5
        hp = float(rng.uniform(0.9, 1.4))
        geom["pediment"].append(
            ("box", {"lo": [-xw, front, col_top], "hi": [xw, yf, col_top + ent_h]})
        )
        geom["pediment"].append(
            (
                "prism",
                {
                    "axis": "y",
                    "lo": front,
                    "hi": yf + 0.01,
                    "tri": [[-xw, Hb], [xw, Hb], [0.0, Hb + hp]],
                },
            )
        )
    if "stairs" in has:
        ws = span + 0.6
        for k in range(3):
            geom["stairs"].append(
                (
                    "box",
                    {
                        "lo": [-ws, front - 0.45 * (k + 1), 0.0],
                        "hi": [ws, yf, 0.45 - 0.15 * k],
                    },
                )
            )
        front -= 1.35
    if "door" in has:
        wd, hd = (
            float(rng.uniform(0.9, 1.2)),
            float(rng.uniform(1.8, min(2.6, 0.7 * Hb))),
        )
        geom["door"].append(
            (
                "box",
                {
                    "lo": [-wd / 2, yf - 0.06, base_z],
                    "hi": [wd / 2, yf + 0.01, base_z + hd],
                },
            )
        )
    if "window" in has:
        z0, z1 = 0.55 * Hb, 0.82 * Hb
        ww = float(rng.uniform(0.6, 0.9))
        for x in (-0.7 * W / 2, -0.35 * W / 2, 0.35 * W / 2, 0.7 * W / 2):
            geom["window"].append(
                (
                    "box",
                    {
                        "lo": [x - ww / 2, yf - 0.06, z0],
                        "hi": [x + ww / 2, yf + 0.01, z1],
                    },
                )
            )
        for sx in (-1, 1):
            x = sx * W / 2
            geom["window"].append(
                (
                    "box",
                    {
                        "lo": [min(x, x + sx * 0.06), -0.35 * D, z0],
                        "hi": [max(x, x + sx * 0.06), 0.0, z1],
                    },
                )
            )
    top = Hb
    if "roof" in has:
        if "dome" in has:
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
    if "tower" in has:
        rt = float(rng.uniform(0.5, 0.8))
        ht = Hb + float(rng.uniform(1.5, 3.0))
        hs = float(rng.uniform(1.2, 2.2))
        for sx in (-1, 1):
            cx = sx * (W / 2 + rt * 0.9)
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
            x, y = sx * (span + 0.2), front - 1.3
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

    # Textures: distinct hue slots, patterns spread over the parts.
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

    g_hue = float(rng.uniform(20, 60))
    ground = random_texture(
        rng,
        4.0,
        hue=g_hue,
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


def _round_params(p: dict) -> dict:
    def r(v):
        if isinstance(v, (list, tuple)):
            return [r(x) for x in v]
        if isinstance(v, (float, np.floating)):
            return round(float(v), 9)
        return v

    return {k: r(v) for k, v in p.items()}


# ------------------------------------------------------------------ cameras --


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: K [3, 3], cam_from_world [4, 4] (rigid), image size."""

    K: np.ndarray
    cam_from_world: np.ndarray
    width: int
    height: int

    @property
    def R(self) -> np.ndarray:
        return self.cam_from_world[:3, :3]

    @property
    def t(self) -> np.ndarray:
        return self.cam_from_world[:3, 3]

    @property
    def centre(self) -> np.ndarray:
        """Camera centre in world coordinates, [3]."""
        return -(self.R.T @ self.t)

    def ray_dirs(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """World directions with camera-z 1 through image points; [..., 3]."""
        fx, fy, cx, cy = self.K[0, 0], self.K[1, 1], self.K[0, 2], self.K[1, 2]
        xc, yc = (u - cx) / fx, (v - cy) / fy
        R = self.R
        return np.stack(
            [R[0, k] * xc + R[1, k] * yc + R[2, k] for k in range(3)], axis=-1
        )

    def project(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates [N, 2] and camera depths [N] of world points [N, 3]."""
        R, t = self.R, self.t
        xc = [
            R[k, 0] * X[:, 0] + R[k, 1] * X[:, 1] + R[k, 2] * X[:, 2] + t[k]
            for k in range(3)
        ]
        z = xc[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.K[0, 0] * xc[0] / z + self.K[0, 2]
            v = self.K[1, 1] * xc[1] / z + self.K[1, 2]
        return np.stack([u, v], axis=1), z

    def window(self, i0: int, i1: int, j0: int, j1: int) -> Camera:
        """The camera of the pixel rows i0:i1, columns j0:j1 of this image.

        Its pixel (i, j) casts exactly the rays of this camera's pixel
        (i + i0, j + j0), so rendering a window renders those pixels alone.
        """
        K = self.K.copy()
        K[0, 2] -= j0
        K[1, 2] -= i0
        return Camera(K, self.cam_from_world, int(j1 - j0), int(i1 - i0))

    def to_dict(self) -> dict:
        return {
            "width": int(self.width),
            "height": int(self.height),
            "K": self.K.tolist(),
            "cam_from_world": self.cam_from_world.tolist(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> Camera:
        return cls(
            np.asarray(d["K"], float),
            np.asarray(d["cam_from_world"], float),
            int(d["width"]),
            int(d["height"]),
        )


def look_at(eye: np.ndarray, target: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """cam_from_world [4, 4] of a camera at `eye` looking at `target` (world z up)."""
    fwd = target - eye
    fwd = fwd / np.linalg.norm(fwd)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-9:  # looking straight up or down
        right = np.array([1.0, 0.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    c, s = math.cos(roll), math.sin(roll)
    right, down = c * right + s * down, -s * right + c * down
    R = np.stack([right, down, fwd])
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ eye
    return T


def _orbit_eye(world: World, azimuth: float, dist: float, height: float) -> np.ndarray:
    """A camera centre `dist` from the landmark's axis at `azimuth` degrees around
    the front (0 = in front, -y), at `height`."""
    a = math.radians(azimuth)
    return np.array(
        [
            world.center[0] + dist * math.sin(a),
            world.center[1] - dist * math.cos(a),
            height,
        ]
    )


def _focal_to_fill(world: World, eye: np.ndarray, fill: float, side: int) -> float:
    """Focal length at which the bounding sphere, seen from `eye`, spans `fill`
    times an image side of `side` pixels."""
    half = math.asin(
        min(0.99, world.radius / float(np.linalg.norm(world.center - eye)))
    )
    return fill * (side / 2) / math.tan(half)


def sample_camera(
    rng: np.random.Generator,
    world: World,
    long_side: tuple[int, int],
    frontal: bool = False,
) -> Camera:
    """A Photo-Tourism-like camera: varied arcs, distances, focal, size, aspect.

    Args:
        rng: random generator.
        world: the landmark the camera looks at.
        long_side: range of the image's long side in pixels.
        frontal: draw only frontal, non-close-up views (evaluation candidates).

    Returns:
        The camera.
    """
    R = world.radius
    if frontal:
        az = rng.normal(0.0, 25.0)
    elif rng.random() < 0.85:
        az = float(np.clip(rng.normal(0.0, 40.0), -100.0, 100.0))
    else:
        az = rng.uniform(-180.0, 180.0)
    dist = R * math.exp(rng.uniform(math.log(1.8), math.log(3.6)))
    if rng.random() < 0.85 or frontal:
        height = rng.uniform(1.2, 0.3 * 2 * world.center[2] + 1.5)
    else:
        height = rng.uniform(2.0, 1.2 * R)
    eye = _orbit_eye(world, az, dist, height)
    close = (not frontal) and rng.random() < 0.15
    target = world.center + rng.normal(0.0, (0.3 if close else 0.12) * R, 3)
    target[2] = max(target[2], 0.5)
    roll = math.radians(rng.normal(0.0, 2.0))
    L = int(rng.integers(long_side[0], long_side[1] + 1))
    aspect = float(rng.choice([4 / 3, 3 / 2, 16 / 9, 1.0, 5 / 4]))
    S = max(8, round(L / aspect))
    w, h = (S, L) if rng.random() < 0.3 else (L, S)
    fill = rng.uniform(1.5, 2.2) if close else rng.uniform(0.8, 1.35)
    f = _focal_to_fill(world, eye, fill, min(w, h))
    K = np.array([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])
    return Camera(K, look_at(eye, target, roll), int(w), int(h))


# --------------------------------------------------------------- appearance --


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


# --------------------------------------------------------------- transients --


@dataclass(frozen=True)
class Billboard:
    """A transient occluder: a camera-facing planar shape with its own texture."""

    shape: str
    center: tuple[float, float, float]
    right: tuple[float, float, float]  # unit, in the plane
    up: tuple[float, float, float]  # unit, in the plane
    half_w: float
    half_h: float
    texture: Texture

    def to_dict(self) -> dict:
        d = {k: v for k, v in self.__dict__.items() if k != "texture"}
        d = {
            k: ([float(x) for x in v] if isinstance(v, tuple) else v)
            for k, v in d.items()
        }
        d["texture"] = self.texture.to_dict()
        return d

    @classmethod
    def from_dict(cls, d: dict) -> Billboard:
        return cls(
            shape=d["shape"],
            center=tuple(d["center"]),
            right=tuple(d["right"]),
            up=tuple(d["up"]),
            half_w=float(d["half_w"]),
            half_h=float(d["half_h"]),
            texture=Texture.from_dict(d["texture"]),
        )

    def intersect(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Hit t [R] (inf if missed) and local coordinates [R, 2] in [-1, 1]^2."""
        c, r, u = np.asarray(self.center), np.asarray(self.right), np.asarray(self.up)
        n = np.cross(r, u)
        o2 = np.broadcast_to(o, d.shape)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = _dot3(c - o2, n) / _dot3(d, n)
        p = o2 + t[:, None] * d - c
        s = _dot3(p, r) / self.half_w
        q = _dot3(p, u) / self.half_h
        inside = _silhouette(self.shape, s, q) & (t > _EPS)
        return np.where(inside, t, np.inf), np.stack([s, q], axis=1)


def _silhouette(shape: str, s: np.ndarray, q: np.ndarray) -> np.ndarray:
    box = (np.abs(s) <= 1) & (np.abs(q) <= 1)
    if shape == "person":
        head = s * s / 0.16 + (q - 0.72) ** 2 / 0.07 <= 1
        body = (np.abs(s) <= 0.75 - 0.25 * np.clip(q - 0.2, 0, 1) / 0.3) & (q <= 0.5)
        return box & (head | body)
    if shape == "umbrella":
        canopy = (s * s + ((q - 0.25) / 0.75) ** 2 <= 1) & (q >= 0.25)
        pole = np.abs(s) <= 0.05
        return box & (canopy | pole)
    if shape == "vehicle":
        body = q <= 0.2
        cabin = (np.abs(s) <= 0.6) & (q <= 0.9)
        return box & (body | cabin)
    return box


def sample_transients(
    rng: np.random.Generator,
    world: World,
    cam: Camera,
    max_cover: float = 0.4,
    k_max: int = 5,
) -> list[Billboard]:
    """0 to k_max billboards between the camera and the landmark.

    The target coverage is 0 with probability 0.3, else uniform in
    [0.03, max_cover]; billboards are added until it is reached and never
    beyond max_cover + 0.05 of the image.

    Args:
        rng: random generator.
        world: the landmark (sets how far away the billboards may stand).
        cam: the camera the billboards face.
        max_cover: largest target fraction of the image covered.
        k_max: most billboards.

    Returns:
        The billboards.
    """
    if rng.random() < 0.3 or max_cover <= 0:
        return []
    target = rng.uniform(0.03, max_cover)
    C = cam.centre
    dist = float(np.linalg.norm(world.center - C))
    d_far = max(0.25 * dist, dist - 1.1 * world.radius)
    W, H = cam.width, cam.height
    fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
    R = cam.R
    covered = np.zeros((H, W), bool)
    uu, vv = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    dirs = cam.ray_dirs(uu, vv).reshape(-1, 3)
    out: list[Billboard] = []
    for _ in range(k_max):
        shape = str(rng.choice(SHAPES, p=[0.5, 0.2, 0.15, 0.15]))
        aspect = {"person": 0.4, "umbrella": 1.0, "vehicle": 2.0, "sign": 0.8}[shape]
        hf = rng.uniform(0.2, 0.75)  # height as a fraction of the image height
        hpx = hf * H
        wpx = aspect * hpx
        uc = rng.uniform(0.0, W)
        vb = rng.uniform(0.6 * H, 1.15 * H)  # bottom edge
        vc = vb - hpx / 2
        depth = rng.uniform(0.15 * dist, d_far)
        pc = np.array([(uc - cx) / fx * depth, (vc - cy) / fy * depth, depth])
        centre = R.T @ (pc - cam.t)
        hue = rng.uniform(0, 360)
        tex = random_texture(rng, 1.0, hue=hue, sat=(0.4, 0.9), val=(0.3, 0.95))
        bb = Billboard(
            shape=shape,
            center=tuple(round(float(x), 9) for x in centre),
            right=tuple(float(x) for x in R[0]),
            up=tuple(float(x) for x in -R[1]),
            half_w=round(float(wpx / 2 / fx * depth), 9),
            half_h=round(float(hpx / 2 / fy * depth), 9),
            texture=tex,
        )
        t, _ = bb.intersect(C, dirs)
        mask = covered | np.isfinite(t).reshape(H, W)
        if mask.mean() > max_cover + 0.05:
            continue
        out.append(bb)
        covered = mask
        if covered.mean() >= target:
            break
    return out


# ------------------------------------------------------------------ casting --


def screen_boxes(world: World, cam: Camera) -> list[tuple[int, int, int, int] | None]:
    """Conservative pixel box of every primitive's bounding box in a camera.

    Args:
        world: the world.
        cam: the camera.

    Returns:
        Per primitive, (i0, i1, j0, j1) (rows i0:i1, columns j0:j1), or None when
        it projects outside the image.
    """
    out = []
    for p in world.prims:
        uv, z = cam.project(p.corners())
        if (z <= 1e-6).any():
            out.append((0, cam.height, 0, cam.width))
            continue
        j0 = max(0, int(math.floor(uv[:, 0].min())) - 1)
        j1 = min(cam.width, int(math.ceil(uv[:, 0].max())) + 1)
        i0 = max(0, int(math.floor(uv[:, 1].min())) - 1)
        i1 = min(cam.height, int(math.ceil(uv[:, 1].max())) + 1)
        out.append((i0, i1, j0, j1) if (i1 > i0 and j1 > j0) else None)
    return out


def cast(
    world: World,
    o: np.ndarray,
    d: np.ndarray,
    cands: Sequence[np.ndarray | None] | None = None,
    ground: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First hit of rays with the landmark and the ground.

    Args:
        world: the world.
        o: origins, [3] (shared) or [R, 3].
        d: directions, [R, 3].
        cands: per primitive, the indices of the rays that may hit it (None: all).
        ground: include the ground plane z = 0.

    Returns:
        t [R] (inf: sky), primitive index [R] int32 (NO_HIT, GROUND or >= 0),
        and unit normals [R, 3].
    """
    n_rays = len(d)
    best_t = np.full(n_rays, np.inf)
    best_i = np.full(n_rays, NO_HIT, np.int32)
    best_n = np.zeros((n_rays, 3))
    for k, prim in enumerate(world.prims):
        idx = None if cands is None else cands[k]
        if idx is None:
            t, n = prim.intersect(o, d)
            better = t < best_t
            best_t[better] = t[better]
            best_i[better] = k
            best_n[better] = n[better]
            continue
        if len(idx) == 0:
            continue
        oo = o if o.ndim == 1 else o[idx]
        t, n = prim.intersect(oo, d[idx])
        better = t < best_t[idx]
        sel = idx[better]
        best_t[sel] = t[better]
        best_i[sel] = k
        best_n[sel] = n[better]
    if ground:
        oz = o[2] if o.ndim == 1 else o[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            tg = np.where((d[:, 2] < 0) & (oz > 0), -oz / d[:, 2], np.inf)
        better = tg < best_t
        best_t[better] = tg[better]
        best_i[better] = GROUND
        best_n[better] = (0.0, 0.0, 1.0)
    return best_t, best_i, best_n


def _grid_cands(boxes, rows: int, cols: int) -> list[np.ndarray]:
    out = []
    for b in boxes:
        if b is None:
            out.append(np.zeros(0, np.int64))
            continue
        i0, i1, j0, j1 = b
        out.append(
            (np.arange(i0, i1)[:, None] * cols + np.arange(j0, j1)[None, :]).ravel()
        )
    return out


def _shadowed(world: World, p: np.ndarray, light: np.ndarray) -> np.ndarray:
    """Whether points [N, 3] are in the shadow of the landmark (directional light)."""
    if len(p) == 0:
        return np.zeros(0, bool)
    # Cull per primitive in the plane perpendicular to the light.
    e1 = np.cross(light, [0.0, 0.0, 1.0] if abs(light[2]) < 0.9 else [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(light, e1)
    a, b, c = _dot3(p, e1), _dot3(p, e2), _dot3(p, light)
    cands = []
    for prim in world.prims:
        cr = prim.corners()
        ca, cb, cc = _dot3(cr, e1), _dot3(cr, e2), _dot3(cr, light)
        sel = (
            (a >= ca.min())
            & (a <= ca.max())
            & (b >= cb.min())
            & (b <= cb.max())
            & (c <= cc.max())
        )
        cands.append(np.flatnonzero(sel))
    d = np.broadcast_to(light, p.shape).copy()
    t, _, _ = cast(world, p, d, cands, ground=False)
    return np.isfinite(t)


# ---------------------------------------------------------------- rendering --


@dataclass
class View:
    """A rendered image and its truth at pixel centres."""

    image: np.ndarray  # [H, W, 3] uint8 RGB
    part_id: np.ndarray  # [H, W] int16, -1 sky/ground
    transient: np.ndarray  # [H, W] bool
    depth: np.ndarray  # [H, W] float32 camera z of landmark or ground, inf for sky


def _lin(c) -> np.ndarray:
    return np.asarray(c, float) ** 2.2


def develop(radiance: np.ndarray, app: Appearance) -> np.ndarray:
    """Camera processing: exposure, tint, filter, clip, gamma, 8-bit rounding.

    Args:
        radiance: linear RGB, [..., 3].
        app: the appearance.

    Returns:
        uint8 RGB, [..., 3].
    """
    x = radiance * (2.0**app.exposure) * np.asarray(app.tint)
    if app.filter != "none":
        y = x[..., 0] * _LUMA[0] + x[..., 1] * _LUMA[1] + x[..., 2] * _LUMA[2]
        x = y[..., None] * (_SEPIA if app.filter == "sepia" else np.ones(3))
    x = np.clip(x, 0.0, 1.0) ** (1.0 / app.gamma)
    return np.floor(x * 255.0 + 0.5).astype(np.uint8)


def _sky(app: Appearance, d: np.ndarray) -> np.ndarray:
    dn = d / np.linalg.norm(d, axis=1, keepdims=True)
    w = _smoothstep(0.0, 0.5, dn[:, 2])[:, None]
    rad = _lin(app.sky_horizon) * (1 - w) + _lin(app.sky_zenith) * w
    if app.sky in ("day", "dusk") and app.sun_dir[2] > 0:
        glow = np.clip(_dot3(dn, np.asarray(app.sun_dir)), 0, 1) ** 64
        rad = rad + 0.4 * glow[:, None] * _lin(app.sun_color)
    return rad


def surface_albedo(
    world: World, prim: np.ndarray, p: np.ndarray, footprint: np.ndarray | None = None
) -> np.ndarray:
    """Display-space albedo [N, 3] at hit points of primitives / the ground.

    Args:
        world: the world.
        prim: primitive index per point (>= 0 or GROUND), [N].
        p: world points, [N, 3].
        footprint: world size of a pixel per point, [N]; None for the clean texture.

    Returns:
        [N, 3] float64.
    """
    out = np.zeros((len(p), 3))
    part = world.part_of(prim)
    for k, part_k in enumerate(world.parts):
        sel = np.flatnonzero((part == k) & (prim >= 0))
        if len(sel):
            fp = None if footprint is None else footprint[sel]
            out[sel] = texture_albedo(part_k.texture, p[sel], fp)
    sel = np.flatnonzero(prim == GROUND)
    if len(sel):
        fp = None if footprint is None else footprint[sel]
        out[sel] = texture_albedo(world.ground, p[sel], fp)
    return out


def render(
    world: World,
    cam: Camera,
    app: Appearance,
    billboards: Sequence[Billboard] = (),
    aa: int = 5,
    shadows: bool = True,
) -> View:
    """Ray-cast one image with its truth.

    Args:
        world: the world.
        cam: the camera.
        app: the appearance.
        billboards: transient occluders.
        aa: samples per pixel, 1 (pixel centre) or 5 (centre and four diagonals).
        shadows: cast shadow rays towards the sun.

    Returns:
        The view: colour image and truth at pixel centres.
    """
    if aa not in _AA_OFFSETS:
        raise ValueError(f"aa must be one of {sorted(_AA_OFFSETS)}, got {aa}")
    H, W = cam.height, cam.width
    C = cam.centre
    boxes = screen_boxes(world, cam)
    cands = _grid_cands(boxes, H, W)
    jj, ii = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    acc = np.zeros((H * W, 3))
    light = np.asarray(app.sun_dir)
    amb = app.ambient * np.asarray(app.ambient_color)
    sun = app.sun_strength * np.asarray(app.sun_color)
    fx = cam.K[0, 0]
    truth = None
    for s, (du, dv) in enumerate(_AA_OFFSETS[aa]):
        d = cam.ray_dirs(jj + du, ii + dv).reshape(-1, 3)
        t, prim, n = cast(world, C, d, cands)
        tb = np.full(len(d), np.inf)
        kb = np.full(len(d), -1)
        sq = np.zeros((len(d), 2))
        for k, bb in enumerate(billboards):
            tk, sqk = bb.intersect(C, d)
            better = tk < tb
            tb[better], kb[better], sq[better] = tk[better], k, sqk[better]
        trans = tb < t
        if s == 0:
            truth = (
                world.part_of(prim).reshape(H, W),
                trans.reshape(H, W),
                np.where(np.isfinite(t), t, np.inf).astype(np.float32).reshape(H, W),
            )
        rad = np.zeros((len(d), 3))
        hit = np.flatnonzero(np.isfinite(t) & ~trans)
        if len(hit):
            dn = np.linalg.norm(d[hit], axis=1)
            p = C + t[hit, None] * d[hit]
            nn = n[hit]
            cos_i = np.abs(_dot3(nn, d[hit])) / dn
            footprint = t[hit] * dn / fx / np.maximum(cos_i, 0.1)
            alb = _lin(surface_albedo(world, prim[hit], p, footprint))
            ndl = np.clip(_dot3(nn, light), 0.0, None)
            if shadows and light[2] > 0.02:
                lit = np.flatnonzero(ndl > 0)
                sh = _shadowed(world, p[lit] + 1e-4 * nn[lit], light)
                ndl[lit[sh]] = 0.0
            rad[hit] = alb * (amb + ndl[:, None] * sun)
        bh = np.flatnonzero(trans)
        if len(bh):
            for k, bb in enumerate(billboards):
                sel = bh[kb[bh] == k]
                if not len(sel):
                    continue
                loc = sq[sel]
                pl = np.stack(
                    [loc[:, 0] * bb.half_w, np.zeros(len(sel)), loc[:, 1] * bb.half_h],
                    1,
                )
                fp = tb[sel] * np.linalg.norm(d[sel], axis=1) / fx
                alb = _lin(texture_albedo(bb.texture, pl, fp))
                nb = np.cross(bb.right, bb.up)
                ndl = abs(float(np.dot(nb, light)))
                rad[sel] = alb * (amb + ndl * sun)
        sky = np.flatnonzero(~np.isfinite(t) & ~trans)
        if len(sky):
            rad[sky] = _sky(app, d[sky])
        acc += rad
    acc /= len(_AA_OFFSETS[aa])
    part_id, transient, depth = truth
    return View(develop(acc.reshape(H, W, 3), app), part_id, transient, depth)


def render_truth(world: World, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Part ids [H, W] int16 and depth [H, W] float64 at pixel centres (no shading)."""
    H, W = cam.height, cam.width
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d = cam.ray_dirs(jj, ii).reshape(-1, 3)
    t, prim, _ = cast(world, cam.centre, d, _grid_cands(screen_boxes(world, cam), H, W))
    return world.part_of(prim).reshape(H, W), t.reshape(H, W)


# ------------------------------------------------------------------ swatches --


def render_swatch(desc: dict, size: int = 224) -> np.ndarray:
    """The canonical swatch of a vocabulary entry, as the text side sees it.

    Args:
        desc: {"kind": "texture", "texture": Texture dict, "origin": [3],
            "e1": [3], "e2": [3], "extent": float, "light": float, "gamma": float,
            "render_px": int} (a square patch of the solid texture on the plane
            origin + a e1 + b e2 under a constant linear light factor, rendered at
            render_px and resized as a crop would be), {"kind": "sky",
            "zenith": rgb, "horizon": rgb} (a vertical gradient), or
            {"kind": "landmark", ...} (`landmark_swatch`).
        size: output side in pixels.

    Returns:
        [size, size, 3] float32 RGB in [1/255, 1] (never black: black means
        "outside the mask" to the encoder; a landmark swatch is black outside
        the landmark, as a segment crop is).
    """
    import cv2

    kind = desc.get("kind")
    if kind == "sky":
        w = np.linspace(1.0, 0.0, size)[:, None, None]
        img = np.asarray(desc["horizon"]) * (1 - w) + np.asarray(desc["zenith"]) * w
        img = np.broadcast_to(img, (size, size, 3))
    elif kind == "texture":
        tex = Texture.from_dict(desc["texture"])
        n = int(desc.get("render_px", 64))
        ext = float(desc["extent"])
        o = np.asarray(desc["origin"], float)
        e1, e2 = np.asarray(desc["e1"], float), np.asarray(desc["e2"], float)
        acc = np.zeros((n * n, 3))
        offs = _AA_OFFSETS[5]
        for du, dv in offs:
            a = (np.arange(n) + du) / n - 0.5
            b = (np.arange(n) + dv) / n - 0.5
            A, B = np.meshgrid(a, b)
            p = o + ext * (A.reshape(-1, 1) * e1 + B.reshape(-1, 1) * e2)
            acc += _lin(texture_albedo(tex, p, ext / n))
        rad = acc / len(offs) * float(desc.get("light", neutral_light()))
        disp = np.clip(rad, 0, 1) ** (1.0 / float(desc.get("gamma", 2.2)))
        disp = np.floor(disp * 255 + 0.5) / 255.0  # 8-bit, as a photo
        img = cv2.resize(
            disp.reshape(n, n, 3).astype(np.float32),
            (size, size),
            interpolation=cv2.INTER_LINEAR,
        )
    elif kind == "landmark":
        return landmark_swatch(desc, size)
    else:
        raise ValueError(
            f"unknown swatch kind {kind!r}; expected 'texture', 'sky' or 'landmark'"
        )
    return np.clip(np.asarray(img, np.float32), 1.0 / 255.0, 1.0)


def landmark_camera(world: World, azimuth: float, px: int) -> Camera:
    """A canonical square view of the whole landmark (a style's viewpoint).

    From `azimuth` degrees around the front (0 = the front, as `sample_camera`
    measures it), 2.6 bounding radii from the centre, at the eye height of a
    typical photo (1.2 + 0.3 centre height), looking at the centre, with the
    bounding sphere filling the frame.
    """
    eye = _orbit_eye(world, azimuth, 2.6 * world.radius, 1.2 + 0.3 * world.center[2])
    f = _focal_to_fill(world, eye, 1.0, px)
    K = np.array([[f, 0.0, px / 2], [0.0, f, px / 2], [0.0, 0.0, 1.0]])
    return Camera(K, look_at(eye, np.asarray(world.center, float)), int(px), int(px))


def landmark_swatch(desc: dict, size: int = 224) -> np.ndarray:
    """The whole landmark photographed under neutral daylight, as a segment crop.

    Args:
        desc: {"kind": "landmark", "world": World dict, "azimuth": degrees,
            "px": rendered side} (`landmark_camera`; one sample per pixel,
            with shadows).
        size: output side.

    Returns:
        [size, size, 3] float32: the landmark's pixels (sky and ground black,
        i.e. outside the mask) cropped and padded exactly as `prepare_crop`
        crops a segment; pixels inside the landmark are never black.
    """
    from ptovs.crop import prepare_crop

    world = World.from_dict(desc["world"])
    cam = landmark_camera(world, float(desc["azimuth"]), int(desc.get("px", 128)))
    view = render(world, cam, neutral_appearance(), aa=1)
    inside = view.part_id >= 0
    if not inside.any():
        raise ValueError("landmark swatch: the landmark is not in view")
    img = np.maximum(view.image.astype(np.float32) / 255.0, 1.0 / 255.0)
    return prepare_crop(img, inside, size)


def part_swatch(world: World, part: Part, render_px: int) -> dict:
    """Swatch description of a part: its front-facing texture under neutral light."""
    prims = [q for q in world.prims if q.part == part.id]
    lo = np.min([q.lo for q in prims], axis=0)
    hi = np.max([q.hi for q in prims], axis=0)
    c = (lo + hi) / 2
    origin = [float(c[0]), float(lo[1]), float(c[2])]
    return {
        "kind": "texture",
        "texture": part.texture.to_dict(),
        "origin": origin,
        "e1": [1.0, 0.0, 0.0],
        "e2": [0.0, 0.0, -1.0],
        "extent": float(part.size),
        "light": round(neutral_light(), 9),
        "gamma": 2.2,
        "render_px": int(render_px),
    }


def sky_swatch() -> dict:
    """Swatch description of the neutral (daylight) sky."""
    app = neutral_appearance()
    return {
        "kind": "sky",
        "zenith": list(app.sky_zenith),
        "horizon": list(app.sky_horizon),
    }
