"""Compositing backends: which exist, which work here, and which one a call gets.

"torch" is the pure PyTorch reference (`_reference`), "cpu" the compiled kernel
(`_cpu`), built on first use and cached; a backend that cannot load falls back to
"torch" with one warning.
"""

from __future__ import annotations

import functools
import logging
import warnings
from collections.abc import Callable
from types import ModuleType

import torch
from torch import Tensor

from ptovs.raster import _reference

logger = logging.getLogger(__name__)

Composite = Callable[..., tuple[Tensor, Tensor, Tensor]]


@functools.cache
def cpu_module() -> ModuleType | None:
    """The compiled CPU backend if it imports and reports itself available (cached)."""
    try:
        from ptovs.raster import _cpu

        if _cpu.available():
            return _cpu
    except Exception as exc:  # noqa: BLE001  (any build or import failure)
        logger.debug("cpu raster backend unavailable: %s", exc)
    return None


def _torch_composite() -> Composite | None:
    return _reference.composite


def _cpu_composite() -> Composite | None:
    mod = cpu_module()
    return None if mod is None else mod.composite


# The seam for further backends ("cuda", "gsplat"): name -> loader of its composite.
BACKENDS: dict[str, Callable[[], Composite | None]] = {
    "torch": _torch_composite,
    "cpu": _cpu_composite,
}
_warned: set[str] = set()


def available_backends() -> list[str]:
    """Names of the compositing backends that work here, "torch" first.

    Returns:
        e.g. ["torch", "cpu"].
    """
    return [name for name, load in BACKENDS.items() if load() is not None]


def resolve_backend(backend: str, dtype: torch.dtype, device: torch.device) -> str:
    if backend == "auto":
        if device.type == "cpu" and dtype == torch.float32 and _cpu_composite():
            return "cpu"
        return "torch"
    if BACKENDS[backend]() is None:
        if backend not in _warned:
            _warned.add(backend)
            warnings.warn(
                f"raster backend {backend!r} is unavailable; using 'torch'",
                RuntimeWarning,
                stacklevel=3,
            )
        return "torch"
    if backend == "cpu" and device.type != "cpu":
        raise ValueError(f"backend='cpu' needs CPU tensors, got device {device}")
    return backend
