"""Mask bookkeeping shared by the segmenters: box NMS, LangSplat's mask NMS, painting.

`mask_nms` is LangSplat's per-level filter (`masks_update` / `mask_nms`, docs/method.md
§4) computed with one matrix product instead of its O(n²) Python loop;
`mask_nms_reference` is the plain loop, kept as the oracle for tests. `box_nms` is a
pure-torch greedy NMS (torchvision's compiled `nms` does not load on our CPU torch).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

IOU_THR = 0.8
SCORE_THR = 0.7
INNER_THR = 0.5
INSIDE = 0.85  # share of the inner mask lying inside the outer one
COVER = 0.5  # ... while covering less than this share of the outer one
TOP_K_FALLBACK = 3


def box_iou(a: Tensor, b: Tensor) -> Tensor:
    """IoU [A, B] of xyxy boxes a [A, 4] and b [B, 4] (0 for empty unions)."""
    area_a = (a[:, 2] - a[:, 0]).clamp_min(0) * (a[:, 3] - a[:, 1]).clamp_min(0)
    area_b = (b[:, 2] - b[:, 0]).clamp_min(0) * (b[:, 3] - b[:, 1]).clamp_min(0)
    lt = torch.maximum(a[:, None, :2], b[None, :, :2])
    rb = torch.minimum(a[:, None, 2:], b[None, :, 2:])
    wh = (rb - lt).clamp_min(0)
    inter = wh[..., 0] * wh[..., 1]
    union = area_a[:, None] + area_b[None, :] - inter
    return torch.where(
        union > 0, inter / union.clamp_min(1e-12), torch.zeros_like(inter)
    )


def box_nms(boxes: Tensor, scores: Tensor, iou_thr: float) -> Tensor:
    """Greedy NMS: indices of kept boxes, by descending score.

    Args:
        boxes: [B, 4] xyxy.
        scores: [B].
        iou_thr: a box is suppressed by a kept, higher-scored box with IoU > this.

    Returns:
        [K] int64 indices into `boxes`.
    """
    if boxes.shape[0] == 0:
        return torch.zeros(0, dtype=torch.int64)
    order = torch.argsort(scores, descending=True, stable=True)
    iou = box_iou(boxes[order].float(), boxes[order].float())
    alive = torch.ones(len(order), dtype=torch.bool)
    for i in range(len(order)):  # sequential by nature; the IoU matrix is one op
        if alive[i]:
            alive[i + 1 :] &= iou[i, i + 1 :] <= iou_thr
    return order[alive]


def _keep_or_top(keep: Tensor, k: int) -> Tensor:
    # LangSplat: "if no mask passes, the top 3 are kept" (scores are sorted)
    if keep.numel() and not keep.any():
        keep = keep.clone()
        keep[: min(k, keep.numel())] = True
    return keep


def mask_nms(
    masks: Tensor,  # [M, H, W] bool
    scores: Tensor,  # [M]
    iou_thr: float = IOU_THR,
    score_thr: float = SCORE_THR,
    inner_thr: float = INNER_THR,
) -> Tensor:
    """LangSplat's mask filter of one level, vectorised.

    Masks sorted by descending score; a mask is dropped when (a) its IoU with a
    higher-scored mask exceeds `iou_thr`, (b) its score is ≤ `score_thr` (if none
    pass, the top 3 are kept), or (c) it lies ≥ 85 % inside another mask of the
    level while covering < 50 % of it (1 − (I/a_i)(I/a_j) > 1 − inner_thr). Unlike
    greedy NMS, a dropped mask still suppresses others (as LangSplat).

    Returns:
        [K] int64 indices of the kept masks, in descending score order.
    """
    m = masks.shape[0]
    if m == 0:
        return torch.zeros(0, dtype=torch.int64)
    order = torch.argsort(scores, descending=True, stable=True)
    s = scores[order]
    flat = masks[order].reshape(m, -1).float()
    inter = flat @ flat.T  # [M, M] intersections (exact: counts < 2^24)
    area = torch.diagonal(inter).clone()
    union = area[:, None] + area[None, :] - inter
    iou = torch.where(union > 0, inter / union.clamp_min(1), torch.zeros_like(inter))
    iou_max = torch.triu(iou, diagonal=1).max(dim=0).values
    safe = area.clamp_min(1)
    share_of_row = inter / safe[:, None]  # I / a_i (row mask i)
    share_of_col = inter / safe[None, :]  # I / a_j
    inner_val = 1 - share_of_col * share_of_row
    # entry [p, q] flags column mask q lying inside row mask p; LangSplat's two
    # cases (stored at [i, j] and [j, i] for i < j) are this one rule on both sides
    inner = torch.where((share_of_row < COVER) & (share_of_col >= INSIDE), inner_val, 0)
    inner_u = torch.triu(inner, diagonal=1).max(dim=0).values
    inner_l = torch.tril(inner, diagonal=1).max(dim=0).values
    keep = iou_max <= iou_thr
    keep_conf = _keep_or_top(s > score_thr, TOP_K_FALLBACK)
    keep_u = _keep_or_top(inner_u <= 1 - inner_thr, TOP_K_FALLBACK)
    keep_l = _keep_or_top(inner_l <= 1 - inner_thr, TOP_K_FALLBACK)
    return order[keep & keep_conf & keep_u & keep_l]


def mask_nms_reference(
    masks: Tensor,
    scores: Tensor,
    iou_thr: float = IOU_THR,
    score_thr: float = SCORE_THR,
    inner_thr: float = INNER_THR,
) -> Tensor:
    """The same filter as LangSplat writes it: a double loop over mask pairs."""
    m = masks.shape[0]
    if m == 0:
        return torch.zeros(0, dtype=torch.int64)
    order = torch.argsort(scores, descending=True, stable=True)
    s = scores[order]
    ms = masks[order]
    area = ms.reshape(m, -1).sum(1).double()
    iou = torch.zeros(m, m, dtype=torch.float64)
    inner = torch.zeros(m, m, dtype=torch.float64)
    for i in range(m):
        for j in range(i, m):
            inter = float((ms[i] & ms[j]).sum())
            union = float((ms[i] | ms[j]).sum())
            iou[i, j] = inter / union if union > 0 else 0.0
            ai, aj = max(float(area[i]), 1.0), max(float(area[j]), 1.0)
            if inter / ai < COVER and inter / aj >= INSIDE:
                inner[i, j] = 1 - (inter / aj) * (inter / ai)
            if inter / ai >= INSIDE and inter / aj < COVER:
                inner[j, i] = 1 - (inter / aj) * (inter / ai)
    iou_max = torch.triu(iou, diagonal=1).max(dim=0).values
    inner_u = torch.triu(inner, diagonal=1).max(dim=0).values
    inner_l = torch.tril(inner, diagonal=1).max(dim=0).values
    keep = iou_max <= iou_thr
    keep_conf = _keep_or_top(s > score_thr, TOP_K_FALLBACK)
    keep_u = _keep_or_top(inner_u <= 1 - inner_thr, TOP_K_FALLBACK)
    keep_l = _keep_or_top(inner_l <= 1 - inner_thr, TOP_K_FALLBACK)
    return order[keep & keep_conf & keep_u & keep_l]


def paint(
    masks: list[np.ndarray], shape: tuple[int, int]
) -> tuple[np.ndarray, list[int]]:
    """Segment map from masks painted in list order (later masks overwrite).

    Args:
        masks: bool [H, W] each.
        shape: (H, W).

    Returns:
        labels [H, W] int32 with ids 0..K-1 (−1 where no mask), and the indices
        into `masks` of the K masks that are still visible (id k = masks[kept[k]]).
    """
    raw = np.full(shape, -1, np.int32)
    for i, m in enumerate(masks):
        raw[m.astype(bool)] = i
    kept = np.unique(raw[raw >= 0]).tolist()
    lut = np.full(len(masks) + 1, -1, np.int32)
    lut[np.asarray(kept, np.int64)] = np.arange(len(kept), dtype=np.int32)
    labels = np.where(raw >= 0, lut[raw], -1).astype(np.int32)
    return labels, kept
