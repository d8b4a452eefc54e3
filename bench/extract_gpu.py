"""What one photo costs the real extract-features backends: SAM ViT-H's multi-level
masks (ptovs.segment.sam, LangSplat's recipe: 32×32 points, one crop layer) and
OpenCLIP ViT-B-16 on the segment crops, on CUDA and on the CPU.

python bench/extract_gpu.py --devices cuda cpu --out extract_gpu.json

No weights can be downloaded here, so both models are randomly initialised: the
networks' arithmetic is the trained models', the masks are not. Two SAM settings
bound the mask post-processing: `filters on` (the default predicted-IoU and
stability filters; random weights pass few masks, so little NMS and clean-up: a low
bound) and `filters off` (every candidate mask goes on to NMS: a high bound). The
photo is 640×480 (a PT-OVS photo at the authors' r = 2 is 400-800 px wide); SAM
resizes to 1024 px whatever the size. Each figure is the median of --repeat photos
after one warm-up. The figures feed the on-paper cluster estimate in
docs/benchmarks.md ("Many scenes, many machines").
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))


def photo(seed: int, h: int = 480, w: int = 640) -> np.ndarray:
    """A smooth random photo-like image (blobs of colour and edges)."""
    import cv2

    rng = np.random.default_rng(seed)
    small = rng.integers(0, 256, (h // 32, w // 32, 3), dtype=np.uint8)
    img = cv2.resize(small, (w, h), interpolation=cv2.INTER_NEAREST)
    return cv2.GaussianBlur(img, (0, 0), 3)


def sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def time_sam(device: str, filters: bool, repeat: int) -> dict:
    from ptovs.compat import import_backend
    from ptovs.segment.sam import SamSegmenter

    sa = import_backend("segment_anything")
    torch.manual_seed(0)
    model = sa.sam_model_registry["vit_h"](checkpoint=None)
    kw = {} if filters else {"pred_iou_thresh": 0.0, "stability_score_thresh": 0.0}
    seg = SamSegmenter(model=model, device=device, **kw)
    times, masks = [], []
    for i in range(repeat + 1):
        img = photo(i)
        sync(device)
        t0 = time.perf_counter()
        levels = seg.segment(img)
        sync(device)
        if i:  # the first is a warm-up
            times.append(time.perf_counter() - t0)
            masks.append([len(lv.masks) for lv in levels])
    return {"s_per_photo": round(statistics.median(times), 3),
            "masks_s_m_l": masks[-1], "runs": [round(t, 3) for t in times]}  # fmt: skip


def time_clip(device: str, crops: int, repeat: int) -> dict:
    from ptovs.encoders.openclip import OpenClipEncoder

    torch.manual_seed(0)
    enc = OpenClipEncoder("ViT-B-16", device=device, batch_size=64, random_weights=True)
    rng = np.random.default_rng(0)
    batch = rng.random((crops, 224, 224, 3), dtype=np.float32)
    times = []
    for i in range(repeat + 1):
        sync(device)
        t0 = time.perf_counter()
        enc.encode_images(batch)
        sync(device)
        if i:
            times.append(time.perf_counter() - t0)
    return {"crops": crops, "s": round(statistics.median(times), 3)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", nargs="+", default=["cuda", "cpu"])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--cpu-repeat", type=int, default=1)
    ap.add_argument("--crops", type=int, default=256, help="segment crops a photo")
    ap.add_argument("--out", type=Path, default=Path("extract_gpu.json"))
    args = ap.parse_args()
    res = {"torch": torch.__version__, "threads": torch.get_num_threads()}
    if torch.cuda.is_available():
        res["gpu"] = torch.cuda.get_device_name()
    for device in args.devices:
        n = args.repeat if device == "cuda" else args.cpu_repeat
        for filters in (True, False):
            key = f"{device}/sam_vit_h/filters_{'on' if filters else 'off'}"
            res[key] = time_sam(device, filters, n)
            print(key, res[key], flush=True)
        res[f"{device}/clip_vit_b16"] = time_clip(device, args.crops, n)
        print(device, res[f"{device}/clip_vit_b16"], flush=True)
        args.out.write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
