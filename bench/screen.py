"""How often the generator's answerability screen redraws or drops a part (issue 20).

    python bench/screen.py --presets tiny small bench scale --seeds 50

Plans each (preset, seed) as `ptovs synth-scene` does (`plan_scene`: world,
cameras, evaluation views, screen; no photos rendered) and counts the screen's
verdicts: parts that passed as drawn, were redrawn (and after how many draws),
were dropped (no longer queries) or are labelled in no evaluation view. Also the
queries per scene and the plan's time. Two worker processes.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path


def _one(preset: str, seed: int) -> dict:
    from ptovs.synthetic.generate import plan_scene

    t0 = time.perf_counter()
    plan = plan_scene(preset, seed)
    return {
        "seconds": time.perf_counter() - t0,
        "queries": len(plan.queries),
        "verdicts": [(v.status, v.attempt, v.median) for v in plan.screen.values()],
    }


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--presets", nargs="+", default=["tiny", "small", "bench", "scale"])
    ap.add_argument("--seeds", type=int, default=50, help="seeds 0 .. N-1")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    print("| preset | seeds | labelled parts | passed | redrawn (mean draws) | "
          "dropped | unlabelled | queries per scene | plan s per seed |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    out = {}
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(args.jobs, mp_context=ctx) as ex:
        for preset in args.presets:
            seeds = range(args.seeds)
            rows = list(ex.map(_one, [preset] * len(seeds), seeds))
            st = [v for r in rows for v in r["verdicts"]]
            n = {k: sum(s == k for s, _, _ in st) for k in
                 ("pass", "redrawn", "dropped", "unseen")}  # fmt: skip
            lab = len(st) - n["unseen"]
            draws = [a for s, a, _ in st if s == "redrawn"]
            q = [r["queries"] for r in rows]
            print(
                f"| {preset} | {len(rows)} | {lab} | {n['pass']} ({n['pass'] / lab:.0%}) "
                f"| {n['redrawn']} ({n['redrawn'] / lab:.0%}; "
                f"{sum(draws) / max(len(draws), 1):.1f}) | {n['dropped']} "
                f"({n['dropped'] / lab:.1%}) | {n['unseen']} | "
                f"{sum(q) / len(q):.1f} ({min(q)}–{max(q)}) | "
                f"{sum(r['seconds'] for r in rows) / len(rows):.1f} |",
                flush=True,
            )
            out[preset] = {"counts": n, "draws": draws, "queries": q}
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
