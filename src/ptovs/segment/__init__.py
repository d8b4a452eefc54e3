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
`ptovs.segment.sam2`). extract-features builds them from its config through their
backends (`ptovs.segment.backend`; graph's, hier's and truth's are below).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ptovs.segment.backend import SegmenterBackend
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


class GraphBackend(SegmenterBackend):
    """One Felzenszwalb pass per level (`ptovs.segment.graph`)."""

    name = "graph"
    config_keys = ("graph_k", "graph_sigma", "graph_min_size")

    def build(self, config: Any, levels: tuple, scene_root: Path | None) -> Segmenter:
        if config.graph_k and len(config.graph_k) != len(levels):
            raise ValueError(f"graph_k needs one value per level {list(levels)}")
        k = dict(zip(levels, config.graph_k, strict=True)) if config.graph_k else None
        return get_segmenter(
            "graph", levels=levels, k=k, sigma=config.graph_sigma,
            min_size=config.graph_min_size,
        )  # fmt: skip

    def empty_causes(self, config: Any) -> list[str]:
        return [
            f"thresholds too strict (graph_k, graph_min_size = {config.graph_min_size})"
        ]


class HierBackend(SegmenterBackend):
    """Nested levels cut from one merge hierarchy (`ptovs.segment.hier`)."""

    name = "hier"
    config_keys = ("hier_thresholds", "hier_texture", "hier_edge", "hier_min_size")

    def build(self, config: Any, levels: tuple, scene_root: Path | None) -> Segmenter:
        if config.hier_thresholds and len(config.hier_thresholds) != len(levels):
            raise ValueError(
                f"hier_thresholds needs one value per level {list(levels)}"
            )
        th = config.hier_thresholds
        return get_segmenter(
            "hier",
            levels=levels,
            thresholds=dict(zip(levels, th, strict=True)) if th else None,
            texture=config.hier_texture,
            edge=config.hier_edge,
            min_size=config.hier_min_size,
        )

    def empty_causes(self, config: Any) -> list[str]:
        return [
            "thresholds too strict (hier_thresholds, hier_min_size = "
            f"{config.hier_min_size})"
        ]


class TruthBackend(SegmenterBackend):
    """A synthetic scene's part masks (`ptovs.segment.truth`)."""

    name = "truth"

    def build(self, config: Any, levels: tuple, scene_root: Path | None) -> Segmenter:
        if scene_root is None:
            raise ValueError("segmenter 'truth' needs the scene's folder")
        from ptovs.segment.truth import TruthSegmenter

        return TruthSegmenter(scene_root, levels)

    def empty_causes(self, config: Any) -> list[str]:
        return ["part masks missing from the scene's folder"]


__all__ = [
    "LEVEL_NAMES",
    "NO_SEGMENT",
    "SEGMENTERS",
    "GraphBackend",
    "HierBackend",
    "TruthBackend",
    "Level",
    "Segmenter",
    "check_levels",
    "get_segmenter",
]
