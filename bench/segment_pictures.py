"""Segment levels on real photos, side by side: the photo, then each
segmenter's s / m / l levels (every segment filled with its mean colour, its
boundary drawn), one row per segmenter.

    python bench/segment_pictures.py PHOTO.jpg --out docs/img/segments_herzjesu.jpg

The photo is downscaled as `ptovs` would read it (the smallest factor that brings
its long side to at most 1,000 px: 4 for a 3072×2048 photo); the time of each
segmenter's three levels is printed and written on its row.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))


def mean_colour(image: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Each segment painted in its mean colour, boundaries in white."""
    from ptovs.segment.quality import boundaries

    n = int(labels.max()) + 1
    flat = labels.ravel()
    cnt = np.maximum(np.bincount(flat, minlength=n), 1)
    out = np.stack(
        [np.bincount(flat, weights=image[..., c].ravel(), minlength=n) / cnt
         for c in range(3)], 1)[flat].reshape(image.shape)  # fmt: skip
    out = out.astype(np.uint8)
    edge = cv2.dilate(boundaries(labels).astype(np.uint8), np.ones((2, 2), np.uint8))
    out[edge > 0] = 255
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("photo", type=Path)
    ap.add_argument("--segmenters", nargs="+", default=["graph", "hier"])
    ap.add_argument("--width", type=int, default=360, help="each panel's width")
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    from ptovs.atomic import atomic_file
    from ptovs.segment import get_segmenter

    img = cv2.cvtColor(cv2.imread(str(args.photo)), cv2.COLOR_BGR2RGB)
    r = 1
    while max(img.shape[:2]) / r > 1000:
        r += 1
    if r > 1:
        img = cv2.resize(img, (round(img.shape[1] / r), round(img.shape[0] / r)),
                         interpolation=cv2.INTER_AREA)  # fmt: skip
    h = round(img.shape[0] * args.width / img.shape[1])
    rows = []
    for name in args.segmenters:
        seg = get_segmenter(name, levels=("s", "m", "l"))
        seg.segment(img)  # warm-up
        t0 = time.perf_counter()
        levels = seg.segment(img)
        secs = time.perf_counter() - t0
        print(f"{name}: {secs:.2f} s for s/m/l at {img.shape[1]}×{img.shape[0]}, "
              f"{[lv.n for lv in levels]} segments", flush=True)  # fmt: skip
        panels = [img] + [mean_colour(img, lv.labels) for lv in levels]
        panels = [
            cv2.resize(p, (args.width, h), interpolation=cv2.INTER_AREA) for p in panels
        ]
        for p, text in zip(panels[1:], ("s", "m", "l"), strict=True):
            cv2.putText(
                p, text, (6, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 0), 2
            )
        cv2.putText(panels[0], f"{name} {secs:.2f} s", (6, 22), cv2.FONT_HERSHEY_SIMPLEX,
                    0.7, (255, 255, 0), 2)  # fmt: skip
        rows.append(np.concatenate(panels, 1))
    pic = np.concatenate(rows, 0)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(args.out) as tmp:
        cv2.imwrite(
            str(tmp),
            cv2.cvtColor(pic, cv2.COLOR_RGB2BGR),
            [cv2.IMWRITE_JPEG_QUALITY, 85],
        )
    print(args.out)


if __name__ == "__main__":
    main()
