"""Crops encoded once: an encoder's rows remembered by the crop's bytes.

    memo = CropMemo(encoder)
    rows = memo.encode_images(crops)   # only crops never seen are encoded
    memo.pin()                         # keep what is remembered now (a probe's)
    memo.forget()                      # drop the rest (after each view)

extract-features wraps a real encoder in one for the whole stage: the crops of the
`images = "auto"` probe are remembered, so the views it measured cost nothing more
when the stage reaches them, and a crop whose pixels recur in another image of
the view (a photo and a render that agree there) is encoded once. A crop's key is
the blake2b digest of its pixels, shape and dtype; a row is the encoder's own
output for those pixels (the batch it came in may differ: rounding of the last
bit, no more).
"""

from __future__ import annotations

import hashlib
from typing import Any

import numpy as np


class CropMemo:
    def __init__(self, encoder: Any):
        self.encoder = encoder
        self._rows: dict[bytes, np.ndarray] = {}
        self._pinned: set[bytes] = set()
        self.hits = 0
        self.encoded = 0

    def __getattr__(self, name: str) -> Any:  # name, dim, size, resample, ...
        return getattr(self.encoder, name)

    @staticmethod
    def key(crop: np.ndarray) -> bytes:
        c = np.ascontiguousarray(crop)
        head = f"{c.shape}{c.dtype.str}".encode()
        return hashlib.blake2b(head + c.tobytes(), digest_size=16).digest()

    def encode_images(self, crops: np.ndarray) -> np.ndarray:
        crops = np.asarray(crops)
        keys = [self.key(c) for c in crops]
        todo: dict[bytes, int] = {}
        for i, k in enumerate(keys):
            if k not in self._rows and k not in todo:
                todo[k] = i
        if todo:
            rows = self.encoder.encode_images(crops[list(todo.values())])
            for k, row in zip(todo, rows, strict=True):
                self._rows[k] = np.array(row, np.float32)
        self.encoded += len(todo)
        self.hits += len(keys) - len(todo)
        if not keys:
            return np.zeros((0, self.encoder.dim), np.float32)
        return np.stack([self._rows[k] for k in keys])

    def pin(self) -> None:
        """Keep every row remembered now through `forget`."""
        self._pinned |= set(self._rows)

    def forget(self) -> None:
        """Drop the rows not pinned (bounded memory: one view's at a time)."""
        self._rows = {k: v for k, v in self._rows.items() if k in self._pinned}


__all__ = ["CropMemo"]
