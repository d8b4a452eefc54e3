"""The README's demo picture from `make demo`'s query output: for one view, a row per
query with the heatmap beside the overlay (the overlay carries the text and score),
enlarged 3×.

    python bench/demo_picture.py                     # work/tiny_s0/query-out/male
    python bench/demo_picture.py --view 0003.jpg --out docs/img/demo_overlay.png

bench/pictures.py redraws it with the README's other demo pictures (and the figures
their captions quote).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT  # noqa: E402  (same folder)

GAP = 2  # white pixels between panels, before the enlargement


def _pad(img: np.ndarray, width: int) -> np.ndarray:
    extra = width - img.shape[1]
    return np.pad(img, ((0, 0), (0, extra), (0, 0)), constant_values=255)


def compose(view_dir: Path, scale: int = 3) -> np.ndarray:
    """Rows [heatmap | overlay] for every query of one view, white between."""
    rows = []
    for heat in sorted(view_dir.glob("*_heatmap.png")):
        over = heat.with_name(heat.name.replace("_heatmap", "_overlay"))
        a, b = cv2.imread(str(heat)), cv2.imread(str(over))
        if a is None or b is None:
            raise SystemExit(f"cannot read {heat} or {over}: rerun `make demo`")
        h = max(a.shape[0], b.shape[0])
        a, b = (np.pad(x, ((0, h - x.shape[0]), (0, 0), (0, 0)), constant_values=255)
                for x in (a, b))  # fmt: skip
        rows.append(np.hstack([a, np.full((h, GAP, 3), 255, np.uint8), b]))
    if not rows:
        raise SystemExit(f"no *_heatmap.png in {view_dir}: run `make demo` first")
    width = max(r.shape[1] for r in rows)
    out = []
    for i, r in enumerate(rows):
        if i:
            out.append(np.full((GAP, width, 3), 255, np.uint8))
        out.append(_pad(r, width))
    pic = np.vstack(out)
    return cv2.resize(pic, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--query-out", type=Path,
                    default=ROOT / "work" / "tiny_s0" / "query-out" / "male")  # fmt: skip
    ap.add_argument("--view", default=None, help="image name (default: the first)")
    ap.add_argument(
        "--out", type=Path, default=ROOT / "docs" / "img" / "demo_overlay.png"
    )
    args = ap.parse_args()
    views = sorted(p for p in args.query_out.iterdir() if p.is_dir())
    if not views:
        raise SystemExit(f"no views under {args.query_out}: run `make demo` first")
    view = (
        next((v for v in views if v.name == args.view), None) if args.view else views[0]
    )
    if view is None:
        raise SystemExit(
            f"no view {args.view!r}; have {', '.join(v.name for v in views)}"
        )
    pic = compose(view)
    from ptovs.atomic import atomic_file

    with atomic_file(args.out) as tmp:  # keeps .png: cv2 picks the format by it
        if not cv2.imwrite(str(tmp), pic):
            raise SystemExit(f"cannot write {args.out}")
    print(f"{args.out}: {view.name}, {pic.shape[1]}×{pic.shape[0]}")


if __name__ == "__main__":
    main()
