"""Benchmark train-ae and train-male on the bench preset.

python bench/train.py --parts step                 # fast-path step on the raster scene
python bench/train.py --parts bench --seeds 0      # stages on bench (needs bench/extract.py's chain)

Parts:
  step   one train-male step (W·normalize(f), masked L1, Wᵀ·g, normalisation backward)
         on the rasterizer benchmark scene (docs/rasterizer.md §7: 1e5 Gaussians, 256²),
         4 appearances × 3 levels (D = 36) and one level (D = 12), against the same
         step through `render()`; median of 20 after 3 warm-ups
  bench  per seed, through the CLI in the bench work dir: train-ae and train-male
         (the defaults); wall time, peak RSS (GNU time) and the stages' own metrics

Results go to <work>/bench_train.json and are printed as markdown rows.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, Results, bench_scene, run_ptovs  # noqa: E402  (same folder)


def step_timing(n: int = 100_000, size: int = 256, reps: int = 20) -> dict:
    import torch

    from ptovs.field import language as lang
    from ptovs.raster import Camera, Gaussians, blend_weights

    g = torch.Generator().manual_seed(0)
    z = torch.rand(n, generator=g) * 4 + 2
    x = (torch.rand(n, generator=g) - 0.5) * z * 1.1
    y = (torch.rand(n, generator=g) - 0.5) * z * 1.1
    log_s = torch.rand(n, 3, generator=g) * math.log(6) + math.log(0.01)
    gauss = Gaussians(
        torch.stack((x, y, z), 1),
        torch.randn(n, 4, generator=g),
        torch.exp(log_s),
        torch.rand(n, generator=g) * 0.8 + 0.1,
    )
    K = torch.tensor([[size, 0.0, size / 2], [0.0, size, size / 2], [0.0, 0.0, 1.0]])
    cam = Camera(torch.eye(4), K, size, size)
    rng = np.random.default_rng(0)
    out = {}
    for n_lv, n_app in ((3, 4), (1, 4)):
        segs, codes = [], []
        for _ in range(n_app):  # 16 × 16-pixel blocks as segments
            block = (np.arange(size)[:, None] // 16) * (size // 16) + np.arange(size)[
                None
            ] // 16
            segs.append(
                np.stack([block + lv * 256 for lv in range(n_lv)]).astype(np.int16)
            )
            c = rng.normal(size=(256 * n_lv, 3)).astype(np.float32)
            codes.append(c / np.linalg.norm(c, axis=1, keepdims=True))
        u = rng.random((size, size)).astype(np.float32)
        t0 = time.perf_counter()
        bw = blend_weights(gauss, cam)
        view = lang.prepare_view(bw, segs, codes, u, u)
        build = time.perf_counter() - t0
        d = n_lv * n_app * 3
        scale = lang.slot_scale(size * size, n_lv, n_app, "paper")
        f = torch.randn(n, d, requires_grad=True)
        res = {
            "nnz": bw.nnz,
            "build_s": round(build, 3),
            "view_mb": round(view.nbytes / 2**20, 1),
        }
        for renderer in ("sparse", "raster"):
            times = []
            for i in range(reps + 3):
                f.grad = None
                t0 = time.perf_counter()
                lang.train_step(f, view, scale, renderer, gauss, cam)
                if i >= 3:
                    times.append(time.perf_counter() - t0)
                if renderer == "raster" and i >= 8:
                    break
            res[f"{renderer}_ms"] = round(1e3 * float(np.median(times)), 2)
        out[f"D{d}"] = res
        print(f"| 1e5, 256², D={d} | {res} |", flush=True)
    return out


def _metrics(path: Path) -> dict:
    from ptovs.artifacts import Artifact, read_json_dataset

    with Artifact(path) as art:
        return read_json_dataset(art.root()["metrics_json"])


def _path(stdout: str) -> Path:
    return Path(stdout.strip().splitlines()[-1].split(": ", 1)[1])


def bench_seed(work: Path, scene: Path, force: bool) -> dict:
    res: dict = {}
    extra = ["--force"] if force else []
    for stage in ("train-ae", "train-male"):
        wall, rss, out = run_ptovs(work, stage, "--data", str(scene), *extra)
        res[stage] = {"wall_s": round(wall, 1), "peak_rss_mb": round(rss)}
        res[stage]["metrics"] = _metrics(_path(out))
        print(stage, json.dumps(res[stage]), flush=True)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--parts", nargs="+", default=["step", "bench"])
    ap.add_argument("--data", type=Path, default=ROOT / "data")
    ap.add_argument("--work", type=Path, default=ROOT / "work" / "bench")
    ap.add_argument("--force", action="store_true", help="retrain (timing)")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    # each seed's entry is replaced as a whole, others kept
    results = Results(args.work / "bench_train.json")
    save = results.save

    if "step" in args.parts:
        results["step"] = step_timing()
        save()
    if "bench" in args.parts:
        for seed in args.seeds:
            scene = bench_scene(args.data, seed)
            results[f"bench_s{seed}"] = bench_seed(
                args.work / "default", scene, args.force
            )
            save()


if __name__ == "__main__":
    main()
