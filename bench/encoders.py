"""What each CPU-class image encoder costs here, in fp32 and bf16, and by runtime.

    python bench/encoders.py --out work/encoders.json                # the table's models
    python bench/encoders.py --models MobileCLIP2-S0 --threads 2 --crops 64
    python bench/encoders.py --runtimes --models MobileCLIP2-S0 ViT-B-16 \
        --crops 96 --out work/runtimes.json             # both: make bench-encoders

`--runtimes`: for each model, at 1 and then 2 threads in the same run, the fp32 image
tower's crops a second in PyTorch at a batch of 64 (the old default), in each
runtime at its own batch (`ptovs.encoders.runtimes.tower.BATCH`), and what
`runtime = "auto"` chose on 48 of the crops (with its reason), each runtime's max
|Δ| of unit features from PyTorch's.

For each open_clip model: random weights (the arithmetic of a trained model,
not its accuracy), built through ptovs's own wrapper (the model's own
preprocessing, MobileCLIP re-parameterised), then crops a second on `--threads`
threads for fp32 and for the bf16 image tower, best of `--repeats`, and the bf16
copy's agreement with fp32 on those crops (worst centred cosine, top-1 phrase
agreement: what `precision = "auto"` checks on a scene's own crops). Crops are
LangSplat crops of a synthetic landmark photo's segments, at the model's size.
Writes one JSON; docs/results.md quotes it.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import time
from pathlib import Path

import numpy as np
import torch

MODELS = ("ViT-B-32", "ViT-B-16", "MobileCLIP-S1", "MobileCLIP2-S0", "MobileCLIP2-S2")


def crops_for(size: int, n: int, seed: int = 0) -> np.ndarray:
    """n LangSplat-style crops: blobs of texture on black, at size x size."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size] / size
    out = np.zeros((n, size, size, 3), np.float32)
    for i in range(n):
        c = rng.random(3)
        r = rng.uniform(0.2, 0.5)
        m = (xx - rng.uniform(0.3, 0.7)) ** 2 + (
            yy - rng.uniform(0.3, 0.7)
        ) ** 2 < r * r
        tex = rng.random((size, size, 1)) * 0.3
        out[i][m] = np.clip(c + tex[m] - 0.15, 0, 1)
    return out


def measure(model: str, crops: int, repeats: int, batch: int) -> dict:
    from ptovs.encoders.openclip import (
        CHECK_PHRASES,
        OpenClipEncoder,
        centred_agreement,
    )

    torch.manual_seed(0)
    enc = OpenClipEncoder(model, random_weights=True, batch_size=batch)
    x = crops_for(enc.size, crops)
    row: dict = {"model": model, "size": enc.size, "crops": crops, "batch": batch}
    feats = {}
    for prec in ("fp32", "bf16"):
        enc._encode(x[:batch], prec)  # warm-up
        best = float("inf")
        for _ in range(repeats):
            t = time.perf_counter()
            feats[prec] = enc._encode(x, prec)
            best = min(best, time.perf_counter() - t)
        row[f"{prec}_crops_per_s"] = round(crops / best, 2)
    row.update(centred_agreement(feats["fp32"], feats["bf16"],
                                 enc.encode_texts(list(CHECK_PHRASES))))  # fmt: skip
    return row


# the pretrained tag whose preprocessing and activation each model is built with
TAGS = {"ViT-B-16": "laion2b_s34b_b88k", "ViT-B-32": "datacomp_xl_s13b_b90k",
        "MobileCLIP-S1": "datacompdr", "MobileCLIP2-S0": "dfndr2b",
        "MobileCLIP2-S2": "dfndr2b"}  # fmt: skip


def _rate(enc, x: np.ndarray, repeats: int) -> tuple[float, np.ndarray]:
    """(crops a second, best of `repeats` after a warm-up pass; the features)."""
    enc.encode_images(x)
    best, out = float("inf"), None
    for _ in range(repeats):
        t = time.perf_counter()
        out = enc.encode_images(x)
        best = min(best, time.perf_counter() - t)
    return len(x) / best, out


def measure_runtimes(model: str, crops: int, repeats: int) -> list[dict]:
    """Rows of crops/s by runtime, at 1 and 2 threads (one process, one model)."""
    from ptovs.encoders import runtimes
    from ptovs.encoders.openclip import OpenClipEncoder

    torch.manual_seed(0)
    enc = OpenClipEncoder(model, random_weights=True, pretrained=TAGS.get(model, ""))
    x = crops_for(enc.size, crops)
    rows = []
    for threads in (1, 2):
        torch.set_num_threads(threads)
        enc.tower._loaded.clear()  # sessions are made for a thread count
        enc.tower.use("torch")
        enc.batch_size = 64
        rate, ref = _rate(enc, x, repeats)
        rows.append({"model": model, "threads": threads, "runtime": "torch",
                     "batch": 64, "crops_per_s": round(rate, 2), "max_abs_diff": 0.0})  # fmt: skip
        enc.batch_size = 0
        for name in runtimes.installed():
            enc.tower.use(name)
            rate, out = _rate(enc, x, repeats)
            rows.append({"model": model, "threads": threads, "runtime": name,
                         "batch": enc.tower.batch(0), "crops_per_s": round(rate, 2),
                         "max_abs_diff": float(np.abs(out - ref).max())})  # fmt: skip
        enc.tower.use("torch")
        t0 = time.perf_counter()
        report = enc.check_runtime(x[:48])
        own = enc.tower.batch(0)  # the chosen runtime's own batch
        chosen = next(r for r in rows if r["threads"] == threads and
                      r["runtime"] == report["runtime"] and r["batch"] == own)  # fmt: skip
        rows.append({"model": model, "threads": threads, "runtime": "auto",
                     "chose": report["runtime"], "reason": report["reason"],
                     "decision_s": round(time.perf_counter() - t0, 2),
                     "crops_per_s": chosen["crops_per_s"]})  # fmt: skip
        for r in rows[-(len(runtimes.installed()) + 2) :]:
            print(json.dumps(r), flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", nargs="+", default=list(MODELS))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--crops", type=int, default=64)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("work/encoders.json"))
    ap.add_argument("--runtimes", action="store_true",
                    help="crops/s by runtime at 1 and 2 threads instead")  # fmt: skip
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    rows = []
    for m in a.models:
        if a.runtimes:
            rows.extend(measure_runtimes(m, a.crops, a.repeats))
            continue
        rows.append(measure(m, a.crops, a.repeats, a.batch))
        print(json.dumps(rows[-1]), flush=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                            text=True).stdout.strip()  # fmt: skip
    meta = {"date": time.strftime("%Y-%m-%d"), "commit": commit, "threads": a.threads,
            "cpu": platform.processor() or platform.machine(), "nproc": os.cpu_count(),
            "torch": torch.__version__}  # fmt: skip
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
