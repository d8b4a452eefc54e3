"""Compiled CPU rasterizer, csrc/project.cpp + composite.cpp.

The maths: docs/rasterizer.md §1–§4 and §9.

The kernel is built and loaded on first use by `_cpu_build`; its OpenMP team
(`threads()`) is set in `_team`.

Entry points:
- `available()`: builds (once) and reports whether the kernel can be used.
- `project(...)`: `_common.project` with a compiled forward and hand-written backward
  (gradients to means, quats, scales and opacities; a pose that requires a gradient
  falls back to `_common.project`).
- `intersect(...)`: `_common.intersect`, compiled, bit-identical.
- `composite(...)`: autograd forward/backward with the reference's signature.
- `build_blend_weights(...)`, `apply(...)`, `spmm(...)`, `blend_weights_coo(...)`:
  the frozen-geometry fast path (docs/rasterizer.md §9): F = W f and its backward W^T g.
"""

from __future__ import annotations

import ctypes

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from ptovs.raster import _common
from ptovs.raster._common import FOV_MARGIN, Camera, Gaussians, Isect, Projected
from ptovs.raster._cpu_build import load
from ptovs.raster._team import threads


def available() -> bool:
    """Whether the compiled CPU kernel can be used (builds it on the first call)."""
    return load() is not None


def _lib_or_raise() -> ctypes.CDLL:
    lib = load()
    if lib is None:
        raise RuntimeError("the compiled CPU rasterizer is unavailable (see the log)")
    return lib


def _ptr(t: Tensor | None) -> int | None:
    return None if t is None else t.data_ptr()


def _f32(name: str, t: Tensor) -> Tensor:
    if t.dtype != torch.float32 or t.device.type != "cpu":
        raise ValueError(
            f"{name}: expected a float32 CPU tensor, got {t.dtype} {t.device}"
        )
    return t.detach().contiguous()


def _check_isect(
    isect: Isect, n: int, width: int, height: int
) -> tuple[Tensor, Tensor]:
    tile = int(isect.tile)
    if tile < 1 or isect.tw != -(-width // tile) or isect.th != -(-height // tile):
        raise ValueError(
            f"isect grid {isect.tw}x{isect.th} (tile {tile}) does not cover "
            f"{width}x{height}"
        )
    offsets = isect.tile_offsets.to(torch.int32).contiguous()
    ids = isect.flatten_ids.to(torch.int32).contiguous()
    if offsets.shape != (isect.tw * isect.th + 1,):
        raise ValueError(f"tile_offsets: expected {isect.tw * isect.th + 1} entries")
    if offsets.numel() and (
        int(offsets[0]) != 0
        or int(offsets[-1]) > ids.numel()
        or bool((torch.diff(offsets) < 0).any())
    ):
        raise ValueError("tile_offsets must be non-decreasing from 0 to <= len(ids)")
    if ids.numel() and (int(ids.min()) < 0 or int(ids.max()) >= n):
        raise ValueError(f"flatten_ids out of range [0, {n})")
    return offsets, ids


def _check_geometry(means2d: Tensor, conics: Tensor, opacities: Tensor):
    m = _f32("means2d", means2d)
    c = _f32("conics", conics)
    o = _f32("opacities", opacities).reshape(-1)
    n = m.shape[0]
    if m.shape != (n, 2) or c.shape != (n, 3) or o.shape != (n,):
        raise ValueError(
            f"shapes: means2d {tuple(m.shape)}, conics {tuple(c.shape)}, "
            f"opacities {tuple(o.shape)}; expected [N, 2], [N, 3], [N]"
        )
    return m, c, o


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx, means2d, conics, opacities, colors, background, isect, width, height
    ):
        lib = _lib_or_raise()
        m, c, o = _check_geometry(means2d, conics, opacities)
        col = _f32("colors", colors)
        n, d = m.shape[0], col.shape[1] if col.dim() == 2 else 0
        if col.shape != (n, d) or d < 1:
            raise ValueError(f"colors: expected [N={n}, D>=1], got {tuple(col.shape)}")
        bg = None
        if background is not None:
            bg = _f32("background", background).reshape(-1)
            if bg.shape != (d,):
                raise ValueError(f"background: expected [{d}], got {tuple(bg.shape)}")
        offsets, ids = _check_isect(isect, n, width, height)
        nt = threads()
        image = torch.empty(height, width, d)
        alpha = torch.empty(height, width, 1)
        t_final = torch.empty(height, width)
        n_contrib = torch.empty(height, width, dtype=torch.int32)
        last = torch.empty(height, width, dtype=torch.int32)
        if width * height:
            rc = lib.ptovs_composite_fwd(
                *map(_ptr, (m, c, o, col, bg)), n, d, _ptr(offsets), _ptr(ids),
                isect.tw, isect.th, isect.tile, width, height,
                *map(_ptr, (image, alpha, t_final, n_contrib, last)), nt,
            )  # fmt: skip
            if rc:
                raise MemoryError(f"ptovs_composite_fwd failed ({rc})")
        ctx.save_for_backward(m, c, o, col, bg, offsets, ids, t_final, last)
        ctx.meta = (isect.tw, isect.th, isect.tile, width, height)
        ctx.opacity_shape = opacities.shape
        ctx.mark_non_differentiable(n_contrib)
        return image, alpha, n_contrib

    @staticmethod
    @once_differentiable
    def backward(ctx, v_image, v_alpha, _v_n_contrib):
        lib = _lib_or_raise()
        m, c, o, col, bg, offsets, ids, t_final, last = ctx.saved_tensors
        tw, th, tile, width, height = ctx.meta
        n, d = col.shape
        v_image = (
            torch.zeros(height, width, d)
            if v_image is None
            else v_image.to(torch.float32).contiguous()
        )
        v_alpha = (
            torch.zeros(height, width)
            if v_alpha is None
            else v_alpha.to(torch.float32).reshape(height, width).contiguous()
        )
        nt = threads()
        # The kernel's fixed gradient slices (not one per thread, so the sums do not
        # follow the thread count), zeroed by the kernel and summed into grads[0].
        grads = torch.empty(lib.ptovs_grad_slices(), n, 6 + d)
        if width * height and n:
            rc = lib.ptovs_composite_bwd(
                *map(_ptr, (m, c, o, col, bg)), n, d, _ptr(offsets), _ptr(ids),
                tw, th, tile, width, height,
                *map(_ptr, (t_final, last, v_image, v_alpha, grads)), nt,
            )  # fmt: skip
            if rc:
                raise MemoryError(f"ptovs_composite_bwd failed ({rc})")
        else:
            grads.zero_()
        g = grads[0]
        # The kernel sums v_sigma * (dx, dy, dx^2, dx dy, dy^2) per Gaussian; with
        # sigma = a dx^2 / 2 + b dx dy + c dy^2 / 2 and d = mean2d - pixel:
        # A culled Gaussian may carry an inf conic (overflowing scale) and zero sums:
        # 0 * inf would be NaN. Contributing Gaussians always have finite conics.
        a, b, cc = torch.where(torch.isfinite(c), c, 0.0).unbind(1)
        v_means2d = torch.stack(
            (a * g[:, 0] + b * g[:, 1], b * g[:, 0] + cc * g[:, 1]), 1
        )
        v_conics = torch.stack((0.5 * g[:, 2], g[:, 3], 0.5 * g[:, 4]), 1)
        v_opac = g[:, 5].reshape(ctx.opacity_shape)
        v_bg = None
        if bg is not None and ctx.needs_input_grad[4]:
            v_bg = (t_final[..., None] * v_image).sum((0, 1))  # d C / d bg = T_final
        return v_means2d, v_conics, v_opac, g[:, 6:], v_bg, None, None, None


def composite(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, D]
    background: Tensor | None,  # [D]
    isect: Isect,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor, Tensor]:
    """Alpha-composite splats front to back with the compiled kernel, differentiable.

    Same contract as `_reference.composite`: gradients flow to means2d, conics,
    opacities, colors and background (all float32 on the CPU).

    Args:
        means2d: splat centres in pixels.
        conics: (a, b, c) inverse 2D covariances.
        opacities: splat opacities.
        colors: values to blend, any D >= 1.
        background: added as T_final * background; None for no background.
        isect: tile lists from `intersect`.
        width: image width.
        height: image height.

    Returns:
        image [H, W, D], alpha [H, W, 1] (1 - T_final) and n_contrib [H, W] int32,
        the number of composited Gaussians per pixel.
    """
    image, alpha, n_contrib = _Composite.apply(
        means2d, conics, opacities, colors, background, isect, width, height
    )
    return image, alpha, n_contrib


# Projection and tile binning (docs/rasterizer.md §1, §2), mirroring `_common`.


def _camera_params(cam: Camera, near: float, far: float) -> Tensor:
    """float64 [22]: R_cw (row-major), t, fx, fy, cx, cy, the four clamp limits, near, far.

    Computed exactly as `_common.project` does: the pose rounded to float32 (the
    Gaussians' dtype), the intrinsics and limits in float64.
    """
    view = cam.cam_from_world.detach().to(torch.float32).to(torch.float64).cpu()
    K = cam.K.detach().to(torch.float64).cpu()
    fx, fy, cx, cy = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
    width, height = cam.width, cam.height
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lims = (
        (width - cx) / fx + FOV_MARGIN * tan_fovx,
        cx / fx + FOV_MARGIN * tan_fovx,
        (height - cy) / fy + FOV_MARGIN * tan_fovy,
        cy / fy + FOV_MARGIN * tan_fovy,
    )
    rest = torch.tensor((fx, fy, cx, cy, *lims, near, far), dtype=torch.float64)
    return torch.cat((view[:3, :3].reshape(-1), view[:3, 3], rest))


class _Project(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, params, width, height, antialias):
        lib = _lib_or_raise()
        m, q, s, o = (
            t.detach().contiguous() for t in (means, quats, scales, opacities)
        )
        n = m.shape[0]
        means2d = torch.empty(n, 2)
        conics = torch.empty(n, 3)
        opac = torch.empty(n)
        depths = torch.empty(n)
        radii = torch.empty(n, 2, dtype=torch.int32)
        if n:
            rc = lib.ptovs_project_fwd(
                *map(_ptr, (m, q, s, o)), n, _ptr(params), width, height,
                int(antialias), *map(_ptr, (means2d, conics, opac, depths, radii)),
                threads(),
            )  # fmt: skip
            if rc:
                raise RuntimeError(f"ptovs_project_fwd failed ({rc})")
        ctx.save_for_backward(m, q, s, o, params)
        ctx.meta = (width, height, int(antialias))
        ctx.mark_non_differentiable(radii)
        return means2d, conics, opac, depths, radii

    @staticmethod
    @once_differentiable
    def backward(ctx, v_means2d, v_conics, v_opac, v_depths, _v_radii):
        lib = _lib_or_raise()
        m, q, s, o, params = ctx.saved_tensors
        n = m.shape[0]
        grads = (
            torch.empty(n, 3),
            torch.empty(n, 4),
            torch.empty(n, 3),
            torch.empty(n),
        )
        ups = [
            None if v is None else v.to(torch.float32).contiguous()
            for v in (v_means2d, v_conics, v_opac, v_depths)
        ]
        if n:
            rc = lib.ptovs_project_bwd(
                *map(_ptr, (m, q, s, o)), n, _ptr(params), *ctx.meta,
                *map(_ptr, ups), *map(_ptr, grads), threads(),
            )  # fmt: skip
            if rc:
                raise RuntimeError(f"ptovs_project_bwd failed ({rc})")
        need = ctx.needs_input_grad
        return (*(g if need[k] else None for k, g in enumerate(grads)),) + (None,) * 4


def _compiled_ok(g: Gaussians, cam: Camera) -> bool:
    n = g.means.shape[0] if g.means.ndim == 2 else -1
    shapes = ((g.means, (n, 3)), (g.quats, (n, 4)), (g.scales, (n, 3)))
    return (
        all(
            t.dtype == torch.float32 and t.device.type == "cpu" and t.shape == shape
            for t, shape in (*shapes, (g.opacities, (n,)))
        )
        and not (torch.is_grad_enabled() and cam.cam_from_world.requires_grad)
        and load() is not None
    )


def project(
    g: Gaussians,
    cam: Camera,
    *,
    near: float = _common.NEAR,
    far: float = _common.FAR,
    antialias: bool = False,
    tile: int = 16,
) -> Projected:
    """`_common.project` with a compiled forward and a hand-written backward.

    Same maths, constants, culling and outputs (culled Gaussians included); values
    agree with the float32 torch graph to float32 rounding (the kernel works in
    float64 per Gaussian), radii exactly unless torch's own float32 rounding puts
    3.33 sqrt(c) within an ulp of an integer. Gradients flow to means, quats, scales
    and opacities; a Gaussian whose cotangents are all zero (a culled one in `render`)
    gets exactly zero. The camera gets no gradient: when its pose requires one, or the
    Gaussians are not float32 CPU tensors, this falls back to `_common.project`.

    Args:
        g: the Gaussians (N of them).
        cam: the camera.
        near: cull when z <= near.
        far: cull when z >= far.
        antialias: multiply opacities by the Mip-Splatting compensation.
        tile: accepted for a uniform signature; the radius rule ignores it.

    Returns:
        Projected splats: means2d [N, 2], conics [N, 3], opacities [N], depths [N],
        radii [N, 2] int32.
    """
    if not _compiled_ok(g, cam):
        return _common.project(
            g, cam, near=near, far=far, antialias=antialias, tile=tile
        )
    params = _camera_params(cam, near, far)
    means2d, conics, opac, depths, radii = _Project.apply(
        g.means, g.quats, g.scales, g.opacities, params, cam.width, cam.height,
        bool(antialias),
    )  # fmt: skip
    return Projected(
        means2d=means2d, conics=conics, opacities=opac, depths=depths, radii=radii
    )


@torch.no_grad()
def intersect(p: Projected, width: int, height: int, tile: int) -> Isect:
    """`_common.intersect`, compiled: bit-identical tile lists.

    Args:
        p: projected splats; radii (0, 0) are skipped.
        width: image width in pixels.
        height: image height in pixels.
        tile: tile edge in pixels.

    Returns:
        The tile lists: `tile_offsets` [n_tiles + 1] int32 and `flatten_ids` [M] int32.
    """
    lib = load()
    means2d, radii = p.means2d.detach(), p.radii
    n = means2d.shape[0]
    if (
        lib is None
        or means2d.dtype != torch.float32
        or means2d.device.type != "cpu"
        or means2d.shape != (n, 2)
        or radii.shape != (n, 2)
        or p.depths.shape != (n,)
    ):
        return _common.intersect(p, width, height, tile)
    tw, th = -(-width // tile), -(-height // tile)
    n_tiles = tw * th
    means2d = means2d.contiguous()
    radii = radii.to(torch.int32).contiguous()
    depths = p.depths.detach().to(torch.float32).contiguous()
    nt = max(1, min(threads(), n))
    boxes = torch.empty(n, 4, dtype=torch.int32)
    order = torch.empty(n, dtype=torch.int32)
    counts = torch.empty(nt, n_tiles, dtype=torch.int32)
    tile_offsets = torch.zeros(n_tiles + 1, dtype=torch.int32)
    sizes = torch.zeros(2, dtype=torch.int64)  # binned Gaussians, entries
    if n:
        rc = lib.ptovs_intersect_count(
            *map(_ptr, (means2d, radii, depths)), n, tw, th, tile,
            _ptr(boxes), _ptr(order), _ptr(sizes[0:]), _ptr(counts),
            _ptr(tile_offsets), _ptr(sizes[1:]), nt,
        )  # fmt: skip
        if rc == 3:
            raise ValueError("more tile entries than int32 offsets can index")
        if rc:
            raise MemoryError(f"ptovs_intersect_count failed ({rc})")
    n_valid, total = (int(x) for x in sizes)
    flatten_ids = torch.empty(total, dtype=torch.int32)
    if total:
        lib.ptovs_intersect_fill(
            n_valid, _ptr(order), _ptr(boxes), _ptr(counts), tw, th,
            _ptr(flatten_ids), nt,
        )  # fmt: skip
    return Isect(
        tile_offsets=tile_offsets, flatten_ids=flatten_ids, tw=tw, th=th, tile=tile
    )


# Frozen geometry (docs/rasterizer.md §9): W [H*W, N] holds alpha_i T_i per composited
# pair.

Csr = tuple[
    Tensor, Tensor, Tensor
]  # (indptr int32 [rows + 1], indices int32, values f32)


@torch.no_grad()
def _blend_rows(means2d, conics, opacities, isect, width, height) -> tuple[Csr, int]:
    lib = _lib_or_raise()
    m, c, o = _check_geometry(means2d, conics, opacities)
    n = m.shape[0]
    offsets, ids = _check_isect(isect, n, width, height)
    nt = threads()
    args = (isect.tw, isect.th, isect.tile, width, height)
    counts = torch.zeros(width * height, dtype=torch.int32)
    rowptr = torch.zeros(width * height + 1, dtype=torch.int64)
    if width * height:
        geo = (*map(_ptr, (m, c, o)), n, _ptr(offsets), _ptr(ids), *args)
        rc = lib.ptovs_blend_weights(*geo, _ptr(counts), None, None, None, nt)
        if rc:
            raise MemoryError(f"ptovs_blend_weights failed ({rc})")
        torch.cumsum(counts, 0, out=rowptr[1:])
    nnz = int(rowptr[-1])
    if nnz >= 2**31:
        raise ValueError(f"{nnz} blend weights exceed int32 CSR indices")
    indices = torch.empty(nnz, dtype=torch.int32)
    values = torch.empty(nnz, dtype=torch.float32)
    if nnz:
        rc = lib.ptovs_blend_weights(
            *geo, None, _ptr(rowptr), _ptr(indices), _ptr(values), nt
        )
        if rc:
            raise MemoryError(f"ptovs_blend_weights failed ({rc})")
    return (rowptr.to(torch.int32), indices, values), n


@torch.no_grad()
def csr_transpose(w: Csr, n_cols: int) -> Csr:
    """Transpose a CSR matrix [rows, n_cols]; each output row is sorted by column.

    Args:
        w: (indptr int32 [rows + 1], indices int32 [nnz], values f32 [nnz]).
        n_cols: number of columns of `w`.

    Returns:
        The CSR triple of the [n_cols, rows] transpose.
    """
    lib = _lib_or_raise()
    indptr, indices, values = (t.contiguous() for t in w)
    rows, nnz = indptr.numel() - 1, indices.numel()
    nt = threads()
    t_indptr = torch.zeros(n_cols + 1, dtype=torch.int32)
    t_indices = torch.empty(nnz, dtype=torch.int32)
    t_values = torch.empty(nnz, dtype=torch.float32)
    if nnz:
        scratch = torch.empty(nt, n_cols, dtype=torch.int32)
        rc = lib.ptovs_csr_transpose(
            *map(_ptr, (indptr, indices, values)), rows, n_cols,
            *map(_ptr, (t_indptr, t_indices, t_values, scratch)), nt,
        )  # fmt: skip
        if rc:
            raise MemoryError(f"ptovs_csr_transpose failed ({rc})")
    return t_indptr, t_indices, t_values


def build_blend_weights(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    isect: Isect,
    width: int,
    height: int,
) -> tuple[Csr, Csr]:
    """Blend-weight matrices of a frozen geometry and view (docs/rasterizer.md §9).

    W [H*W, N] holds w = alpha_i T_i for every composited (pixel, Gaussian) pair, with
    the forward's skip and stop rules, so that `W @ f` equals `composite(..., f, None,
    ...)[0]` flattened. Rows list their Gaussians front to back; rows of W^T are sorted
    by pixel. Built straight in CSR order by the kernel (no generic sort).

    Args:
        means2d, conics, opacities: the splats (gradients are not tracked).
        isect: tile lists from `intersect`.
        width, height: image size.

    Returns:
        (W, WT): CSR triples (indptr int32, indices int32, values float32) of
        W [H*W, N] and W^T [N, H*W].
    """
    w, n = _blend_rows(means2d, conics, opacities, isect, width, height)
    return w, csr_transpose(w, n)


def blend_weights_coo(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    isect: Isect,
    width: int,
    height: int,
) -> tuple[Tensor, Tensor, Tensor]:
    """The composited pairs as COO, sorted by pixel, front to back within a pixel.

    Returns:
        pixel_idx int64 [nnz] (y * W + x), gaussian_id int32 [nnz], weight f32 [nnz]
        (alpha_i T_i).
    """
    (indptr, indices, values), _ = _blend_rows(
        means2d, conics, opacities, isect, width, height
    )
    counts = torch.diff(indptr).to(torch.int64)
    pixel_idx = torch.repeat_interleave(torch.arange(width * height), counts)
    return pixel_idx, indices, values


def spmm(indptr: Tensor, indices: Tensor, values: Tensor, f: Tensor) -> Tensor:
    """CSR [rows, cols] @ f [cols, D] -> [rows, D], OpenMP over rows (no autograd).

    Args:
        indptr: int32 [rows + 1].
        indices: int32 [nnz] column ids (< f.shape[0]; not checked).
        values: float32 [nnz].
        f: float32 [cols, D].

    Returns:
        float32 [rows, D].
    """
    lib = _lib_or_raise()
    if indptr.dtype != torch.int32 or indices.dtype != torch.int32:
        raise ValueError("spmm: indptr and indices must be int32")
    f = _f32("f", f)
    if f.dim() != 2:
        raise ValueError(f"spmm: f must be [cols, D], got {tuple(f.shape)}")
    rows, d = indptr.numel() - 1, f.shape[1]
    out = torch.empty(rows, d)
    if rows > 0 and d > 0:
        indptr, indices, values = (t.contiguous() for t in (indptr, indices, values))
        rc = lib.ptovs_spmm(
            *map(_ptr, (indptr, indices, values)), rows, _ptr(f), d, _ptr(out),
            threads(),
        )  # fmt: skip
        if rc:
            raise MemoryError(f"ptovs_spmm failed ({rc})")
    return out


class _BlendApply(torch.autograd.Function):
    @staticmethod
    def forward(ctx, f, w_indptr, w_indices, w_values, t_indptr, t_indices, t_values):
        ctx.save_for_backward(t_indptr, t_indices, t_values)
        return spmm(w_indptr, w_indices, w_values, f)

    @staticmethod
    @once_differentiable
    def backward(ctx, g):
        t_indptr, t_indices, t_values = ctx.saved_tensors
        return (
            spmm(t_indptr, t_indices, t_values, g),
            None,
            None,
            None,
            None,
            None,
            None,
        )


def apply(w: Csr, wt: Csr, f: Tensor) -> Tensor:
    """F = W f, differentiable in f (its backward is W^T g).

    Args:
        w: CSR triple of W [rows, N].
        wt: CSR triple of W^T [N, rows] (from `build_blend_weights`).
        f: float32 [N, D] per-Gaussian values.

    Returns:
        float32 [rows, D]; reshape to [H, W, D] for an image.
    """
    if f.shape[0] != wt[0].numel() - 1:
        raise ValueError(f"f has {f.shape[0]} rows; W has {wt[0].numel() - 1} columns")
    return _BlendApply.apply(f, *w, *wt)
