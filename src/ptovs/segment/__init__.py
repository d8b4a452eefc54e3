"""Segmenters: one image in, L levels of segments out (docs/method.md §4).

```python
seg = get_segmenter("graph", levels=("s", "m", "l"))
for level in seg.segment(image):  # image [H, W, 3] uint8 RGB
    level.labels  # [H, W] int32: ids 0..n-1, every id present; NO_SEGMENT = -1
    level.mask(k)  # the bool mask that is cropped for segment k
```

Backends: `hier` (nested levels cut from one region-merging hierarchy; the CPU
default), `graph` (OpenCV's Felzenszwalb graph segmentation at one scale per level)
`sam` (segment-anything from a local checkpoint, extra
`[sam]`, LangSplat's multi-level recipe; see `ptovs.segment.sam`) and `sam2` (the
same recipe on SAM 2.1's cheaper Hiera encoder, extra `[sam2]`;
`ptovs.segment.sam2`).
"""

from __future__ import annotations

from ptovs.segment.levels import (
    LEVEL_NAMES,
    NO_SEGMENT,
    Level,
    Segmenter,
    check_levels,
)

SEGMENTERS = ("graph", "hier", "sam", "sam2")


def get_segmenter(name: str, **kwargs) -> Segmenter:
    """Build a segmenter by name (one of `SEGMENTERS`); kwargs go to its constructor."""
    if name == "graph":
        from ptovs.segment.graph import GraphSegmenter

        return GraphSegmenter(**kwargs)
    if name == "hier":
        from ptovs.segment.hier import HierSegmenter

        return HierSegmenter(**kwargs)
    if name == "sam":
        from ptovs.segment.sam import SamSegmenter

        return SamSegmenter(**kwargs)
    if name == "sam2":
        from ptovs.segment.sam2 import Sam2Segmenter

        return Sam2Segmenter(**kwargs)
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
