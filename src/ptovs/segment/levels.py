"""What every segmenter returns and checks: `Level`, the `Segmenter` protocol, the
level names and `NO_SEGMENT`. The segmenters import this module, and the package's
face (`ptovs.segment`) hands its names on, so no segmenter imports the face back."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

NO_SEGMENT = -1
"""Label of a pixel no segment covers. Every consumer treats it as invalid."""

LEVEL_NAMES = ("default", "s", "m", "l")
"""LangSplat's levels: "default" pools SAM's three outputs; s/m/l = subpart/part/whole."""


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
