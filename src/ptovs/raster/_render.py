"""`render`: validate the inputs once, project and bin the splats, composite."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ptovs.raster._backends import BACKENDS, cpu_module, resolve_backend
from ptovs.raster._common import (
    FAR,
    NEAR,
    TILE_SIZES,
    Camera,
    Gaussians,
    Isect,
    Projected,
    intersect,
    project,
)


@dataclass
class RenderOutput:
    """What `render` returns."""

    image: Tensor  # [H, W, D] sum_i c_i alpha_i T_i (+ T_final * background)
    alpha: Tensor  # [H, W, 1] 1 - T_final
    depth: Tensor | None  # [H, W, 1] sum_i z_i alpha_i T_i, unnormalised, no bg
    radii: Tensor  # [N, 2] int32, (0, 0) for culled Gaussians
    n_contrib: Tensor | None  # [H, W] int32 composited Gaussians per pixel
    means2d: Tensor | None = None  # [N, 2] projected centres; `.retain_grad()` on
    # it before backward gives the screen-space gradients that densification uses


# --- validation -------------------------------------------------------------


def _check_tensor(
    name: str, x: Any, shape: tuple[int | None, ...], dtype: torch.dtype | None
) -> None:
    if not isinstance(x, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    if x.ndim != len(shape) or any(
        s is not None and s != d for s, d in zip(shape, x.shape, strict=True)
    ):
        want = ", ".join("*" if s is None else str(s) for s in shape)
        raise ValueError(f"{name} must have shape [{want}], got {list(x.shape)}")
    if dtype is not None and x.dtype != dtype:
        raise ValueError(f"{name} must be {dtype} like means, got {x.dtype}")
    # x * 0 is NaN exactly where x is NaN or +-Inf, and its sum is one cheap
    # reduction (about 10x faster than isfinite().all() on 1.2 M values)
    with torch.no_grad():
        bad = x.numel() > 0 and bool(torch.isnan((x.detach() * 0).sum()))
    if bad:
        n_bad = int((~torch.isfinite(x.detach())).sum())
        raise ValueError(f"{name} contains NaN or Inf ({n_bad} of {x.numel()} values)")


def validate(
    gaussians: Gaussians,
    camera: Camera,
    colors: Tensor | None,
    background: Tensor | None,
    tile: int,
    near: float,
    far: float,
    backend: str,
) -> None:
    if not isinstance(gaussians, Gaussians):
        raise ValueError(
            f"gaussians must be a Gaussians, got {type(gaussians).__name__}"
        )
    if not isinstance(camera, Camera):
        raise ValueError(f"camera must be a Camera, got {type(camera).__name__}")
    means = gaussians.means
    _check_tensor("means", means, (None, 3), None)
    if means.dtype not in (torch.float32, torch.float64):
        raise ValueError(f"means must be float32 or float64, got {means.dtype}")
    n, dtype, device = means.shape[0], means.dtype, means.device
    _check_tensor("quats", gaussians.quats, (n, 4), dtype)
    _check_tensor("scales", gaussians.scales, (n, 3), dtype)
    _check_tensor("opacities", gaussians.opacities, (n,), dtype)
    tensors = {
        "quats": gaussians.quats,
        "scales": gaussians.scales,
        "opacities": gaussians.opacities,
    }
    if colors is not None:
        _check_tensor("colors", colors, (n, None), dtype)
        if colors.shape[1] < 1:
            raise ValueError("colors must have at least one channel (D >= 1)")
        tensors["colors"] = colors
        if background is not None:
            _check_tensor("background", background, (colors.shape[1],), dtype)
            tensors["background"] = background
    for name, x in tensors.items():
        if x.device != device:
            raise ValueError(f"{name} is on {x.device}, means on {device}")
    if n and bool((gaussians.scales < 0).any()):
        raise ValueError("scales must be >= 0 (activated)")
    if n and bool(((gaussians.opacities < 0) | (gaussians.opacities > 1)).any()):
        raise ValueError("opacities must lie in [0, 1] (activated)")

    _check_tensor("camera.cam_from_world", camera.cam_from_world, (4, 4), None)
    _check_tensor("camera.K", camera.K, (3, 3), None)
    if not (camera.K[0, 0] > 0 and camera.K[1, 1] > 0):
        raise ValueError("camera.K must have positive focal lengths fx, fy")
    for name in ("width", "height"):
        value = getattr(camera, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"camera.{name} must be an int >= 1, got {value!r}")
    if tile not in TILE_SIZES:
        raise ValueError(f"tile must be one of {TILE_SIZES}, got {tile!r}")
    if not (0 <= near < far) or math.isnan(far):
        raise ValueError(
            f"near and far must satisfy 0 <= near < far, got {near}, {far}"
        )
    if backend != "auto" and backend not in BACKENDS:
        raise ValueError(
            f"backend must be 'auto' or one of {sorted(BACKENDS)}, got {backend!r}"
        )


# --- rendering --------------------------------------------------------------


def project_and_bin(
    gaussians: Gaussians,
    camera: Camera,
    tile: int,
    near: float,
    far: float,
    antialias: bool,
    backend: str,
) -> tuple[Projected, Isect]:
    # The cpu backend projects and bins in its compiled kernel (no camera gradients:
    # `_cpu.project` falls back to `_common.project` when the pose requires one).
    mod = cpu_module() if backend == "cpu" else None
    proj, isect = (project, intersect) if mod is None else (mod.project, mod.intersect)
    projected = proj(
        gaussians, camera, near=near, far=far, antialias=antialias, tile=tile
    )
    return projected, isect(projected, camera.width, camera.height, tile)


def render(
    gaussians: Gaussians,
    camera: Camera,
    colors: Tensor,  # [N, D]
    *,
    background: Tensor | None = None,  # [D]
    backend: str = "auto",
    tile: int = 16,
    near: float = NEAR,
    far: float = FAR,
    antialias: bool = False,
    depth: bool = True,
) -> RenderOutput:
    """Differentiably rasterize Gaussians with D channels (docs/rasterizer.md §1–§4).

    Gradients flow to means, quats, scales, opacities, colors and background. Every
    backend gives the same result up to float rounding.

    Args:
        gaussians: N Gaussians (float32 or float64, all tensors alike).
        camera: the view; its tensors are cast to the Gaussians' dtype and device.
        colors: what is splatted: RGB, features, anything [N, D] (D >= 1).
        background: [D] added as T_final * background; None for none (features).
        backend: "auto" ("cpu" for float32 CPU tensors when compiled, else "torch"),
            "torch" or "cpu" (falls back to "torch" with a warning when unavailable).
        tile: tile edge in pixels, one of 4, 8, 16, 32; the image does not depend on it.
        near: cull Gaussians with camera z <= near.
        far: cull Gaussians with camera z >= far.
        antialias: Mip-Splatting opacity compensation (off in Inria and LangSplat).
        depth: also composite the camera z (one more channel, no background).

    Returns:
        RenderOutput with image [H, W, D], alpha [H, W, 1], depth [H, W, 1] or None,
        radii [N, 2] int32 and n_contrib [H, W] int32.
    """
    validate(gaussians, camera, colors, background, tile, near, far, backend)
    name = resolve_backend(backend, colors.dtype, colors.device)
    composite = BACKENDS[name]()
    projected, isect = project_and_bin(
        gaussians, camera, tile, near, far, antialias, name
    )

    values, bg = colors, background
    if depth:  # depth rides along as one more channel with a zero background
        values = torch.cat((colors, projected.depths[:, None]), 1)
        if background is not None:
            bg = torch.cat((background, background.new_zeros(1)))
    image, alpha, n_contrib = composite(
        projected.means2d,
        projected.conics,
        projected.opacities,
        values,
        bg,
        isect,
        camera.width,
        camera.height,
    )
    out_depth = None
    if depth:
        image, out_depth = image[..., :-1], image[..., -1:]
    return RenderOutput(
        image=image,
        alpha=alpha,
        depth=out_depth,
        radii=projected.radii,
        n_contrib=n_contrib,
        means2d=projected.means2d,
    )
