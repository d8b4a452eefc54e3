"""Transient occluders (people, umbrellas, vehicles, signs) as textured
billboards placed in front of the landmark.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ptovs.synthetic.world.cameras import Camera
from ptovs.synthetic.world.constants import EPS, SHAPES
from ptovs.synthetic.world.landmark import World, random_texture
from ptovs.synthetic.world.primitives import dot3
from ptovs.synthetic.world.textures import Texture


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
            t = dot3(c - o2, n) / dot3(d, n)
        p = o2 + t[:, None] * d - c
        s = dot3(p, r) / self.half_w
        q = dot3(p, u) / self.half_h
        inside = _silhouette(self.shape, s, q) & (t > EPS)
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
