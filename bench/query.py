"""Benchmark a query's speed: one text on one view.

python bench/query.py --seeds 0

On the largest labelled view of bench seed s (the default chain, built by
bench/extract.py and bench/train.py in the same --work): one text, 4 appearances ×
3 levels, at bench resolution; render, decode (the 64³ table lookup),
relevancy-to-mask, median of 10 warm runs; and the cold start (loading the field
and the AE, the text embeddings, the table).

Accuracy (every variant, the ceilings, the statistics) is bench/accuracy.py's.
Results go to <work>/bench_query.json.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, Results, bench_scene  # noqa: E402  (same folder)


def _chain(work: Path, scene: Path, variant: str, extra: dict | None = None):
    from ptovs.stage import Chain, RunContext, resolve_scene
    from ptovs.variants import variant_sets

    ctx = RunContext(work, {})  # as `ptovs` without --config (the CLI runs above)
    ref = resolve_scene(ctx, None, scene)
    return Chain(ctx, ref, variant_sets(variant, extra))


def speed_part(work: Path, scene: Path, reps: int = 10) -> dict:
    from ptovs.field.query import Querier, resolve_queries
    from ptovs.field.query import QueryConfig as Config
    from ptovs.field.relevancy import finish

    chain = _chain(work, scene, "male")
    t0 = time.perf_counter()
    inputs = chain.inputs("query")
    sc = inputs.scene
    text = resolve_queries(Config(), sc)[0]
    q = Querier(inputs, Config(queries=(text,)), [text])
    qi = q.index[text]
    _ = q.query_table(qi, (qi,))
    cold = time.perf_counter() - t0
    view = max(sc.labelled_views(), key=lambda v: v.width * v.height)  # the largest
    parts = {"render": [], "decode": [], "answer": [], "total": []}
    for _ in range(reps + 2):
        t = time.perf_counter()
        codes, alpha = q.code_maps(view)
        t1 = time.perf_counter()
        vals = q.decoder.lookup(codes, q.query_table(qi, (qi,)))
        t2 = time.perf_counter()
        finish(vals[..., 0], vals[..., 1], q.settings, (alpha >= 0.5).float())
        t3 = time.perf_counter()
        for k, v in zip(parts, (t1 - t, t2 - t1, t3 - t2, t3 - t), strict=True):
            parts[k].append(v)
    res = {k: round(1e3 * float(np.median(v[2:])), 1) for k, v in parts.items()}
    res = {f"{k}_ms": v for k, v in res.items()}
    res.update(
        cold_start_s=round(cold, 2),
        view=view.name,
        size=f"{view.width}x{view.height}",
        levels=len(q.levels),
        appearances=len(q.apps),
        gaussians=len(q.gaussians),
    )
    print("speed", json.dumps(res), flush=True)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--data", type=Path, default=ROOT / "data")
    ap.add_argument("--work", type=Path, default=ROOT / "work" / "bench")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    results = Results(args.work / "bench_query.json")
    save = results.save

    work = args.work / "default"
    for seed in args.seeds:
        scene = bench_scene(args.data, seed)
        results[f"speed_s{seed}"] = speed_part(work, scene)
        save()


if __name__ == "__main__":
    main()
