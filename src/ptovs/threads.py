"""Torch's intra-op thread count, set for a block and restored after it.

    with torch_threads(1):      # torch's own operations on one thread here
        train()
    # here torch has the threads it had before, also after an error

The one place ptovs pins torch's threads for a while: the compiled rasterizer's
`kernels_only_parallel` (`ptovs.raster`) and train-ae's small network use it.
Imports only torch: every room may import it.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch


@contextmanager
def torch_threads(n: int | None) -> Iterator[None]:
    """Torch on `n` threads inside the block (None: as many as it has); the count
    it had before is set back on the way out, whatever the block did."""
    outer = torch.get_num_threads()
    if n is not None:
        torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(outer)
