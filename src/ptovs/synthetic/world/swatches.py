"""Swatches: what the stand-in encoder sees of a texture, a part or the whole
landmark, rendered under neutral light.
"""

from __future__ import annotations

import numpy as np

from ptovs.synthetic.world.appearance import neutral_appearance, neutral_light
from ptovs.synthetic.world.cameras import Camera, focal_to_fill, look_at, orbit_eye
from ptovs.synthetic.world.constants import AA_OFFSETS
from ptovs.synthetic.world.landmark import Part, World
from ptovs.synthetic.world.rendering import render, to_linear
from ptovs.synthetic.world.textures import Texture, texture_albedo


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
        offs = AA_OFFSETS[5]
        for du, dv in offs:
            a = (np.arange(n) + du) / n - 0.5
            b = (np.arange(n) + dv) / n - 0.5
            A, B = np.meshgrid(a, b)
            p = o + ext * (A.reshape(-1, 1) * e1 + B.reshape(-1, 1) * e2)
            acc += to_linear(texture_albedo(tex, p, ext / n))
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
    eye = orbit_eye(world, azimuth, 2.6 * world.radius, 1.2 + 0.3 * world.center[2])
    f = focal_to_fill(world, eye, 1.0, px)
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
