"""Pictures a person looks at: heatmaps, masks and labelled overlays (PNG).

heat = heatmap(score_map, photo)            # [H, W, 3] uint8 RGB
over = overlay(photo, mask, "Dome", 0.83)   # photo | label panel
write_png(path, over)
"""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

EDGE_RGB = (255, 230, 0)
FILL_RGB = (255, 80, 40)


def to_uint8(photo: np.ndarray) -> np.ndarray:
    """RGB float [0, 1] or uint8 → uint8."""
    if photo.dtype == np.uint8:
        return photo
    return (np.clip(photo, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def heatmap(score: np.ndarray, photo: np.ndarray | None = None) -> np.ndarray:
    """A score map min-max scaled to the turbo colour map, half over the photo."""
    s = np.nan_to_num(np.asarray(score, np.float32))
    lo, hi = float(s.min()), float(s.max())
    n = (s - lo) / (hi - lo) if hi > lo else np.zeros_like(s)
    bgr = cv2.applyColorMap((n * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    if photo is None:
        return rgb
    return cv2.addWeighted(to_uint8(photo), 0.5, rgb, 0.5, 0)


def overlay(
    photo: np.ndarray, mask: np.ndarray, label: str, score: float | None = None
) -> np.ndarray:
    """The photo with the region tinted, its edge drawn, and the label beside it.

    The label goes in a panel to the right of the image, never over the region.
    """
    img = to_uint8(photo).copy()
    m = mask.astype(bool)
    if m.any():
        tint = img.astype(np.float32)
        tint[m] = 0.6 * tint[m] + 0.4 * np.asarray(FILL_RGB, np.float32)
        img = tint.astype(np.uint8)
        contours, _ = cv2.findContours(
            m.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE
        )
        thick = max(1, round(max(img.shape[:2]) / 200))
        cv2.drawContours(img, contours, -1, EDGE_RGB, thick)
    h = img.shape[0]
    lines = [label] if score is None else [label, f"score {score:.3f}"]
    if not m.any():
        lines.append("(empty mask)")
    font, fs = cv2.FONT_HERSHEY_SIMPLEX, max(0.35, h / 600)
    widths = [cv2.getTextSize(t, font, fs, 1)[0][0] for t in lines]
    panel = np.full((h, max(widths) + 16, 3), 24, np.uint8)
    y = 8
    for t in lines:
        (_, th), base = cv2.getTextSize(t, font, fs, 1)
        y += th + base
        cv2.putText(panel, t, (8, y), font, fs, (255, 255, 255), 1, cv2.LINE_AA)
        y += 4
    cv2.rectangle(panel, (0, 0), (3, h - 1), EDGE_RGB, -1)
    return np.hstack((img, panel))


def write_png(path: Path, rgb_or_gray: np.ndarray) -> None:
    """Write atomically (a reader never sees half a PNG)."""
    from ptovs.artifacts import write_atomic

    arr = rgb_or_gray
    if arr.ndim == 3:
        arr = cv2.cvtColor(arr, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", arr)
    if not ok:
        raise OSError(f"could not encode {path}")
    write_atomic(Path(path), buf.tobytes())


def slug(text: str) -> str:
    """A file-name-safe form of a query ("Ionic Column" → "ionic_column")."""
    s = re.sub(r"[^0-9a-zA-Z]+", "_", text.strip()).strip("_").lower()
    return s or "query"


__all__ = ["heatmap", "overlay", "slug", "to_uint8", "write_png"]
