"""What each CPU-class image encoder costs here, in fp32 and bf16.

    python bench/encoders.py --out work/encoders.json                # the table's models
    python bench/encoders.py --models MobileCLIP2-S0 --threads 2 --crops 64

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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", nargs="+", default=list(MODELS))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--crops", type=int, default=64)
    ap.add_argument("--batch", type=int, default=32)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("work/encoders.json"))
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    rows = []
    for m in a.models:
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
