"""Photometric losses and metrics: L1, SSIM (pytorch_msssim), PSNR."""

from __future__ import annotations

import math

import numpy as np
from pytorch_msssim import ssim as _ssim
from torch import Tensor

SSIM_WINDOW = 11  # Gaussian window 11 x 11, sigma 1.5, as 3DGS


def ssim(a: Tensor, b: Tensor) -> Tensor:
    """Mean SSIM of two [H, W, C] images in [0, 1] (differentiable).

    Images smaller than the window are compared with a smaller odd window.
    """
    h, w = a.shape[:2]
    win = min(SSIM_WINDOW, h if h % 2 else h - 1, w if w % 2 else w - 1)
    if win < 3:
        return 1.0 - (a - b).abs().mean()  # degenerate image: fall back to L1
    x = a.permute(2, 0, 1)[None]
    y = b.permute(2, 0, 1)[None]
    return _ssim(x, y, data_range=1.0, size_average=True, win_size=win, win_sigma=1.5)


def psnr(a: np.ndarray | Tensor, b: np.ndarray | Tensor, mask=None) -> float:
    """PSNR in dB of images in [0, 1]; `mask` [H, W] (True = counted) optional."""
    a = a.detach().cpu().numpy() if isinstance(a, Tensor) else np.asarray(a)
    b = b.detach().cpu().numpy() if isinstance(b, Tensor) else np.asarray(b)
    err = (a.astype(np.float64) - b.astype(np.float64)) ** 2
    if mask is not None:
        m = np.asarray(mask, bool)
        if not m.any():
            return math.nan
        err = err[m]
    mse = float(err.mean())
    return 99.0 if mse <= 1e-10 else -10.0 * math.log10(mse)


def auroc(scores: np.ndarray, labels: np.ndarray) -> float:
    """Area under the ROC curve (ties counted half); NaN with one class only."""
    s = np.asarray(scores, np.float64).ravel()
    y = np.asarray(labels, bool).ravel()
    n_pos, n_neg = int(y.sum()), int((~y).sum())
    if n_pos == 0 or n_neg == 0:
        return math.nan
    order = np.argsort(s, kind="mergesort")
    s_sorted = s[order]
    ranks = np.empty(len(s), np.float64)
    # average ranks over ties
    _, first, counts = np.unique(s_sorted, return_index=True, return_counts=True)
    avg = first + (counts - 1) / 2.0 + 1.0
    ranks[order] = np.repeat(avg, counts)
    return float((ranks[y].sum() - n_pos * (n_pos + 1) / 2.0) / (n_pos * n_neg))


def l1(a: Tensor, b: Tensor) -> Tensor:
    return (a - b).abs().mean()


__all__ = ["auroc", "l1", "psnr", "ssim"]
