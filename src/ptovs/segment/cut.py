"""An image's segments as extract-features crops them: the segments too small to
read left out (`drop_small_segments`, by `crop_sides`), and levels cut once
handed back as a segmenter (`Cut`) so that one view's segments crop all of its
images.
"""

from __future__ import annotations

import numpy as np

from ptovs.segment.levels import NO_SEGMENT, Level, Segmenter


def crop_sides(level: Level) -> np.ndarray:
    """[n] the longer side of each segment's crop box (of `level.mask(k)`, the
    pixels `prepare_crop` cuts out, its box inclusive), in pixels."""
    if level.masks is None:
        lab = level.labels
        n = level.n
        ys, xs = np.nonzero(lab >= 0)
        ids = lab[ys, xs]
        y0 = np.full(n, np.iinfo(np.int64).max)
        x0 = y0.copy()
        y1 = np.full(n, -1)
        x1 = y1.copy()
        np.minimum.at(y0, ids, ys)
        np.minimum.at(x0, ids, xs)
        np.maximum.at(y1, ids, ys)
        np.maximum.at(x1, ids, xs)
        return np.maximum(y1 - y0, x1 - x0) + 1
    sides = []
    for m in level.masks:
        rows = np.flatnonzero(m.any(axis=1))
        cols = np.flatnonzero(m.any(axis=0))
        sides.append(max(rows[-1] - rows[0], cols[-1] - cols[0]) + 1)
    return np.array(sides, np.int64)


def drop_small_segments(levels: list[Level], min_crop_px: int) -> list[Level]:
    """Each level without the segments whose crop's longer side is under
    `min_crop_px` (`crop_sides`): their pixels become NO_SEGMENT and the rest are
    renumbered 0..n'-1 in their order. 0 returns `levels` unchanged."""
    if min_crop_px <= 0:
        return levels
    out = []
    for level in levels:
        keep = crop_sides(level) >= min_crop_px
        if keep.all():
            out.append(level)
            continue
        new = np.where(keep, np.cumsum(keep) - 1, NO_SEGMENT).astype(np.int32)
        lab = level.labels
        labels = np.where(lab >= 0, new[np.maximum(lab, 0)], NO_SEGMENT)
        masks = None
        if level.masks is not None:
            masks = [m for m, k in zip(level.masks, keep, strict=True) if k]
        out.append(Level(labels.astype(np.int32), masks))
    return out


class Cut:
    """A segmenter that hands back levels already cut (by `cut_levels`), so that
    `image_features` crops and encodes an image with them."""

    name = "cut"

    def __init__(self, names: tuple[str, ...], levels: list[Level]):
        self.levels = names
        self._cut = levels

    def segment(self, image: np.ndarray) -> list[Level]:
        shape = self._cut[0].labels.shape if self._cut else image.shape[:2]
        if image.shape[:2] != shape:
            raise ValueError(f"image {image.shape[:2]} is not the segments' {shape}")
        return self._cut


def cut_levels(
    segmenter: Segmenter, stem: str, app: str, image: np.ndarray, min_crop_px: int
) -> list[Level]:
    """Segment the image `app` of view `stem`, small segments left out."""
    if hasattr(segmenter, "select"):  # truth: this view, occluders or not
        segmenter.select(stem, app == "orig")
    return drop_small_segments(segmenter.segment(image), min_crop_px)


__all__ = [
    "Cut",
    "crop_sides",
    "cut_levels",
    "drop_small_segments",
]
