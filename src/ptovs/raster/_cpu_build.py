"""Building and loading the compiled CPU rasterizer (csrc/project.cpp +
composite.cpp); `ptovs.raster._cpu` calls it.

The kernel is built on first use with `torch.utils.cpp_extension.load` (ninja and the
system C++ compiler) into `<cache>/torch_ext/<name>/`, where `<cache>` is
`$PTOVS_CACHE_DIR`, else `$XDG_CACHE_HOME/ptovs`, else `~/.cache/ptovs`. The name holds
a hash of the source, the flags, torch, Python and the CPU (the build uses
`-march=native`), so a shared home directory never loads a library built for another
machine. `$PTOVS_MARCH` names another target (e.g. `x86-64-v3`, AVX2), built into a
library of its own (docs/guide.md, "How steady the answers are"). The library exports a
plain C ABI called through ctypes: it includes no torch headers, so a cold build takes
about 6 s, and ctypes releases the GIL during a call.
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import platform
import re
import shutil
import sys
import threading
from pathlib import Path

import torch

from ptovs.atomic import atomic_file  # standard library only, below every room

log = logging.getLogger(__name__)

SOURCES = tuple(
    Path(__file__).with_name("csrc") / name for name in ("composite.cpp", "project.cpp")
)
ABI_VERSION = 3  # ptovs_abi_version() in composite.cpp
# No -ffast-math: the kernel relies on IEEE comparisons (NaN fails every test) and on
# forward and backward rounding identically; exp is a hand-written polynomial, so
# fast-math buys nothing. -ffp-contract=off keeps a * b + c unfused except where the
# source asks for an FMA, for the same reason.
_BASE_FLAGS = ["-O3", "-fno-math-errno", "-ffp-contract=off", "-Wno-psabi"]
_OPENMP = ["-fopenmp"]
_MARCH_OK = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.+-]{0,63}")


def march() -> str:
    """The -march target: `$PTOVS_MARCH`, else "native". A value that is not a
    plain target name is refused (it goes onto a compiler's command line)."""
    value = os.environ.get("PTOVS_MARCH", "").strip() or "native"
    if not _MARCH_OK.fullmatch(value):
        raise ValueError(
            f"PTOVS_MARCH={value!r} is not a compiler target name (e.g. native, "
            "x86-64-v3, x86-64-v4); unset it or give a plain name"
        )
    return value


def _flag_sets() -> tuple[tuple[list[str], list[str]], ...]:
    """Tried in order; later entries drop what some compilers reject."""
    arch = [f"-march={march()}"]
    return (
        (_BASE_FLAGS + arch + _OPENMP, _OPENMP),
        (_BASE_FLAGS + _OPENMP, _OPENMP),
        (_BASE_FLAGS + arch, []),
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
    "ptovs_grad_slices": [],
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
    "ptovs_project_fwd": [_p] * 4 + [_i64, _p] + [_i32] * 3 + [_p] * 5 + [_i32],
    "ptovs_project_bwd": [_p] * 4 + [_i64, _p] + [_i32] * 3 + [_p] * 8 + [_i32],
    "ptovs_intersect_count": [_p, _p, _p, _i64] + [_i32] * 3 + [_p] * 6 + [_i32],
    "ptovs_intersect_fill": [_i64, _p, _p, _p, _i32, _i32, _p, _i32],
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
        *(source.read_bytes() for source in SOURCES),
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
            sources=[str(source) for source in SOURCES],
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
    with atomic_file(marker) as tmp:  # other processes never see a half-built library
        tmp.write_text(name + "\n")
    return lib


def load() -> ctypes.CDLL | None:
    """The compiled kernel's library (built and loaded on the first call), or None
    when it cannot be built here (the reason is logged once)."""
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
        sets = _flag_sets()
        for cflags, ldflags in sets:
            try:
                _lib = _build(list(cflags), list(ldflags))
                simd = "AVX2+FMA" if _lib.ptovs_simd_width() == 8 else "portable"
                if (cflags, ldflags) != sets[0]:
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
