"""Felzenszwalb graph segmentation as the CPU stand-in for SAM's levels.

One OpenCV `ximgproc` graph segmentation per level, coarser k for coarser levels
(docs/method.md §4: k = 100/300/1000/3000 for default/s/m/l). `min_size` scales with
the image area so a level means the same on a 96-px and a 512-px image (100 px at
512×384, as measured in docs/environment.md §3). Every pixel gets a segment.
"""

from __future__ import annotations

import cv2
import numpy as np

from ptovs.segment.levels import Level, check_levels

GRAPH_K = {"default": 100.0, "s": 300.0, "m": 1000.0, "l": 3000.0}
REF_AREA = 512 * 384
REF_MIN_SIZE = 100


def require_ximgproc() -> None:
    """ImportError with the fix when OpenCV's contrib modules are missing."""
    if not hasattr(cv2, "ximgproc"):
        raise ImportError(
            "cv2.ximgproc is missing: install opencv-contrib-python-headless "
            "(and not opencv-python next to it)"
        )


def check_image(image: np.ndarray) -> None:
    """ValueError unless `image` is RGB uint8 [H, W, 3]."""
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise ValueError(f"expected uint8 [H, W, 3], got {image.dtype} {image.shape}")


class GraphSegmenter:
    name = "graph"

    def __init__(
        self,
        levels: tuple[str, ...] = ("s", "m", "l"),
        k: dict[str, float] | None = None,
        sigma: float = 0.8,
        min_size: int = REF_MIN_SIZE,
    ):
        self.levels = check_levels(levels)
        self.k = dict(GRAPH_K, **(k or {}))
        self.sigma = float(sigma)
        self.min_size = int(min_size)
        require_ximgproc()

    def segment(self, image: np.ndarray) -> list[Level]:
        check_image(image)
        h, w = image.shape[:2]
        min_size = max(4, round(self.min_size * h * w / REF_AREA))
        img = np.ascontiguousarray(image)
        out = []
        for level in self.levels:
            gs = cv2.ximgproc.segmentation.createGraphSegmentation(
                sigma=self.sigma, k=self.k[level], min_size=min_size
            )
            labels = gs.processImage(img).astype(np.int32, copy=False)
            n = int(labels.max()) + 1
            if np.bincount(labels.ravel(), minlength=n).min() == 0:  # not contiguous
                _, inv = np.unique(labels, return_inverse=True)
                labels = inv.reshape(h, w).astype(np.int32)
            out.append(Level(labels))
        return out
