"""The analytic primitives a landmark is made of (convex polytopes, vertical
cylinders and cones, clipped spheres) and their exact ray intersections.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ptovs.synthetic.world.constants import EPS


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


def dot3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
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
    hit = (t_enter <= t_exit) & ~outside & (t_enter > EPS)
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
    ts = np.stack([np.where(ok & (t > EPS), t, np.inf) for t, ok in cands])
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
    r1, r2 = _quadratic_roots(dot3(d, d), 2.0 * dot3(oc, d), dot3(oc, oc) - r * r)
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
