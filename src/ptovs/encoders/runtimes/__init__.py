"""Runtimes for a network's image side: PyTorch eager, ONNX Runtime, OpenVINO.

A runtime runs one torch module that maps a float32 batch [B, C, H, W] to a
float32 array [B, ...] (OpenCLIP's image tower, SAM's image encoder) with the
same arithmetic, faster where it can. A backend is one module holding one class
with the `Backend` methods, named by one line of BACKENDS:

    backend = get_backend("onnxruntime")
    why = backend.missing()               # None, or a one-line refusal naming the extra
    run = backend.load(tower, example, key, threads=2)
    out = run(batch)                      # np.ndarray float32 [B, ...]

The module is exported to ONNX once (`export.onnx_file`), into a cache every scene
shares (`cache_dir`), keyed by what decides its arithmetic (`key`: the weights'
digest, the model, the input size) and the exporter's and the runtime's versions.
Every backend runs float32: OpenVINO's own default on a CPU with bf16 instructions
is bf16, so its precision hint is set to f32. Choosing among them on a scene's own
crops (`runtime = "auto"`) is `ptovs.encoders.runtimes.choose`.
"""

from __future__ import annotations

import hashlib
import importlib
import os
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch

from ptovs.errors import InputError

BACKENDS: dict[str, str] = {
    "torch": "ptovs.encoders.runtimes.eager:TorchEager",
    "onnxruntime": "ptovs.encoders.runtimes.ort:OnnxRuntime",
    "openvino": "ptovs.encoders.runtimes.ov:OpenVino",
}
"""Each runtime: "module:class". A new runtime is one module and one line here."""

RUNTIMES = ("auto", *BACKENDS)

Runner = Callable[[np.ndarray], np.ndarray | list[np.ndarray]]
"""A loaded network: float32 [B, C, H, W] → float32 [B, ...], or a list of such
arrays in the module's output order where it returns several (SAM 2.1's encoder)."""


class Backend(Protocol):
    name: str
    extra: str
    """The pip extra that installs it (named in the refusal)."""

    def missing(self) -> str | None:
        """None where it can run here; else why not, in one line, naming the extra."""

    def version(self) -> str:
        """The installed version (part of every cache key)."""

    def cannot_win(self, device: str) -> str | None:
        """Without running anything: why it cannot be faster than PyTorch on
        `device` (e.g. no CUDA execution here), or None where it may be."""

    def load(
        self, module: Any, example: Any, key: Mapping[str, Any], threads: int
    ) -> Runner:
        """`module` (eval mode, on the CPU for exported backends) as a Runner;
        `example` a batch of the input's shape (the batch side is dynamic)."""


_LOADED: dict[str, Backend] = {}


def get_backend(name: str) -> Backend:
    """The backend named `name` (one of BACKENDS)."""
    if name not in BACKENDS:
        raise InputError(
            f"extract-features.runtime = {name!r}: choose from {list(RUNTIMES)}"
        )
    if name not in _LOADED:
        module, cls = BACKENDS[name].split(":")
        _LOADED[name] = getattr(importlib.import_module(module), cls)()
    return _LOADED[name]


def require(name: str) -> Backend:
    """The backend, or an InputError with its one-line refusal."""
    backend = get_backend(name)
    why = backend.missing()
    if why is not None:
        raise InputError(why)
    return backend


def installed() -> list[str]:
    """The runtimes that can run here, PyTorch first."""
    return [n for n in BACKENDS if get_backend(n).missing() is None]


def refusal(runtime: str, package: str, extra: str) -> str:
    """The one line a missing runtime answers with."""
    return (
        f"runtime {runtime!r} is not installed (no module {package}); install the "
        f"extra with: pip install -e '.[{extra}]' (make setup does), or set "
        "extract-features.runtime = 'torch'"
    )


def cache_dir() -> Path:
    """Where exported networks are kept for every scene: `$PTOVS_RUNTIME_CACHE`,
    else `<cache>/runtimes` with `<cache>` `$PTOVS_CACHE_DIR`,
    `$XDG_CACHE_HOME/ptovs` or `~/.cache/ptovs`."""
    own = os.environ.get("PTOVS_RUNTIME_CACHE")
    if own:
        return Path(own).expanduser()
    root = os.environ.get("PTOVS_CACHE_DIR") or (
        str(Path(os.environ["XDG_CACHE_HOME"]) / "ptovs")
        if os.environ.get("XDG_CACHE_HOME")
        else "~/.cache/ptovs"
    )
    return Path(root).expanduser() / "runtimes"


def file_digest(path: str | Path) -> str:
    """sha256 of a file's bytes (a user's checkpoint: the export's key)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 22):
            h.update(chunk)
    return h.hexdigest()


def tensors_digest(state: Mapping[str, Any]) -> str:
    """sha256 of a state dict's names, shapes and bytes (weights with no file:
    random ones in tests, or a reparameterised copy)."""
    h = hashlib.sha256()
    for name in sorted(state):
        t = state[name].detach().cpu().contiguous()
        h.update(f"{name}:{tuple(t.shape)}:{t.dtype};".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()


__all__ = [
    "BACKENDS",
    "RUNTIMES",
    "Backend",
    "Runner",
    "cache_dir",
    "file_digest",
    "get_backend",
    "installed",
    "refusal",
    "require",
    "tensors_digest",
]
