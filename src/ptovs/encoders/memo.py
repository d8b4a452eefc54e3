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

Before any crop is cut, `unique_segments` finds the segments of an image's levels
whose masks are the same (a region no finer level splits), so each is cropped
and encoded once.
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


def unique_segments(
    levels: list,
) -> tuple[list[tuple[int, int]], dict[tuple[int, int], list[tuple[int, int]]]]:
    """The (level, id) of each distinct segment mask, first occurrence first,
    and for each of them every (level, id) with the same mask."""
    first: dict[bytes, tuple[int, int]] = {}
    where: dict[tuple[int, int], list[tuple[int, int]]] = {}
    order: list[tuple[int, int]] = []
    for lv, level in enumerate(levels):
        for k in range(level.n):
            m = np.asarray(level.mask(k), bool)
            rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
            box = np.array([rows[0], rows[-1], cols[0], cols[-1]], np.int64)
            inner = m[box[0] : box[1] + 1, box[2] : box[3] + 1]
            key = hashlib.blake2b(
                box.tobytes() + np.packbits(inner).tobytes(), digest_size=16
            ).digest()
            if key not in first:
                first[key] = (lv, k)
                order.append((lv, k))
                where[(lv, k)] = []
            where[first[key]].append((lv, k))
    return order, where


__all__ = ["CropMemo", "unique_segments"]
