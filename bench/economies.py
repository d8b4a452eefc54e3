"""What extract-features' economies save on a scene's photos (default config).

    python bench/economies.py --data data/econ --preset tiny --seed 0 --views 12
    python bench/economies.py --data data/econ --preset landmark --seed 0 --photos 8

Generates the synthetic scene if missing, segments its first --views train photos
with the default segmenter (`hier`, as extract-features builds it, at the scene's
loaded size) and reports per photo: the segmenter's time, the segments (crops to
encode) per level, and how many of them `min_crop_px` = 16 / 32 would leave out
(crop box's longer side under that). `segment = "once"` saves the segmenter's time
on every image of a view but one (with three novel slots: 4 of 5 calls). JSON to
--out.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--photos", type=int, default=None, help="train photos generated")
    ap.add_argument("--views", type=int, default=8, help="train photos segmented")
    ap.add_argument("--px", type=int, nargs="+", default=[16, 32])
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)

    from ptovs.scene import load_scene
    from ptovs.stages.extract_features import Config, build_segmenter, crop_sides
    from ptovs.synthetic import generate_scene

    name = f"{args.preset}_s{args.seed}" + (f"_p{args.photos}" if args.photos else "")
    root = args.data / name
    if not (root / "synthetic" / "truth" / "cameras.json").is_file():
        root = generate_scene(args.data, args.preset, args.seed, progress=False,
                              photos=args.photos)  # fmt: skip
    scene = load_scene(root, downscale="auto")
    seg = build_segmenter(Config(), scene.root)
    rows = []
    for v in scene.train_views()[: args.views]:
        img = (scene.load_image(v) * 255.0 + 0.5).astype(np.uint8)
        t0 = time.perf_counter()
        levels = seg.segment(img)
        secs = time.perf_counter() - t0
        sides = [crop_sides(lv) for lv in levels]
        rows.append({
            "view": v.name, "size": list(img.shape[:2]), "segment_s": secs,
            "segments": [len(s) for s in sides],
            **{f"under_{px}": [int((s < px).sum()) for s in sides] for px in args.px},
        })  # fmt: skip
    total = sum(sum(r["segments"]) for r in rows)
    summary = {
        "preset": args.preset, "seed": args.seed, "views": len(rows),
        "size": rows[0]["size"] if rows else None,
        "threads": os.environ.get("OMP_NUM_THREADS"),
        "segment_s_mean": float(np.mean([r["segment_s"] for r in rows])),
        "crops_per_photo": total / max(len(rows), 1),
        **{f"dropped_{px}": sum(sum(r[f"under_{px}"]) for r in rows) / max(total, 1)
           for px in args.px},
        "rows": rows,
    }  # fmt: skip
    text = json.dumps(summary, indent=1)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text)
    print(json.dumps({k: v for k, v in summary.items() if k != "rows"}, indent=1))


if __name__ == "__main__":
    main()
