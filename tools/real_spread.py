"""The grey-level spread of real photographs, whole and in part-sized windows.

    python tools/real_spread.py PHOTO_FOLDER [PHOTO_FOLDER ...]

For each photo (any image OpenCV reads, searched recursively): resized so its short
side is 224 px, as the published low-contrast studies show their images; its
luminance's 5-95 % range, and the same range in 20 windows of 40-112 px at fixed
pseudo-random places (the size of a landmark part in such a photo). Prints the
medians. `bench/standin_profile.py` uses the whole photos' median (`REAL_SPREAD`)
to blend each part to the grey levels a whole photograph keeps at low contrast.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".ppm"}


def spread(y: np.ndarray) -> float:
    """The 5-95 % range of a luminance image in [0, 1]."""
    lo, hi = np.percentile(y, [5, 95])
    return float(hi - lo)


def measure(path: Path, rng: np.random.Generator, windows: int = 20):
    im = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if im is None:
        return None
    h, w = im.shape[:2]
    s = 224 / min(h, w)
    im = cv2.resize(im, (round(w * s), round(h * s)), interpolation=cv2.INTER_AREA)
    y = cv2.cvtColor(im, cv2.COLOR_BGR2GRAY).astype(np.float64) / 255.0
    parts = []
    for _ in range(windows):
        k = int(rng.integers(40, 112))
        r = int(rng.integers(0, y.shape[0] - k))
        c = int(rng.integers(0, y.shape[1] - k))
        parts.append(spread(y[r : r + k, c : c + k]))
    return spread(y), parts


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("folders", nargs="+", type=Path)
    args = ap.parse_args(argv)
    rng = np.random.default_rng(0)
    whole, win = [], []
    for folder in args.folders:
        if not folder.is_dir():
            print(f"error: {folder} is not a folder of photos", file=sys.stderr)
            return 2
        for p in sorted(folder.rglob("*")):
            if p.suffix.lower() in SUFFIXES and (m := measure(p, rng)) is not None:
                whole.append(m[0])
                win.extend(m[1])
    if not whole:
        print("error: no photo found in " + ", ".join(map(str, args.folders)),
              file=sys.stderr)  # fmt: skip
        return 2
    q = np.percentile(whole, [25, 50, 75])
    print(f"{len(whole)} photos: whole-photo spread median {q[1]:.3f} "
          f"(quartiles {q[0]:.3f}, {q[2]:.3f}); part-sized windows median "
          f"{np.median(win):.3f} ({len(win)} windows)")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
