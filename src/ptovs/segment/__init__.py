"""Segmenters: one image in, L levels of segments out (docs/method.md §4).

```python
seg = get_segmenter("graph", levels=("s", "m", "l"))
for level in seg.segment(image):  # image [H, W, 3] uint8 RGB
    level.labels  # [H, W] int32: ids 0..n-1, every id present; NO_SEGMENT = -1
    level.mask(k)  # the bool mask that is cropped for segment k
```

Backends: `graph` (OpenCV's Felzenszwalb graph segmentation at one scale per level;
the CPU default) and `sam` (segment-anything from a local checkpoint, extra
`[sam]`, LangSplat's multi-level recipe; see `ptovs.segment.sam`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

NO_SEGMENT = -1
"""Label of a pixel no segment covers. Every consumer treats it as invalid."""

LEVEL_NAMES = ("default", "s", "m", "l")
"""LangSplat's levels: "default" pools SAM's three outputs; s/m/l = subpart/part/whole."""

SEGMENTERS = ("graph", "hier", "sam")


@dataclass
class Level:
    """One level's segmentation of one image."""

    labels: np.ndarray  # [H, W] int32, NO_SEGMENT or 0..n-1 (each id present)
    masks: list[np.ndarray] | None = None
    """Crop mask per id (SAM: the whole mask, even where a later one painted over
    it, as LangSplat crops); None = the labelled pixels `labels == k`."""

    @property
    def n(self) -> int:
        return int(self.labels.max()) + 1 if self.labels.size else 0

    def mask(self, k: int) -> np.ndarray:
        return self.masks[k] if self.masks is not None else self.labels == k


@runtime_checkable
class Segmenter(Protocol):
    name: str
    levels: tuple[str, ...]

    def segment(self, image: np.ndarray) -> list[Level]:
        """Segment an RGB uint8 image [H, W, 3]; one `Level` per entry of `levels`."""
        ...


def check_levels(levels: tuple[str, ...] | list[str]) -> tuple[str, ...]:
    levels = tuple(levels)
    bad = [lv for lv in levels if lv not in LEVEL_NAMES]
    if not levels or bad or len(set(levels)) != len(levels):
        raise ValueError(
            f"levels {list(levels)}: give distinct names from {list(LEVEL_NAMES)}"
        )
    return levels


def get_segmenter(name: str, **kwargs) -> Segmenter:
    """Build a segmenter by name ("graph" or "sam"); kwargs go to its constructor."""
    if name == "graph":
        from ptovs.segment.graph import GraphSegmenter

        return GraphSegmenter(**kwargs)
    if name == "hier":
        from ptovs.segment.hier import HierSegmenter

        return HierSegmenter(**kwargs)
    if name == "sam":
        from ptovs.segment.sam import SamSegmenter

        return SamSegmenter(**kwargs)
    raise ValueError(f"unknown segmenter {name!r}; choose from {list(SEGMENTERS)}")


__all__ = [
    "LEVEL_NAMES",
    "NO_SEGMENT",
    "SEGMENTERS",
    "Level",
    "Segmenter",
    "check_levels",
    "get_segmenter",
]
