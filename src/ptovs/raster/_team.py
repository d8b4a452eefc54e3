"""The compiled kernels' OpenMP team, and whether torch runs beside it on one thread.

`_cpu` passes `threads()` to every kernel call. Training wraps its steps in
`kernels_only_parallel()`: torch's own operations on one thread (`ptovs
--deterministic`, the default) and the kernels on the count torch had. The
setting is recorded in every artifact's provenance (`deterministic()`).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch

from ptovs.threads import torch_threads

_team: int | None = None  # the kernels' thread count inside `kernels_only_parallel`
_serial_torch = (
    True  # inside it, torch's own operations on one thread (`--deterministic`)
)


def threads() -> int:
    """The compiled kernels' OpenMP team: torch's thread count, or inside
    `kernels_only_parallel` the count it was entered with."""
    return _team or torch.get_num_threads()


def set_deterministic(same_bits: bool) -> None:
    """Whether `kernels_only_parallel` runs torch's operations on one thread (True,
    the default: the same field at any thread count) or leaves them on every thread
    (False: faster on many cores, reproducible per thread count only). `ptovs
    --deterministic/--nondeterministic` sets it for a command."""
    global _serial_torch
    _serial_torch = bool(same_bits)


def deterministic() -> bool:
    """The setting of `set_deterministic`."""
    return _serial_torch


@contextmanager
def kernels_only_parallel() -> Iterator[None]:
    """Torch's own operations on one thread, the compiled kernels on all of torch's.

    The kernels give the same bits at any thread count (their sums run in fixed
    slices); MKL's matrix products and oneDNN's convolutions do not (a weight
    gradient's long sum is split by thread, in a shape-dependent way). Training
    under this context is therefore the same at 1 or 16 threads: `--threads` changes
    the time, not the field. Torch's share of a step is the small networks, the
    losses and Adam: on 2 threads it costs reconstruct 1.26-1.45x, on 16 threads
    2.7x (docs/results.md, "Threads"). After `set_deterministic(False)` torch keeps
    every thread here; only the kernels' team is fixed."""
    global _team
    before = _team
    _team = threads()
    try:
        with torch_threads(1 if _serial_torch else None):
            yield
    finally:
        _team = before
