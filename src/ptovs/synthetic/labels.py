"""ISAT labels of a synthetic scene's evaluation views: query masks as their
labels encode them, and polygons that reproduce them."""

from __future__ import annotations

import cv2
import numpy as np

from ptovs.synthetic.presets import _min_px
from ptovs.synthetic.world import (
    Camera,
)


def _splice_holes(outer: np.ndarray, holes: list[np.ndarray]) -> np.ndarray:
    """One polygon for a region with holes: each hole joined by a zero-width bridge.

    cv2.fillPoly fills with the even-odd rule, so the bridged hole stays empty.
    """
    poly = outer
    for h in holes:
        d = ((poly[:, None, :].astype(np.int64) - h[None, :, :]) ** 2).sum(-1)
        a, b = np.unravel_index(int(np.argmin(d)), d.shape)
        hh = np.roll(h, -b, axis=0)
        poly = np.concatenate([poly[: a + 1], hh, hh[:1], poly[a:]], axis=0)
    return poly


def mask_polygons(mask: np.ndarray) -> list[np.ndarray]:
    """One polygon per 8-connected component of a mask (holes bridged in).

    Args:
        mask: [H, W] bool.

    Returns:
        int32 polygons [n, 2] of (x, y) vertices; filling them all with
        cv2.fillPoly at [H, W] reproduces the mask.
    """
    contours, hier = cv2.findContours(
        mask.astype(np.uint8), cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE
    )
    if not contours:
        return []
    hier = hier[0]
    out = []
    for k, c in enumerate(contours):
        if hier[k][3] != -1:
            continue
        holes = [contours[j][:, 0, :] for j in range(len(contours)) if hier[j][3] == k]
        out.append(_splice_holes(c[:, 0, :], holes).astype(np.int32))
    return out


MIN_COMPONENT_PX = 3
"""Connected pieces of a query's region smaller than this are left out of the label
and of its truth alike: their contour has fewer than 3 points, which is no
polygon (ISAT readers, ours included, refuse it)."""


def query_mask(part_id: np.ndarray, pids: list[int]) -> np.ndarray:
    """The truth mask of a query in one image, as its label encodes it.

    The pixels of the query's parts, without 8-connected pieces smaller than
    MIN_COMPONENT_PX (slivers of a part seen at a grazing angle).
    """
    mask = np.isin(part_id, pids)
    if not mask.any():
        return mask
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), 8)
    small = np.flatnonzero(stats[:, cv2.CC_STAT_AREA] < MIN_COMPONENT_PX)
    small = small[small > 0]
    if len(small):
        mask &= ~np.isin(lab, small)
    return mask


def isat_label(
    part_id: np.ndarray,  # [H, W] int16
    queries: dict[str, list[int]],
    name: str,
    folder: str,
    min_px: int,
) -> dict:
    """ISAT JSON (docs/method.md §1.2) of one evaluation image from its part-id map.

    Args:
        part_id: truth part ids, [H, W].
        queries: query phrase -> part ids it covers.
        name: the image file name ("<stem>.jpg").
        folder: the value of info.folder.
        min_px: a query with fewer pixels is left out of this image.

    Returns:
        The label dict; categories are the query strings verbatim.
    """
    H, W = part_id.shape
    objects = []
    for group, (query, pids) in enumerate(queries.items(), start=1):
        mask = query_mask(part_id, pids)
        if mask.sum() < min_px:
            continue
        for poly in mask_polygons(mask):
            if len(poly) < 3:  # cannot happen after query_mask; never write one
                raise AssertionError(f"{name}: {query!r} polygon of {len(poly)} points")
            objects.append(
                {
                    "category": query,
                    "group": group,
                    "segmentation": poly.tolist(),
                    "area": float(cv2.contourArea(poly)),
                    "layer": float(len(objects) + 1),
                    "bbox": [
                        int(poly[:, 0].min()),
                        int(poly[:, 1].min()),
                        int(poly[:, 0].max()),
                        int(poly[:, 1].max()),
                    ],
                    "iscrowd": False,
                    "note": "",
                }
            )
    info = {
        "description": "ISAT",
        "folder": folder,
        "name": name,
        "width": int(W),
        "height": int(H),
        "depth": 3,
        "note": "",
    }
    return {"info": info, "objects": objects}


def fill_label(label: dict) -> dict[str, np.ndarray]:
    """Category -> [H, W] bool mask, filled as the evaluation reads ISAT files."""
    H, W = label["info"]["height"], label["info"]["width"]
    out: dict[str, np.ndarray] = {}
    for obj in label["objects"]:
        m = out.setdefault(obj["category"], np.zeros((H, W), np.uint8))
        cv2.fillPoly(m, [np.asarray(obj["segmentation"], np.int32)], 1)
    return {k: v.astype(bool) for k, v in out.items()}


def label_mask(part_id: np.ndarray, pid: int, cam: Camera) -> np.ndarray | None:
    """A part's label mask in a view, or None when the view does not label it
    (fewer pixels than 0.2 % of the image, at least 12)."""
    mask = query_mask(part_id, [pid])
    return mask if mask.sum() >= _min_px(cam, 0.002, 12) else None
