"""The 3-D selection's gate and smoothing, measured on the accuracy instrument's
scenes: for every seed's full-method chain and every query part, the
share of the selected Gaussians that lie on the query's part (their nearest truth
surface sample, `ptovs.synthetic.generate.nearest_parts`), under a grid of
`SelectOptions` (VISIBILITY:K: the visibility gate × neighbours smoothed over).

    python bench/select3d.py --seeds 0-8             # dev seeds: choose the defaults
    python bench/select3d.py --seeds 9-17 --grid 0:0 0.05:16   # test seeds: report

Reads the chains `bench/accuracy.py` trained (<work>/runs, configs/accuracy.toml);
builds what is missing. Writes <work>/select3d.json (each seed under its query
artifact key: a seed measured on another chain is measured again) and prints, per option pair, the
mean share over (seed, query), its cluster-bootstrap CI, the paired difference to
no gate and no smoothing, and the mean number selected.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, Results, instrument_chain, seed_list  # noqa: E402

GRID = ["0:0", "0:8", "0:16", "0:32", "0.02:0", "0.05:0", "0.1:0", "0.05:16", "0.1:16"]


def measure(chain, scene: Path, grid: list[str]) -> dict:
    """{text: {option: {share, selected}}} on one scene's full-method chain."""
    import torch

    from ptovs.apps import close_inputs
    from ptovs.field.query import Querier, SelectOptions
    from ptovs.stage import execute
    from ptovs.synthetic.generate import nearest_parts

    torch.set_num_threads(1)
    for st in chain.closure("train-male"):
        execute(chain, st).close()
    truth = json.loads((scene / "synthetic/truth/parts.json").read_text())
    texts = sorted(truth["query_parts"])
    inputs = chain.inputs("query")
    try:
        querier = Querier(inputs, chain.config("query"), texts)
        means = inputs.reconstruct.root()["means"]
        pid, _ = nearest_parts(scene, means)
        out: dict = {}
        for text in texts:
            parts = truth["query_parts"][text]
            out[text] = {}
            for opt in grid:
                vis, k = opt.split(":")
                t0 = time.perf_counter()
                sel = querier.select(text, SelectOptions(0.0, float(vis), int(k)))
                n = int(sel.mask.sum())
                out[text][opt] = {
                    "share": float(np.isin(pid[sel.mask], parts).mean()) if n else 0.0,
                    "selected": n,
                    "seconds": round(time.perf_counter() - t0, 3),
                }
        return out
    finally:
        from contextlib import suppress

        with suppress(Exception):
            close_inputs(inputs)


def main() -> None:
    from ptovs.stats import bootstrap_mean, paired_difference

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", nargs="+", default=["0-8"])
    ap.add_argument("--preset", default="small")
    ap.add_argument("--grid", nargs="+", default=GRID, help="VISIBILITY:K pairs")
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "accuracy")
    ap.add_argument("--work", type=Path, default=ROOT / "work" / "accuracy")
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "accuracy.toml")
    args = ap.parse_args()
    res = Results(args.work / "select3d.json")
    for seed in seed_list(args.seeds):
        name = f"{args.preset}_s{seed}"
        chain = instrument_chain(args.data / name, args.work, args.config)
        have = res.get(name, {})
        if have.get("key") == chain.key("query") and all(
            o in v for v in have["queries"].values() for o in args.grid
        ):
            continue
        queries = measure(chain, args.data / name, args.grid)
        res[name] = {"key": chain.key("query"), "queries": queries}
        res.save()
        print(name, "measured", flush=True)
    names = [f"{args.preset}_s{s}" for s in seed_list(args.seeds)]
    base_opt = args.grid[0]
    per = {n: res[n]["queries"] for n in names}
    base = {(n, t): v[base_opt]["share"] for n in names for t, v in per[n].items()}
    print(f"seeds {args.seeds}: {len(base)} (seed, query) clusters")
    print(
        "| visibility:k | share on the part [95 % CI] | Δ vs "
        + base_opt
        + " | selected |"
    )
    print("|---|---|---|---|")
    for opt in args.grid:
        cm = {(n, t): v[opt]["share"] for n in names for t, v in per[n].items()}
        sel = np.mean([v[opt]["selected"] for n in names for v in per[n].values()])
        m = bootstrap_mean(np.array(list(cm.values())))
        d = paired_difference(cm, base)
        print(f"| {opt} | {m.mean:.3f} [{m.lo:.3f}, {m.hi:.3f}] | "
              f"{d.mean:+.3f} [{d.lo:+.3f}, {d.hi:+.3f}] | {sel:.0f} |")  # fmt: skip


if __name__ == "__main__":
    main()
