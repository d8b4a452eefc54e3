"""Give freed heap memory back to the system between large per-view steps.

A stage that builds and frees hundreds of MB per view (train-male's blend weights,
its per-view targets) leaves freed chunks inside glibc's heap, pinned between live
ones; the process's resident memory then creeps up with the number of views though
what it holds does not (measured: train-male's lift peaked at 10.9 GB on 763 photos
for 6.5 GB on 100). `release()` asks glibc to hand every free page back
(`malloc_trim(0)`, which since glibc 2.8 also returns free pages in the middle of
the heap). Elsewhere (musl, macOS) it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools


@functools.cache
def _trim():
    name = ctypes.util.find_library("c")
    if not name:
        return None
    try:
        fn = ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):  # not glibc
        return None
    fn.argtypes = [ctypes.c_size_t]
    fn.restype = ctypes.c_int
    return fn


def release() -> bool:
    """Return free heap pages to the system; True when glibc released some."""
    fn = _trim()
    return bool(fn(0)) if fn is not None else False
