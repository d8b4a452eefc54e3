"""Pinhole cameras around a landmark: sampling photo viewpoints, look-at, orbits."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ptovs.synthetic.world.landmark import World


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

    def scaled(self, scale: int) -> Camera:
        """The same view with `scale` times the pixels on each side."""
        if scale == 1:
            return self
        K = self.K.copy()
        K[:2] *= scale
        return Camera(K, self.cam_from_world, self.width * scale, self.height * scale)

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


def orbit_eye(world: World, azimuth: float, dist: float, height: float) -> np.ndarray:
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


def focal_to_fill(world: World, eye: np.ndarray, fill: float, side: int) -> float:
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
    eye = orbit_eye(world, az, dist, height)
    close = (not frontal) and rng.random() < 0.15
    target = world.center + rng.normal(0.0, (0.3 if close else 0.12) * R, 3)
    target[2] = max(target[2], 0.5)
    roll = math.radians(rng.normal(0.0, 2.0))
    L = int(rng.integers(long_side[0], long_side[1] + 1))
    aspect = float(rng.choice([4 / 3, 3 / 2, 16 / 9, 1.0, 5 / 4]))
    S = max(8, round(L / aspect))
    w, h = (S, L) if rng.random() < 0.3 else (L, S)
    fill = rng.uniform(1.5, 2.2) if close else rng.uniform(0.8, 1.35)
    f = focal_to_fill(world, eye, fill, min(w, h))
    K = np.array([[f, 0.0, w / 2], [0.0, f, h / 2], [0.0, 0.0, 1.0]])
    return Camera(K, look_at(eye, target, roll), int(w), int(h))
