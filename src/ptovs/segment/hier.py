"""Hierarchical region merging: nested levels that follow textured parts (CPU).

SAM's levels nest (a subpart lies inside its part, a part inside the whole); one
Felzenszwalb pass per level does not, and on textured surfaces (stripes, tiles,
dots) its colour edges cut a part along its texture and join it to a neighbour of a
similar colour. Here one hierarchy is built and the levels are cuts of it:

1. **Texture features.** Each pixel's local colour statistics in CIELAB: the mean and
   the standard deviation over a Gaussian window of `texture` px (at 512×384; scaled
   with the image side). A striped part has one mean and one spread everywhere;
   its stripes no longer differ.
2. **Regions.** A fine graph segmentation of that feature image (Felzenszwalb, k =
   `k0`): a few hundred regions, each inside one part.
3. **Merging.** Adjacent regions merge in order of the distance between their mean
   features plus `edge` × the mean feature gradient along their shared boundary
   (a real contour costs more than a texture seam), the means updated after each
   merge. Regions under `min_size` px (at 512×384) merge first, into their closest
   neighbour.
4. **Levels.** The labels when the next merge would cost more than `thresholds[ℓ]`:
   s, m, l from low to high, so every level is a union of the one below.

Every pixel gets a segment. The defaults (texture 1 px, no edge term, 300 px
specks, cuts at 8 / 20 / 45) were chosen on the accuracy instrument's dev seeds
(`bench/segments.py`, docs/findings.md): 2-D ceiling 0.415 against the graph
segmenter's 0.325 there, with about as many segments (113 against 96 a photo).
"""

from __future__ import annotations

import heapq

import cv2
import numpy as np

from ptovs.segment.graph import check_image, require_ximgproc
from ptovs.segment.levels import Level, check_levels

REF_AREA = 512 * 384
HIER_THRESHOLDS = {"default": 20.0, "s": 8.0, "m": 20.0, "l": 45.0}  # chosen on dev


def texture_features(image: np.ndarray, texture: float) -> np.ndarray:
    """[H, W, 6] float32: local CIELAB mean and standard deviation (8-bit Lab
    units) over a Gaussian window of `texture` px (sigma)."""
    lab = cv2.cvtColor(image, cv2.COLOR_RGB2LAB).astype(np.float32)
    s = max(0.5, float(texture))
    m = cv2.GaussianBlur(lab, (0, 0), s)
    v = cv2.GaussianBlur(lab * lab, (0, 0), s) - m * m
    return np.ascontiguousarray(np.concatenate([m, np.sqrt(np.maximum(v, 0))], 2))


def _contiguous(labels: np.ndarray) -> tuple[np.ndarray, int]:
    u, inv = np.unique(labels.ravel(), return_inverse=True)
    return inv.reshape(labels.shape).astype(np.int32), len(u)


def _adjacency(labels: np.ndarray, grad: np.ndarray, n: int):
    """Adjacent region pairs (a < b) with their boundary length and summed gradient."""
    a = np.concatenate([labels[:, :-1].ravel(), labels[:-1, :].ravel()])
    b = np.concatenate([labels[:, 1:].ravel(), labels[1:, :].ravel()])
    g = np.concatenate(
        [
            np.maximum(grad[:, :-1], grad[:, 1:]).ravel(),
            np.maximum(grad[:-1, :], grad[1:, :]).ravel(),
        ]
    )
    diff = a != b
    a, b, g = a[diff], b[diff], g[diff]
    lo, hi = np.minimum(a, b).astype(np.int64), np.maximum(a, b).astype(np.int64)
    key = lo * n + hi
    uniq, inv = np.unique(key, return_inverse=True)
    length = np.bincount(inv).astype(np.float64)
    gsum = np.bincount(inv, weights=g.astype(np.float64))
    return uniq // n, uniq % n, length, gsum


class HierSegmenter:
    """Nested levels cut from one merge hierarchy (see the module docstring).

    Args:
        levels: level names, from "default", "s", "m", "l".
        thresholds: merge cost at which each level is cut (default HIER_THRESHOLDS).
        texture: the texture window's sigma at 512×384, px.
        k0: the fine graph segmentation's k (on the feature image).
        edge: weight of the boundary's mean feature gradient in the merge cost.
        min_size: smallest region at 512×384, px (scaled with the image area).
    """

    name = "hier"

    def __init__(
        self,
        levels: tuple[str, ...] = ("s", "m", "l"),
        thresholds: dict[str, float] | None = None,
        texture: float = 1.0,
        k0: float = 60.0,
        edge: float = 0.0,
        min_size: int = 300,
    ):
        self.levels = check_levels(levels)
        self.thresholds = dict(HIER_THRESHOLDS, **(thresholds or {}))
        self.texture = float(texture)
        self.k0 = float(k0)
        self.edge = float(edge)
        self.min_size = int(min_size)
        require_ximgproc()

    def segment(self, image: np.ndarray) -> list[Level]:
        check_image(image)
        h, w = image.shape[:2]
        scale = (h * w / REF_AREA) ** 0.5
        feat = texture_features(np.ascontiguousarray(image), self.texture * scale)
        min_size = max(4, round(self.min_size * h * w / REF_AREA))
        gs = cv2.ximgproc.segmentation.createGraphSegmentation(
            sigma=0.0, k=self.k0, min_size=max(2, min_size // 4)
        )
        fine, n = _contiguous(gs.processImage(feat).astype(np.int32))
        gx = cv2.Sobel(feat, cv2.CV_32F, 1, 0, ksize=3)
        gy = cv2.Sobel(feat, cv2.CV_32F, 0, 1, ksize=3)
        grad = np.sqrt((gx * gx + gy * gy).sum(2)) / 8.0  # per-pixel feature change
        cuts = sorted(
            ((self.thresholds[lv], i) for i, lv in enumerate(self.levels)),
        )
        maps = merge_levels(
            fine, n, feat, grad, [c for c, _ in cuts], self.edge, min_size
        )
        out: list[Level | None] = [None] * len(self.levels)
        for (_, i), lab in zip(cuts, maps, strict=True):
            out[i] = Level(_contiguous(lab)[0])
        return out  # type: ignore[return-value]


def merge_levels(
    fine: np.ndarray,
    n: int,
    feat: np.ndarray,
    grad: np.ndarray,
    cuts: list[float],
    edge: float,
    min_size: int,
) -> list[np.ndarray]:
    """Merge the regions of `fine` ([H, W] ids 0..n-1) by cost; the label map at
    each cost in `cuts` (ascending)."""
    d = feat.shape[2]
    size = np.bincount(fine.ravel(), minlength=n).astype(np.float64)
    sums = np.stack(
        [np.bincount(fine.ravel(), weights=feat[..., c].ravel(), minlength=n)
         for c in range(d)], 1)  # fmt: skip
    mean = sums / np.maximum(size, 1)[:, None]
    ra, rb, length, gsum = _adjacency(fine, grad, n)
    nbr: list[dict[int, list[float]]] = [dict() for _ in range(n)]
    for a, b, ln, gs in zip(
        ra.tolist(), rb.tolist(), length.tolist(), gsum.tolist(), strict=True
    ):
        nbr[a][b] = [ln, gs]
        nbr[b][a] = [ln, gs]
    parent = list(range(n))
    version = [0] * n

    def find(x: int) -> int:
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    def cost(a: int, b: int) -> float:
        ln, gs = nbr[a][b]
        c = float(np.linalg.norm(mean[a] - mean[b])) + edge * gs / max(ln, 1.0)
        if min(size[a], size[b]) < min_size:  # specks first, whatever their colour
            c -= 1e6
        return c

    heap = [(cost(a, b), a, b, 0, 0) for a in range(n) for b in nbr[a] if a < b]
    heapq.heapify(heap)
    out = []
    ci = 0

    def snapshot() -> np.ndarray:
        roots = np.array([find(i) for i in range(n)], np.int32)
        return roots[fine]

    while heap and ci < len(cuts):
        c, a, b, va, vb = heapq.heappop(heap)
        if parent[a] != a or parent[b] != b or version[a] != va or version[b] != vb:
            continue  # stale: a merged region or an old cost
        while ci < len(cuts) and c > cuts[ci]:
            out.append(snapshot())
            ci += 1
        if ci >= len(cuts):
            break
        # merge b into a (the larger keeps its id)
        if size[b] > size[a]:
            a, b = b, a
        parent[b] = a
        tot = size[a] + size[b]
        mean[a] = (mean[a] * size[a] + mean[b] * size[b]) / tot
        size[a] = tot
        version[a] += 1
        for x, (ln, gs) in nbr[b].items():
            if x == a:
                continue
            del nbr[x][b]
            if x in nbr[a]:
                nbr[a][x][0] += ln
                nbr[a][x][1] += gs
            else:
                nbr[a][x] = [ln, gs]
            nbr[x][a] = nbr[a][x]
        nbr[b] = {}
        del nbr[a][b]
        for x in nbr[a]:
            heapq.heappush(heap, (cost(a, x), min(a, x), max(a, x),
                                  version[min(a, x)], version[max(a, x)]))  # fmt: skip
    while ci < len(cuts):
        out.append(snapshot())
        ci += 1
    return out


__all__ = ["HIER_THRESHOLDS", "HierSegmenter", "merge_levels", "texture_features"]
