"""How well segments follow the truth: segment covering and boundary F-measure.

    covering(labels, truth)      Σ_R |R| · max_S IoU(R, S) / Σ_R |R|, over the truth
                                 regions R (the parts; ids < 0 left out) and the
                                 segments S of one level (Arbeláez et al. 2011)
    boundary_f(labels, truth)    F-measure of the segment boundary pixels against the
                                 truth's, matched within a tolerance (0.75 % of the
                                 image diagonal, at least 1 px, as BSDS)

Both take [H, W] integer maps; neither needs the ids to be contiguous.
"""

from __future__ import annotations

import cv2
import numpy as np


def _dense(labels: np.ndarray) -> tuple[np.ndarray, int]:
    u, inv = np.unique(np.asarray(labels).ravel(), return_inverse=True)
    return inv.reshape(np.shape(labels)), len(u)


def covering(labels: np.ndarray, truth: np.ndarray, min_id: int = 0) -> float:
    """Segment covering of the truth regions with id >= `min_id` by `labels`
    (1: every region is a segment; NaN when no pixel has such a truth id)."""
    labels, truth = np.asarray(labels), np.asarray(truth)
    if labels.shape != truth.shape:
        raise ValueError(f"labels {labels.shape} and truth {truth.shape} differ")
    seg, n_seg = _dense(labels)
    keep = truth >= min_id
    if not keep.any():
        return float("nan")
    tru, n_tru = _dense(np.where(keep, truth, truth.max() + 1))
    joint = np.bincount((tru * n_seg + seg).ravel(), minlength=n_tru * n_seg)
    joint = joint.reshape(n_tru, n_seg).astype(np.float64)
    area_t, area_s = joint.sum(1), joint.sum(0)
    iou = joint / (area_t[:, None] + area_s[None, :] - joint)
    kept_ids = np.unique(tru[keep])
    best = iou[kept_ids].max(1)
    return float((area_t[kept_ids] * best).sum() / area_t[kept_ids].sum())


def boundaries(labels: np.ndarray) -> np.ndarray:
    """[H, W] bool: pixels whose right or lower neighbour has another label."""
    labels = np.asarray(labels)
    b = np.zeros(labels.shape, bool)
    b[:, :-1] |= labels[:, :-1] != labels[:, 1:]
    b[:-1, :] |= labels[:-1, :] != labels[1:, :]
    return b


def _near(mask: np.ndarray, tol: float) -> np.ndarray:
    """Pixels within `tol` (Euclidean) of a True pixel of `mask`."""
    if not mask.any():
        return np.zeros(mask.shape, bool)
    dist = cv2.distanceTransform((~mask).astype(np.uint8), cv2.DIST_L2, 3)
    return dist <= tol


def boundary_f(
    labels: np.ndarray, truth: np.ndarray, tol: float | None = None
) -> tuple[float, float, float]:
    """(F, precision, recall) of `labels`' boundaries against `truth`'s."""
    labels, truth = np.asarray(labels), np.asarray(truth)
    if labels.shape != truth.shape:
        raise ValueError(f"labels {labels.shape} and truth {truth.shape} differ")
    if tol is None:
        tol = max(1.0, 0.0075 * float(np.hypot(*labels.shape)))
    bs, bt = boundaries(labels), boundaries(truth)
    if not bs.any() and not bt.any():
        return 1.0, 1.0, 1.0
    p = float((bs & _near(bt, tol)).sum() / bs.sum()) if bs.any() else 1.0
    r = float((bt & _near(bs, tol)).sum() / bt.sum()) if bt.any() else 1.0
    f = 0.0 if p + r == 0 else 2 * p * r / (p + r)
    return f, p, r


__all__ = ["boundaries", "boundary_f", "covering"]
