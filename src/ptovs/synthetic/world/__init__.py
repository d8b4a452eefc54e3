"""Procedural landmark world: primitives, textures, appearance, ray casting.

The synthetic test bed of docs/synthetic.md. A landmark is a union of analytic
primitives (convex polytopes: boxes, triangular prisms and thin panels; vertical
cylinders and cones; spheres clipped into domes), each belonging to a named part
with a solid procedural texture. Around it: a ground plane (z = 0) and a sky.
Images are rendered by exact, vectorised numpy ray casting, never by the Gaussian
rasterizer, so the ground truth is independent of the code under test.

Frames: the world is z up and the landmark's front faces -y. A camera looks down
+z with x right and y down; pixel (i, j) has its centre at (u, v) = (j + .5, i + .5)
and u = fx * x / z + cx. A primary ray is `C + t * d` with d = R^T K^-1 [u, v, 1],
so its parameter t is the camera-space depth z of the hit.

A package of the old module's sections, each a module, in import order (each
imports only the ones above it):

- `constants`: hit codes, pattern/sky/filter/shape names, AA offsets, colour transforms
- `textures`: solid procedural textures and their albedo
- `primitives`: analytic primitives and their exact ray intersections
- `landmark`: `Part`, `World`, `build_world` (a landmark from a generator's state)
- `cameras`: pinhole cameras, look-at, orbits, photo viewpoints
- `appearance`: per-photo sky, sun, exposure, tint and film filter
- `transients`: occluders (people, umbrellas, vehicles, signs) as billboards
- `casting`: primary and shadow rays, screen boxes of the primitives
- `rendering`: a photo and its per-pixel truth by exact ray casting
- `swatches`: what the stand-in encoder sees of a texture, a part or the landmark

This face re-exports every public name, so `from ptovs.synthetic.world import render`
works as before.
"""

from __future__ import annotations

from ptovs.synthetic.world.appearance import (
    Appearance,
    neutral_appearance,
    neutral_light,
    sample_appearance,
)
from ptovs.synthetic.world.cameras import (
    Camera,
    focal_to_fill,
    look_at,
    orbit_eye,
    sample_camera,
)
from ptovs.synthetic.world.casting import (
    cast,
    grid_candidates,
    in_shadow,
    screen_boxes,
)
from ptovs.synthetic.world.constants import (
    AA_OFFSETS,
    EPS,
    FILTERS,
    GROUND,
    LUMA,
    NO_HIT,
    PATTERNS,
    SEPIA,
    SHAPES,
    SKIES,
)
from ptovs.synthetic.world.landmark import (
    DISTRACTORS,
    PART_QUERIES,
    Part,
    World,
    build_world,
    random_texture,
)
from ptovs.synthetic.world.primitives import (
    Primitive,
    dot3,
)
from ptovs.synthetic.world.rendering import (
    View,
    develop,
    render,
    render_truth,
    surface_albedo,
    to_linear,
)
from ptovs.synthetic.world.swatches import (
    landmark_camera,
    landmark_swatch,
    part_swatch,
    render_swatch,
    sky_swatch,
)
from ptovs.synthetic.world.textures import (
    Texture,
    pattern_value,
    smooth_step,
    texture_albedo,
)
from ptovs.synthetic.world.transients import (
    Billboard,
    sample_transients,
)

__all__ = [
    "AA_OFFSETS",
    "Appearance",
    "Billboard",
    "Camera",
    "DISTRACTORS",
    "EPS",
    "FILTERS",
    "GROUND",
    "LUMA",
    "NO_HIT",
    "PART_QUERIES",
    "PATTERNS",
    "Part",
    "Primitive",
    "SEPIA",
    "SHAPES",
    "SKIES",
    "Texture",
    "View",
    "World",
    "build_world",
    "cast",
    "develop",
    "dot3",
    "focal_to_fill",
    "grid_candidates",
    "in_shadow",
    "landmark_camera",
    "landmark_swatch",
    "look_at",
    "neutral_appearance",
    "neutral_light",
    "orbit_eye",
    "part_swatch",
    "pattern_value",
    "random_texture",
    "render",
    "render_swatch",
    "render_truth",
    "sample_appearance",
    "sample_camera",
    "sample_transients",
    "screen_boxes",
    "sky_swatch",
    "smooth_step",
    "surface_albedo",
    "texture_albedo",
    "to_linear",
]
