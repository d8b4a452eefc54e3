"""Stability: the answers a user reads, where only the rounding of floats differs.

    make bench-stability                               # the demo, then the dev seeds
    python bench/stability.py --part demo              # the demo scene alone
    python bench/stability.py --part dev --seeds 0-8   # the accuracy instrument's dev seeds
    python bench/stability.py --report-only            # tables from the results file

Perturbations (the same photos and config; only how floats round differs):

  t1, t2, t3   --threads 1 / 2 / 3 (ptovs gives the same bits at every count: the
               demo runs all three to show it)
  avx2         2 threads, every kernel held to AVX2 as on a CPU without AVX-512: ATen
               (ATEN_CPU_CAPABILITY=avx2), oneDNN (ONEDNN_MAX_CPU_ISA=AVX2), MKL
               (MKL_CBWR=AVX2) and the compiled rasterizer (PTOVS_MARCH=x86-64-v3)
  avx2-t1      the same on 1 thread
  torch        2 threads, the pure-PyTorch rasterizer in every stage that renders
               (demo only: several times slower)

Each perturbation runs the whole chain in a work folder of its own (artifacts are keyed
by data and config, not by rounding, so a shared folder would hand one run's answers
to the next), then reads what a user reads: held-out PSNR (as is, NeRF-W), the
Gaussians, per (view, query) the chosen level, the peak score and the mask's area,
mIoU / mPA / mP, `select TEXT`'s count, level and score, and the style vote.

The report gives each answer's spread over the perturbations: the range of a number,
max / min of a count, the share of runs that agree with the most common choice. On
the dev seeds: each seed's mIoU range, their mean, and beside it the seed-to-seed
spread of mIoU (the standard deviation over seeds), which is what a single scene's
figure is already subject to.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, Results, seed_list  # noqa: E402  (same folder)

AVX2_ENV = {
    "ATEN_CPU_CAPABILITY": "avx2",
    "ONEDNN_MAX_CPU_ISA": "AVX2",
    "MKL_CBWR": "AVX2",
    "MKL_ENABLE_INSTRUCTIONS": "AVX2",
    "PTOVS_MARCH": "x86-64-v3",
}
RENDERING_STAGES = ("reconstruct", "render-appearances", "train-male", "query")
PERTURBATIONS: dict[str, dict] = {
    "t1": {"threads": 1},
    "t2": {"threads": 2},
    "t3": {"threads": 3},
    "avx2": {"threads": 2, "env": AVX2_ENV},
    "avx2-t1": {"threads": 1, "env": AVX2_ENV},
    "torch": {"threads": 2, "sets": [f"{s}.backend=torch" for s in RENDERING_STAGES]},
}
DEMO_TEXT = "Minaret"  # make demo's DEMO_TEXT
DEMO_CONFIG = str(ROOT / "configs" / "demo.toml")  # and its DEMO_CONFIG


def _ptovs(work: Path, threads: int, env: dict, sets: list[str], *args: str) -> str:
    """`ptovs ARGS` in a fresh process with this perturbation; its stdout."""
    cmd = [sys.executable, "-m", "ptovs", "-q", "--work-dir", str(work),
           "--threads", str(threads), *(f"--set={s}" for s in sets), *args]  # fmt: skip
    full_env = dict(os.environ, **env, PYTHONUNBUFFERED="1")
    proc = subprocess.run(cmd, capture_output=True, text=True, env=full_env)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
    return proc.stdout


def answers(work: Path, scene: Path, text: str | None, style: bool) -> dict:
    """What a user reads from a finished chain in `work` (this process reads only)."""
    from ptovs.artifacts import Artifact, read_json_dataset
    from ptovs.metrics import read_metrics

    name = scene.name
    out: dict = {}
    (recon,) = sorted((work / name / "reconstruct").glob("*.h5"))
    with Artifact(recon) as a:
        m = read_json_dataset(a.root()["metrics_json"])
    out["psnr_test"] = m.get("psnr_test")
    out["psnr_test_nerfw"] = m.get("psnr_test_nerfw")
    out["gaussians"] = m.get("gaussians")
    (ev,) = sorted((work / name / "evaluate").glob("*.h5"))
    with Artifact(ev) as a:
        summary, pairs = read_metrics(a)
    out["miou"], out["mpa"], out["mp"] = (summary[k] for k in ("miou", "mpa", "mp"))
    (qa,) = sorted((work / name / "query").glob("*.h5"))
    with Artifact(qa) as a:
        meta = read_json_dataset(a.root()["meta_json"])
        scores = {v: a.read(v, ("score",))["score"] for v in meta["views"] if v in a}
    qi = {q: i for i, q in enumerate(meta["queries"])}
    out["pairs"] = {
        f"{p['view']}|{p['query']}": {
            "level": p["level"],
            "iou": round(p["iou"], 4),
            "area": p["pred_pixels"],
            "score": round(float(scores[p["view"]][qi[p["query"]]]), 4),
        }
        for p in pairs
    }
    if text:
        out["select"] = json.loads((work / name / "select.json").read_text())
    if style:
        rec = json.loads(
            (work / name / "style-out" / "male" / "style.json").read_text()
        )
        out["style"] = {"winner": rec["winner"], "votes": rec["votes"]}
    return out


def run_scene(
    label: str,
    scene: Path,
    work: Path,
    text: str | None,
    style: bool,
    config: str | None,
) -> dict:
    """The whole chain on `scene` under perturbation `label`, then its answers."""
    p = PERTURBATIONS[label]
    env, sets, threads = p.get("env", {}), p.get("sets", []), p["threads"]
    cfg = ["--config", config] if config else []
    t0 = time.perf_counter()
    _ptovs(work, threads, env, sets, *cfg, "evaluate", "--data", str(scene))
    if text:
        # writes select.json beside the PLY: count, level, score
        _ptovs(work, threads, env, sets, *cfg, "select", text, "--data", str(scene),
               "--out", str(work / scene.name / "select.ply"))  # fmt: skip
    if style:
        _ptovs(work, threads, env, sets, *cfg, "style", "--data", str(scene))
    res = answers(work, scene, text, style)
    res["seconds"] = round(time.perf_counter() - t0, 1)
    return res


# ------------------------------------------------------------------ spreads --
def spread_numbers(values: list[float]) -> float:
    v = [x for x in values if x is not None]
    return float(max(v) - min(v)) if v else float("nan")


def ratio_counts(values: list[int]) -> float:
    v = [x for x in values if x is not None]
    return float(max(v) / max(min(v), 1)) if v else float("nan")


def agreement(choices: list) -> float:
    """Share of runs that give the most common choice."""
    return Counter(choices).most_common(1)[0][1] / len(choices) if choices else 1.0


def scene_spread(runs: dict[str, dict]) -> dict:
    """Per answer, its spread over the perturbations of one scene."""
    rs = list(runs.values())
    out = {
        "runs": list(runs),
        "miou": [r["miou"] for r in rs],
        "miou_range": spread_numbers([r["miou"] for r in rs]),
        "psnr_test_range": spread_numbers([r["psnr_test"] for r in rs]),
        "psnr_nerfw_range": spread_numbers([r["psnr_test_nerfw"] for r in rs]),
        "gaussians_ratio": ratio_counts([r["gaussians"] for r in rs]),
    }
    keys = sorted(set.intersection(*(set(r["pairs"]) for r in rs)))
    if keys:
        lv = [agreement([r["pairs"][k]["level"] for r in rs]) for k in keys]
        out["level_agreement"] = float(np.mean(lv))
        out["level_flips"] = int(sum(a < 1 for a in lv))
        out["score_range_mean"] = float(
            np.mean(
                [spread_numbers([r["pairs"][k]["score"] for r in rs]) for k in keys]
            )
        )
        out["area_ratio_median"] = float(
            np.median([ratio_counts([r["pairs"][k]["area"] for r in rs]) for k in keys])
        )
        out["iou_range_mean"] = float(
            np.mean([spread_numbers([r["pairs"][k]["iou"] for r in rs]) for k in keys])
        )
        out["pairs"] = len(keys)
    if all("select" in r for r in rs):
        out["select"] = [r["select"]["selected"] for r in rs]
        out["select_ratio"] = ratio_counts(out["select"])
        out["select_levels"] = [r["select"]["level"] for r in rs]
    if all("style" in r for r in rs):
        out["style_winners"] = [r["style"]["winner"] for r in rs]
        out["style_agreement"] = agreement(out["style_winners"])
    return out


# -------------------------------------------------------------------- parts --
def part_demo(args: argparse.Namespace, res: Results) -> None:
    data = args.data / "demo"
    scene = data / "demo_s0"
    if not scene.is_dir():
        subprocess.run([sys.executable, "-m", "ptovs", "synth-scene", str(data),
                        "--preset", "demo", "--seed", "0"], check=True)  # fmt: skip
    demo = res.setdefault("demo", {})
    for label in args.demo_perturbations:
        if label in demo:
            continue
        print(f"demo {label} ...", flush=True)
        demo[label] = run_scene(label, scene, args.work / "demo" / label,
                                args.text, True, DEMO_CONFIG)  # fmt: skip
        res.save()


def part_dev(args: argparse.Namespace, res: Results) -> None:
    dev = res.setdefault("dev", {})
    config = str(ROOT / "configs" / "accuracy.toml")
    for seed in seed_list(args.seeds):
        scene = args.acc_data / f"small_s{seed}"
        if not scene.is_dir():
            subprocess.run([sys.executable, "-m", "ptovs", "synth-scene", str(args.acc_data),
                            "--preset", "small", "--seed", str(seed)], check=True)  # fmt: skip
        runs = dev.setdefault(str(seed), {})
        for label in args.dev_perturbations:
            if label in runs:
                continue
            print(f"dev seed {seed} {label} ...", flush=True)
            runs[label] = run_scene(label, scene, args.work / "dev" / label,
                                    None, False, config)  # fmt: skip
            res.save()


# ------------------------------------------------------------------- report --
def report(res: Results) -> None:
    demo = res.get("demo", {})
    if len(demo) >= 2:
        s = scene_spread(demo)
        res["demo_spread"] = s
        print("\nDemo (the demo scene), per perturbation:")
        print(
            "| run | mIoU / mPA / mP | select | level | style | held-out PSNR / NeRF-W |"
        )
        print("|---|---|---|---|---|---|")
        for k, r in demo.items():
            sel = r.get("select", {})
            print(f"| {k} | {r['miou']:.3f} / {r['mpa']:.3f} / {r['mp']:.3f} | "
                  f"{sel.get('selected')} of {sel.get('gaussians')} | {sel.get('level')} | "
                  f"{r.get('style', {}).get('winner')} | "
                  f"{r['psnr_test']:.2f} / {r['psnr_test_nerfw']:.2f} |")  # fmt: skip
        print(f"\nmIoU range {s['miou_range']:.3f}; select max/min {s.get('select_ratio', 0):.2f}; "
              f"level agreement {s.get('level_agreement', 1):.2f} ({s.get('level_flips')} "
              f"pairs flip); score range {s.get('score_range_mean', 0):.3f}; "
              f"mask area max/min (median) {s.get('area_ratio_median', 0):.2f}")  # fmt: skip
    dev = res.get("dev", {})
    per_seed = {k: scene_spread(v) for k, v in dev.items() if len(v) >= 2}
    if per_seed:
        ranges = [s["miou_range"] for s in per_seed.values()]
        base = [v[next(iter(v))]["miou"] for v in dev.values() if v]
        res["dev_spread"] = {
            "seeds": list(per_seed),
            "miou_range": ranges,
            "miou_range_mean": float(np.mean(ranges)),
            "seed_sd": float(np.std(base, ddof=1)) if len(base) > 1 else None,
            "level_flips": [s.get("level_flips") for s in per_seed.values()],
            "pairs": [s.get("pairs") for s in per_seed.values()],
        }
        d = res["dev_spread"]
        print(
            "\nDev seeds, per seed: mIoU per perturbation, range, level flips / pairs"
        )
        for k, s in per_seed.items():
            print(f"  seed {k}: {' '.join(f'{x:.3f}' for x in s['miou'])}  range "
                  f"{s['miou_range']:.3f}  flips {s.get('level_flips')}/{s.get('pairs')}")  # fmt: skip
        print(f"mean range {d['miou_range_mean']:.3f}; seed-to-seed SD {d['seed_sd']}")
    res.save()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--part", choices=("demo", "dev"), nargs="*", default=["demo", "dev"]
    )
    ap.add_argument("--seeds", nargs="+", default=["0-8"], help="dev seeds")
    ap.add_argument("--demo-perturbations", nargs="+", default=list(PERTURBATIONS),
                    choices=list(PERTURBATIONS))  # fmt: skip
    ap.add_argument("--dev-perturbations", nargs="+", default=["t2", "avx2"],
                    choices=list(PERTURBATIONS))  # fmt: skip
    ap.add_argument("--text", default=DEMO_TEXT, help="the demo's select phrase")
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "stability")
    ap.add_argument("--acc-data", type=Path, default=ROOT / "data" / "accuracy")
    ap.add_argument("--work", type=Path, default=ROOT / "work" / "stability")
    ap.add_argument(
        "--out", type=Path, default=ROOT / "work" / "stability" / "stability.json"
    )
    ap.add_argument("--report-only", action="store_true")
    ap.add_argument("--merge", type=Path, nargs="*", default=[],
                    help="results files of runs made apart (e.g. one per perturbation, "
                    "in parallel), merged into --out first")  # fmt: skip
    args = ap.parse_args()
    res = Results(args.out)
    for extra in args.merge:
        other = json.loads(extra.read_text())
        for part in ("demo", "dev"):
            for k, v in other.get(part, {}).items():
                if part == "dev":
                    res.setdefault(part, {}).setdefault(k, {}).update(v)
                else:
                    res.setdefault(part, {})[k] = v
    if not args.report_only:
        if "demo" in args.part:
            part_demo(args, res)
        if "dev" in args.part:
            part_dev(args, res)
    report(res)


if __name__ == "__main__":
    main()
