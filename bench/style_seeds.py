"""Style recognition over the accuracy instrument's seeds: does
`ptovs style` name each synthetic landmark's true style, and does it beat the raw
encoder that sees the photos themselves?

    python bench/style_seeds.py --seeds 0-17                 # after bench/accuracy.py
    python bench/style_seeds.py --seeds 0-17 --variants male lift paper

Per seed and variant, `ptovs style` on the instrument's chain (<work>/runs,
configs/accuracy.toml; missing stages are built) with its defaults: 20 seeded train
views, each voting by max score over the scene's five candidate styles. The
raw-encoder baseline (bench/common.py's `raw_style_votes`, the authors' raw-CLIP
baseline with the stand-in encoder) votes with the same views' whole photos and,
for reference, with the landmark alone under its truth mask. Each winner is the
most-voted style (ties: the first in the vocabulary's order).

Writes <work>/style_seeds.json (each seed and variant under its query artifact key:
one measured on another chain is measured again) and prints accuracy per half
(dev = first half of the list, as bench/accuracy.py) with a Wilson 95 % interval.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import (  # noqa: E402  (same folder)
    ROOT,
    Results,
    instrument_chain,
    raw_style_votes,
    run_ptovs,
    seed_list,
)


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval of a proportion k/n."""
    if n == 0:
        return 0.0, 1.0
    p = k / n
    mid = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, mid - half), min(1.0, mid + half)


def _winner(votes: dict[str, int]) -> str:
    return max(votes, key=lambda s: votes[s])  # first of equals: dict order


def measure(scene: Path, work: Path, config: Path, variant: str) -> dict:
    truth = json.loads((scene / "synthetic/truth/parts.json").read_text())["style"]
    out = work / "style" / scene.name / variant
    _, _, _ = run_ptovs(work / "runs", "--config", str(config), "style",
                        "--data", str(scene), "--variant", variant,
                        "--pictures", "0", "--out", str(out))  # fmt: skip
    rec = json.loads((out / "style.json").read_text())
    raw = raw_style_votes(scene, [v["view"] for v in rec["views"]])
    return {
        "true": truth,
        "winner": rec["winner"],
        "correct": rec["winner"] == truth,
        "true_rank": rec["ranking"].index(truth) + 1,
        "seconds": rec["seconds"],
        "raw_whole": _winner(raw["whole"]) == truth,
        "raw_landmark": _winner(raw["landmark"]) == truth,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", nargs="+", default=["0-17"])
    ap.add_argument("--dev", nargs="+", default=None,
                    help="dev seeds (default: the first half of --seeds)")  # fmt: skip
    ap.add_argument("--variants", nargs="+", default=["male"])
    ap.add_argument("--preset", default="small")
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "accuracy")
    ap.add_argument("--work", type=Path, default=ROOT / "work" / "accuracy")
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "accuracy.toml")
    args = ap.parse_args()
    seeds = seed_list(args.seeds)
    dev = seed_list(args.dev) if args.dev else seeds[: len(seeds) // 2]
    res = Results(args.work / "style_seeds.json")
    for seed in seeds:
        name = f"{args.preset}_s{seed}"
        for variant in args.variants:
            key = instrument_chain(args.data / name, args.work, args.config,
                                   variant).key("query")  # fmt: skip
            have = res.get(name, {}).get(variant, {})
            if have.get("key") == key:
                continue
            rec = measure(args.data / name, args.work, args.config, variant)
            res.setdefault(name, {})[variant] = {"key": key, **rec}
            res.save()
            print(name, variant, rec, flush=True)
    halves = {"dev": [s for s in seeds if s in dev],
              "test": [s for s in seeds if s not in dev], "all": seeds}  # fmt: skip
    print("| seeds | " + " | ".join(args.variants)
          + " | raw encoder, whole photo | raw encoder, landmark only |")  # fmt: skip
    print("|---" * (len(args.variants) + 3) + "|")
    for half, ss in halves.items():
        if not ss:
            continue
        recs = [res[f"{args.preset}_s{s}"] for s in ss]
        cells = [[r[v]["correct"] for r in recs] for v in args.variants]
        first = args.variants[0]
        cells += [[r[first]["raw_whole"] for r in recs],
                  [r[first]["raw_landmark"] for r in recs]]  # fmt: skip
        txt = []
        for c in cells:
            lo, hi = wilson(sum(c), len(c))
            txt.append(
                f"{sum(c)} of {len(c)} ({sum(c) / len(c):.0%}; {lo:.0%}–{hi:.0%})"
            )
        print(f"| {half} {ss[0]}–{ss[-1]} | " + " | ".join(txt) + " |")


if __name__ == "__main__":
    main()
