"""Photometric losses and metrics: L1, SSIM, PSNR."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor
from torch.nn import functional as F  # noqa: N812

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
    return _ssim(x, y, win)


SSIM_C1, SSIM_C2 = 0.01**2, 0.03**2  # (K · data range)², data range 1


def _window(win: int, sigma: float = 1.5) -> Tensor:
    t = torch.arange(win, dtype=torch.float64) - win // 2
    g = torch.exp(-(t**2) / (2 * sigma**2))
    return g / g.sum()


def _ssim(x: Tensor, y: Tensor, win: int) -> Tensor:
    """Mean SSIM of [1, C, H, W] images over the valid region of a separable
    Gaussian window (pytorch_msssim's `ssim`, data range 1, K = 0.01, 0.03).

    The five local moments (x, y, x², y², xy) of every channel are blurred
    together: on the CPU by OpenCV's separable filter (`_Blur`: 15 planes at
    770 × 512 in ~6 ms against ~24 for torch's convolutions), elsewhere by one
    grouped convolution per axis (pytorch_msssim runs ten)."""
    c = x.shape[1]
    z = torch.cat((x, y, x * x, y * y, x * y), 1)
    if z.device.type == "cpu" and z.dtype in (torch.float32, torch.float64):
        z = _Blur.apply(z[0], win)[None]
    else:
        z = _blur_conv(z, win)
    mx, my, sxx, syy, sxy = z.split(c, 1)
    mx2, my2, mxy = mx * mx, my * my, mx * my
    cs = (2 * (sxy - mxy) + SSIM_C2) / ((sxx - mx2) + (syy - my2) + SSIM_C2)
    lum = (2 * mxy + SSIM_C1) / (mx2 + my2 + SSIM_C1)
    return (lum * cs).mean()


def _blur_conv(z: Tensor, win: int) -> Tensor:
    """[1, C, H, W] -> the valid Gaussian blur by grouped convolutions (off the CPU)."""
    c = z.shape[1]
    g = _window(win).to(z).repeat(c, 1)  # [C, win]
    z = F.conv2d(z, g.reshape(c, 1, 1, win), groups=c)
    return F.conv2d(z, g.reshape(c, 1, win, 1), groups=c)


def _valid_blur(planes: np.ndarray, win: int) -> np.ndarray:
    """[C, H, W] -> [C, H - win + 1, W - win + 1]: the Gaussian window's valid
    correlation, plane by plane (each output pixel's sum is the same at any
    OpenCV thread count)."""
    import cv2

    g = _window(win).numpy().astype(planes.dtype)
    r = win // 2
    return np.stack(
        [
            cv2.sepFilter2D(p, -1, g, g, borderType=cv2.BORDER_CONSTANT)[r:-r, r:-r]
            for p in planes
        ]
    )


class _Blur(torch.autograd.Function):
    """The valid Gaussian blur of [C, H, W] planes and its exact backward: the
    window is symmetric, so the gradient is the same blur of the gradient padded
    by win - 1 zeros on every side."""

    @staticmethod
    def forward(ctx, planes: Tensor, win: int) -> Tensor:  # noqa: D102
        ctx.win = win
        out = _valid_blur(np.ascontiguousarray(planes.detach().numpy()), win)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor, None]:  # noqa: D102
        pad = ctx.win - 1
        padded = np.pad(grad.detach().numpy(), ((0, 0), (pad, pad), (pad, pad)))
        return torch.from_numpy(_valid_blur(padded, ctx.win)), None


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
