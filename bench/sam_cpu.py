"""What SAM's multi-level masks cost a CPU user, per photo (issue 40).

    python bench/sam_cpu.py --out work/sam_cpu.json

SAM's automatic masks (ptovs.segment.sam, LangSplat's recipe) cost, per crop of the
photo, one image-encoder pass at 1024×1024 (ViT-B, -L or -H) and one prompt+mask
decoder call per batch of 64 grid points (the decoder is the same network for the
three encoders). With `crop_n_layers = 1` (LangSplat's setting) the photo is the
whole image plus 4 crops, each with the full point grid (downscale factor 1). So

    seconds ≈ crops × (encoder[model] + ceil(points² / 64) × decoder_batch)

This script measures the two parts on this machine's threads (random weights: no
checkpoint can be downloaded here; the arithmetic is the trained model's, the masks
are not, so SAM's filters keep few masks and the mask post-processing, which is
cheap next to the networks, is a low bound), then checks the sum against whole runs
of `SamSegmenter` at the cheaper settings (whose decoder share, SAM's filters
applied, is what the table uses), and prints the table for every model × points
per side (8, 16, 32) × crop layers (0, 1).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from extract_gpu import photo  # noqa: E402  (same folder)

MODELS = ("vit_b", "vit_l", "vit_h")
POINTS = (8, 16, 32)
CROP_LAYERS = (0, 1)
BATCH = 64


def _model(kind: str):
    from ptovs.compat import import_backend

    sa = import_backend("segment_anything")
    torch.manual_seed(0)
    return sa, sa.sam_model_registry[kind](checkpoint=None).eval()


def time_encoder(kind: str, repeat: int) -> float:
    sa, model = _model(kind)
    pred = sa.SamPredictor(model)
    img = photo(0)
    times = []
    with torch.inference_mode():
        for i in range(repeat + 1):
            t0 = time.perf_counter()
            pred.set_image(img)
            if i:
                times.append(time.perf_counter() - t0)
    return statistics.median(times)


def time_decoder(repeat: int) -> float:
    """One batch of 64 points through the prompt encoder and mask decoder, three
    masks each (multimask), with the IoU and stability filters' arithmetic."""
    from ptovs.compat import import_backend

    amg = import_backend("segment_anything.utils.amg")
    sa, model = _model("vit_b")
    pred = sa.SamPredictor(model)
    img = photo(0)
    times = []
    with torch.inference_mode():
        pred.set_image(img)
        pts = np.random.default_rng(0).random((BATCH, 2)) * [img.shape[1], img.shape[0]]
        pts = torch.as_tensor(pred.transform.apply_coords(pts, img.shape[:2]),
                              dtype=torch.float32)  # fmt: skip
        labels = torch.ones(BATCH, dtype=torch.int64)
        for i in range(repeat + 1):
            t0 = time.perf_counter()
            logits, iou, _ = pred.predict_torch(
                pts[:, None], labels[:, None], multimask_output=True, return_logits=True
            )
            for k in range(3):
                amg.calculate_stability_score(logits[:, k], model.mask_threshold, 1.0)
            if i:
                times.append(time.perf_counter() - t0)
    return statistics.median(times)


def whole(kind: str, points: int, crop_layers: int) -> float:
    from ptovs.segment.sam import SamSegmenter

    _, model = _model(kind)
    seg = SamSegmenter(model=model, points_per_side=points, crop_n_layers=crop_layers)
    seg.segment(photo(1))  # warm-up
    t0 = time.perf_counter()
    seg.segment(photo(2))
    return time.perf_counter() - t0


def predict(enc: float, dec: float, points: int, crop_layers: int) -> float:
    crops = 1 + 4 * crop_layers
    return crops * (enc + math.ceil(points * points / BATCH) * dec)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--check", nargs="+", default=["vit_b:8:0", "vit_b:16:0"],
                    help="whole runs to check the sum against (model:points:layers)")  # fmt: skip
    ap.add_argument("--out", type=Path, default=Path("work/sam_cpu.json"))
    args = ap.parse_args()
    res: dict = {"torch": torch.__version__, "threads": torch.get_num_threads()}
    res["decoder_batch_s"] = time_decoder(max(3, args.repeat))
    print(
        f"decoder, one batch of {BATCH} points: {res['decoder_batch_s']:.3f} s",
        flush=True,
    )
    res["encoder_s"] = {}
    for kind in MODELS:
        res["encoder_s"][kind] = time_encoder(kind, args.repeat)
        print(f"{kind} encoder pass: {res['encoder_s'][kind]:.2f} s", flush=True)
    res["check"] = []
    for item in args.check:
        kind, p, c = item.split(":")
        got = whole(kind, int(p), int(c))
        want = predict(res["encoder_s"][kind], res["decoder_batch_s"], int(p), int(c))
        res["check"].append({"model": kind, "points": int(p), "crop_layers": int(c),
                             "measured_s": got, "predicted_s": want})  # fmt: skip
        print(f"whole {item}: {got:.2f} s (predicted {want:.2f} s)", flush=True)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(res, indent=1))
    # the decoder's cost inside whole runs (SAM's filters drop most masks before
    # the stability score and the clean-up): what the table uses
    per = [(c["measured_s"] - (1 + 4 * c["crop_layers"]) * res["encoder_s"][c["model"]])
           / ((1 + 4 * c["crop_layers"]) * math.ceil(c["points"] ** 2 / BATCH))
           for c in res["check"]]  # fmt: skip
    res["decoder_in_runs_s"] = statistics.mean(per) if per else res["decoder_batch_s"]
    print(f"decoder batch inside whole runs: {res['decoder_in_runs_s']:.2f} s")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=1))
    print("\n| model | encoder pass (s) | " + " | ".join(
        f"{p}² pts, {c} crop layer{'s' if c != 1 else ''}" for c in CROP_LAYERS for p in POINTS
    ) + " |")  # fmt: skip
    print("|---" * (2 + len(POINTS) * len(CROP_LAYERS)) + "|")
    for kind in MODELS:
        enc = res["encoder_s"][kind]
        cells = [f"{predict(enc, res['decoder_in_runs_s'], p, c):.0f}"
                 for c in CROP_LAYERS for p in POINTS]  # fmt: skip
        print(f"| {kind} | {enc:.1f} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
