"""Compiled CPU compositing, csrc/composite.cpp (RASTERIZER.md §3, §4 and §9).

The kernel is built on first use with `torch.utils.cpp_extension.load` (ninja and the
system C++ compiler) into `<cache>/torch_ext/<name>/`, where `<cache>` is
`$PTOVS_CACHE_DIR`, else `$XDG_CACHE_HOME/ptovs`, else `~/.cache/ptovs`. The name holds
a hash of the source, the flags, torch, Python and the CPU (the build uses
`-march=native`), so a shared home directory never loads a library built for another
machine. The library exports a plain C ABI called through ctypes: it includes no torch
headers, so a cold build takes about 6 s, and ctypes releases the GIL during a call.

Entry points:
- `available()`: builds (once) and reports whether the kernel can be used.
- `composite(...)`: autograd forward/backward with the reference's signature.
- `build_blend_weights(...)`, `apply(...)`, `spmm(...)`, `blend_weights_coo(...)`:
  the frozen-geometry fast path (RASTERIZER.md §9): F = W f and its backward W^T g.
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import platform
import shutil
import sys
import threading
from pathlib import Path

import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from ptovs.raster._common import Isect

log = logging.getLogger(__name__)

SOURCE = Path(__file__).with_name("csrc") / "composite.cpp"
ABI_VERSION = 1  # ptovs_abi_version() in composite.cpp
# No -ffast-math: the kernel relies on IEEE comparisons (NaN fails every test) and on
# forward and backward rounding identically; exp is a hand-written polynomial, so
# fast-math buys nothing. -ffp-contract=off keeps a * b + c unfused except where the
# source asks for an FMA, for the same reason.
_BASE_FLAGS = ["-O3", "-fno-math-errno", "-ffp-contract=off", "-Wno-psabi"]
_OPENMP = ["-fopenmp"]
# Tried in order; later entries drop what some compilers reject.
_FLAG_SETS = (
    (_BASE_FLAGS + ["-march=native"] + _OPENMP, _OPENMP),
    (_BASE_FLAGS + _OPENMP, _OPENMP),
    (_BASE_FLAGS + ["-march=native"], []),
)

_lock = threading.Lock()
_lib: ctypes.CDLL | None = None
_tried = False

_p = ctypes.c_void_p
_i32 = ctypes.c_int
_i64 = ctypes.c_int64
_SIGNATURES = {
    "ptovs_abi_version": [],
    "ptovs_simd_width": [],
    "ptovs_composite_fwd": [_p] * 5
    + [_i64, _i32, _p, _p]
    + [_i32] * 5
    + [_p] * 5
    + [_i32],
    "ptovs_composite_bwd": [_p] * 5
    + [_i64, _i32, _p, _p]
    + [_i32] * 5
    + [_p] * 5
    + [_i32],
    "ptovs_blend_weights": [_p] * 3 + [_i64, _p, _p] + [_i32] * 5 + [_p] * 4 + [_i32],
    "ptovs_spmm": [_p] * 3 + [_i64, _p, _i32, _p, _i32],
    "ptovs_csr_transpose": [_p] * 3 + [_i64, _i64] + [_p] * 4 + [_i32],
}


def _cpu_identity() -> str:
    """What -march=native depends on: the CPU model and feature flags."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return f"{platform.machine()} {platform.processor()}"
    keep = [
        line
        for line in text.splitlines()
        if line.split(":")[0].strip() in ("model name", "flags", "Features", "CPU part")
    ]
    return "\n".join(sorted(set(keep)))


def cache_dir() -> Path:
    """Root of ptovs' compiled-extension cache."""
    root = os.environ.get("PTOVS_CACHE_DIR")
    if not root:
        xdg = os.environ.get("XDG_CACHE_HOME")
        root = str(Path(xdg) / "ptovs") if xdg else "~/.cache/ptovs"
    return Path(root).expanduser() / "torch_ext"


def _build_name(cflags: list[str], ldflags: list[str]) -> str:
    h = hashlib.sha256()
    for part in (
        SOURCE.read_bytes(),
        repr((cflags, ldflags, ABI_VERSION)).encode(),
        torch.__version__.encode(),
        sys.version.encode(),
        os.environ.get("CXX", "c++").encode(),
        _cpu_identity().encode(),
    ):
        h.update(part)
        h.update(b"\0")
    return f"ptovs_raster_cpu_{h.hexdigest()[:16]}"


def _open(path: str) -> ctypes.CDLL:
    lib = ctypes.CDLL(path)
    for fn, args in _SIGNATURES.items():
        getattr(lib, fn).argtypes = args
        getattr(lib, fn).restype = ctypes.c_int
    if lib.ptovs_abi_version() != ABI_VERSION:
        raise RuntimeError(f"{path}: ABI {lib.ptovs_abi_version()} != {ABI_VERSION}")
    return lib


def _build(cflags: list[str], ldflags: list[str]) -> ctypes.CDLL:
    from torch.utils import cpp_extension

    name = _build_name(cflags, ldflags)
    build_dir = cache_dir() / name
    marker = build_dir / "ok"
    so_path = build_dir / f"{name}.so"
    if marker.is_file() and so_path.is_file():
        return _open(str(so_path))  # built and verified earlier: skip ninja
    build_dir.mkdir(parents=True, exist_ok=True)

    def compile_and_open() -> ctypes.CDLL:
        path = cpp_extension.load(
            name=name,
            sources=[str(SOURCE)],
            extra_cflags=cflags,
            extra_ldflags=ldflags,
            build_directory=str(build_dir),
            is_python_module=False,
            verbose=False,
        )
        return _open(str(path))

    try:
        lib = compile_and_open()
    except OSError:
        # A library left half-written by a killed build looks up to date to ninja.
        so_path.unlink(missing_ok=True)
        lib = compile_and_open()
    tmp = marker.with_name(f"ok.{os.getpid()}.tmp")
    tmp.write_text(name + "\n")
    os.replace(tmp, marker)  # atomic: other processes never see a half-built library
    return lib


def _load() -> ctypes.CDLL | None:
    global _lib, _tried
    with _lock:
        if _tried:
            return _lib
        _tried = True
        from torch.utils import cpp_extension

        cxx = os.environ.get("CXX", "c++")
        if shutil.which(cxx) is None or not cpp_extension.is_ninja_available():
            log.warning(
                "ptovs compiled CPU rasterizer unavailable: no C++ compiler (%s) or no "
                "ninja; falling back to slower backends",
                cxx,
            )
            return None
        errors = []
        for cflags, ldflags in _FLAG_SETS:
            try:
                _lib = _build(list(cflags), list(ldflags))
                simd = "AVX2+FMA" if _lib.ptovs_simd_width() == 8 else "portable"
                if ldflags != _OPENMP or "-march=native" not in cflags:
                    log.info("ptovs CPU kernel (%s) built with reduced flags", simd)
                log.debug("ptovs CPU kernel loaded (%s, flags %s)", simd, cflags)
                return _lib
            except Exception as exc:  # noqa: BLE001 - any failure: "unavailable"
                errors.append(f"{' '.join(cflags)}: {exc}")
        log.warning(
            "ptovs compiled CPU rasterizer unavailable (the build failed); falling "
            "back to slower backends. Build errors:\n%s",
            "\n".join(errors)[-4000:],
        )
        return None


def available() -> bool:
    """Whether the compiled CPU kernel can be used (builds it on the first call)."""
    return _load() is not None


def _lib_or_raise() -> ctypes.CDLL:
    lib = _load()
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
        nt = torch.get_num_threads()
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
        nt = torch.get_num_threads()
        grads = torch.zeros(nt, n, 6 + d)
        if width * height and n:
            rc = lib.ptovs_composite_bwd(
                *map(_ptr, (m, c, o, col, bg)), n, d, _ptr(offsets), _ptr(ids),
                tw, th, tile, width, height,
                *map(_ptr, (t_final, last, v_image, v_alpha, grads)), nt,
            )  # fmt: skip
            if rc:
                raise MemoryError(f"ptovs_composite_bwd failed ({rc})")
        g = grads.sum(0) if nt > 1 else grads[0]
        # The kernel sums v_sigma * (dx, dy, dx^2, dx dy, dy^2) per Gaussian; with
        # sigma = a dx^2 / 2 + b dx dy + c dy^2 / 2 and d = mean2d - pixel:
        a, b, cc = c.unbind(1)
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


# Frozen geometry (RASTERIZER.md §9): W [H*W, N] holds alpha_i T_i per composited pair.

Csr = tuple[
    Tensor, Tensor, Tensor
]  # (indptr int32 [rows + 1], indices int32, values f32)


@torch.no_grad()
def _blend_rows(means2d, conics, opacities, isect, width, height) -> tuple[Csr, int]:
    lib = _lib_or_raise()
    m, c, o = _check_geometry(means2d, conics, opacities)
    n = m.shape[0]
    offsets, ids = _check_isect(isect, n, width, height)
    nt = torch.get_num_threads()
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
    nt = torch.get_num_threads()
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
    """Blend-weight matrices of a frozen geometry and view (RASTERIZER.md §9).

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
            torch.get_num_threads(),
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
