"""Reading a model's checkpoint, for every backend that loads one (OpenCLIP,
SAM, SAM 2.1), and the parts of a refused checkpoint's error they share.

    state = read_state_dict(path)                   # {name: tensor}
    state = readable_state("sam_checkpoint", path)  # a refusal: one InputError line
    missing, wrong, extra = state_mismatch(state, model.state_dict(), extra=True)

`read_state_dict` reads a `.safetensors` file, or a torch file with
`weights_only=True` (no pickled code runs), takes the state dict out of a
{"model": ...} (sam2's checkpoints) or {"state_dict": ...} wrapper, and drops a
"module." prefix (a checkpoint saved from DataParallel).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from ptovs.errors import InputError

# Where a missing checkpoint's error sends the user: the guide's table of each
# model's source, file and checksum (tests/test_preflight.py checks the heading).
CHECKPOINT_TABLE = "docs/guide.md, 'Checkpoints: where each comes from'"

WRAPPERS = ("model", "state_dict")
"""Keys a checkpoint may hold its state dict under."""


def where(file: str = "", source: str = "") -> str:
    """The tail of a missing-checkpoint error: the expected file, where known,
    and the guide's table."""
    take = f" (take {file}" + (f" from {source}" if source else "") + ")"
    return (take if file else "") + f"; where to download it: {CHECKPOINT_TABLE}"


def read_state_dict(path: str | Path, field: str = "") -> dict[str, Any]:
    """A checkpoint's tensors (see the module's docstring).

    Args:
        path: a `.safetensors` file or a torch file.
        field: the config field that named it, for the error of a file that
            holds no state dict ("": the error names the type it holds).
    """
    path = Path(path)
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        obj: Any = load_file(path)
    else:
        import torch

        obj = torch.load(path, map_location="cpu", weights_only=True)
    for key in WRAPPERS:
        if isinstance(obj, dict) and isinstance(obj.get(key), dict):
            obj = obj[key]
    if not isinstance(obj, dict):
        raise ValueError(
            f"{field} {path}: not a state dict"
            if field
            else f"{path} holds a {type(obj).__name__}, not a state dict"
        )
    return {k.removeprefix("module."): v for k, v in obj.items()}


def readable_state(
    field: str, path: str | Path, read: Callable[[Path], dict] = read_state_dict
) -> dict:
    """`read(path)` (a state dict); whatever error reading it raises (torch,
    pickle, a wrapper that is not one) becomes one InputError line naming the
    file."""
    try:
        return read(Path(path))
    except Exception as exc:  # a torch/pickle error: one line, naming the file
        raise InputError(
            f"{field} {path} could not be read as a state dict "
            f"({type(exc).__name__}: {str(exc).splitlines()[0][:160]})"
        ) from None


def state_mismatch(
    state: dict, want: dict, extra: bool
) -> tuple[list[str], list[str], list[str]]:
    """Tensors of `want` (tensors or shapes) missing from `state`, of another
    shape there, and (when `extra`) tensors of `state` that `want` does not have."""

    def shape(v: Any) -> tuple:
        return tuple(getattr(v, "shape", v))

    missing = [k for k in want if k not in state]
    wrong = [k for k in want if k in state and shape(state[k]) != shape(want[k])]
    unexpected = [k for k in state if k not in want] if extra else []
    return missing, wrong, unexpected


__all__ = [
    "CHECKPOINT_TABLE",
    "read_state_dict",
    "readable_state",
    "state_mismatch",
    "where",
]
