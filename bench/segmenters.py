"""What a SAM-class segmenter costs a CPU per photo: SAM 2.1 hiera tiny / small
against SAM ViT-B, all through ptovs' own generator loop (ptovs.segment.generator).

    PYTHONPATH=src python bench/segmenters.py --out work/segmenters.json
    PYTHONPATH=src python bench/segmenters.py --out work/s.json --models tiny \\
        --sizes 512x384 --points 8 16 32 --repeat 3

Random weights (seeded; no checkpoint is downloaded): the networks' arithmetic is the
trained models', the masks are not. Each photo runs the whole automatic generator
(`segment`: one encoder pass per crop, the point grid decoded in batches of 64, SAM's
filters, box and mask NMS, painting) with `crop_n_layers` crop layers; the seconds
are split into the encoder (`set_image`), the point decoding (`predict`, which
includes upsampling each batch's logits to the photo) and the rest (filters, NMS,
painting; few masks survive random weights' IoU and stability filters, so the rest
is a low bound). Each setting runs `--repeat` times, the settings interleaved so a
change in the machine's load hits all of them; the first run of each includes the
warm-up. Reported: min and median seconds, and the split of the median run.
The machine may be shared: its load average is recorded before and after.
Needs the extras [sam2] (SAM 2.1) and [sam] (ViT-B).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import numpy as np
import torch

SAM2 = ("tiny", "small", "base_plus", "large")
SAM1 = ("vit_b", "vit_l", "vit_h")


def photo(h: int, w: int, seed: int = 0) -> np.ndarray:
    """A smooth random photo-like image (blobs of colour and edges)."""
    import cv2

    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (max(h // 32, 1), max(w // 32, 1), 3), np.uint8)
    img = cv2.resize(small, (w, h), interpolation=cv2.INTER_NEAREST)
    return cv2.GaussianBlur(img, (0, 0), 3)


class Timed:
    """A `PointPredictor` that adds up the seconds of its encoder and decoder."""

    def __init__(self, inner) -> None:
        self.inner = inner
        self.mask_threshold = inner.mask_threshold
        self.encoder = self.decoder = 0.0

    def set_image(self, image: np.ndarray) -> None:
        t0 = time.perf_counter()
        self.inner.set_image(image)
        self.encoder += time.perf_counter() - t0

    def predict(self, points: np.ndarray):
        t0 = time.perf_counter()
        out = self.inner.predict(points)
        self.decoder += time.perf_counter() - t0
        return out

    def reset(self) -> None:
        self.inner.reset()


def segmenter(model: str, points: int, crop_layers: int):
    torch.manual_seed(0)
    opts = dict(points_per_side=points, crop_n_layers=crop_layers)
    if model in SAM2:
        from ptovs.segment.sam2 import Sam2Segmenter, build_sam2_model

        return Sam2Segmenter(model=build_sam2_model(model), **opts)
    from ptovs.compat import import_backend
    from ptovs.segment.sam import SamSegmenter

    sa = import_backend("segment_anything")
    return SamSegmenter(model=sa.sam_model_registry[model](checkpoint=None), **opts)


def one_run(seg, img: np.ndarray) -> dict:
    timed = Timed(seg.points)
    seg.points = timed
    t0 = time.perf_counter()
    levels = seg.segment(img)
    total = time.perf_counter() - t0
    seg.points = timed.inner
    return dict(
        total=total,
        encoder=timed.encoder,
        decoder=timed.decoder,
        rest=total - timed.encoder - timed.decoder,
        segments=[lv.n for lv in levels],
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--models", nargs="+", default=["tiny", "small", "vit_b"])
    ap.add_argument("--sizes", nargs="+", default=["700x467", "512x384"], help="WxH")
    ap.add_argument("--points", nargs="+", type=int, default=[16])
    ap.add_argument("--crop-layers", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    settings = [(m, s, p) for m in args.models for s in args.sizes for p in args.points]
    segs = {m: {} for m in args.models}
    runs: dict[str, list[dict]] = {}
    load_before = os.getloadavg()
    with torch.inference_mode():
        for r in range(args.repeat):
            for model, size, pts in settings:
                w, h = map(int, size.split("x"))
                if pts not in segs[model]:
                    segs[model][pts] = segmenter(model, pts, args.crop_layers)
                key = f"{model} {size} {pts}pts"
                res = one_run(segs[model][pts], photo(h, w))
                runs.setdefault(key, []).append(res)
                print(f"[{r}] {key}: {res['total']:.1f} s (encoder "
                      f"{res['encoder']:.1f}, decoder {res['decoder']:.1f})",
                      flush=True)  # fmt: skip
    summary = {}
    for key, rs in runs.items():
        totals = [x["total"] for x in rs]
        med = sorted(rs, key=lambda x: x["total"])[len(rs) // 2]
        summary[key] = dict(
            min=min(totals),
            median=statistics.median(totals),
            median_split={k: med[k] for k in ("encoder", "decoder", "rest")},
            segments=med["segments"],
            runs=rs,
        )
    out = dict(
        threads=args.threads,
        crop_layers=args.crop_layers,
        repeat=args.repeat,
        cpus=os.cpu_count(),
        loadavg_before=load_before,
        loadavg_after=os.getloadavg(),
        torch=torch.__version__,
        date=time.strftime("%Y-%m-%d %H:%M"),
        results=summary,
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1))
    print(json.dumps({k: [round(v["min"], 1), round(v["median"], 1)]
                      for k, v in summary.items()}, indent=1))  # fmt: skip


if __name__ == "__main__":
    main()
