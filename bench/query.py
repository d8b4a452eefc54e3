"""Benchmark query decoding and speed (issue 11 targets).

python bench/query.py --parts decode speed --seeds 0       # table vs exact decode; one text, one view

Parts:
  decode  on the labelled views of bench seed s (the default chain): cosines of the
          table decode against exact decoding (max / mean error), how many mask
          pixels change, mIoU both ways, and the decode time of each
  speed   one text on one view (4 appearances × 3 levels, bench resolution): render,
          decode, relevancy-to-mask, median of 10 warm runs; and the cold start
          (loading the field and the AE, the text embeddings, the table)

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


def _stage_seconds(chain, stage: str) -> dict[str, float]:
    """run_s of every stage in the closure of `stage` (from the artifacts)."""
    out = {}
    for name in chain.closure(stage):
        art = chain.inputs_of(name)
        out[name] = json.loads(art.attrs["timings_json"])["run_s"]
        art.close()
    return out


def decode_part(work: Path, scene: Path) -> dict:
    import torch

    from ptovs.field.query import Querier, resolve_queries
    from ptovs.field.query import QueryConfig as Config
    from ptovs.field.relevancy import answer
    from ptovs.metrics import pair_metrics
    from ptovs.scene import load_labels

    chain = _chain(work, scene, "male")
    inputs = chain.inputs("query")
    sc = inputs.scene
    queries = resolve_queries(Config(), sc)
    exact = Querier(inputs, Config(decode="exact"), queries)
    t0 = time.perf_counter()
    table = Querier(inputs, Config(decode="table"), queries)
    _ = table.decoder.table
    build = time.perf_counter() - t0
    errs, smax, changed, total, t_exact, t_table = [], 0.0, 0, 0, [], []
    ious = {"exact": [], "table": []}
    qidx = [exact.index[q] for q in queries]
    for view in sc.labelled_views():
        t = time.perf_counter()  # the exact path, as answer_view runs it, keeping
        codes, alpha = exact.code_maps(view)  # its cosines for the error figures
        ce = exact.decoder(codes)
        support = (alpha >= exact.config.min_alpha).float()
        ra = [
            answer(ce, q, exact.canonical, exact.bg, exact.settings, qidx, support)
            for q in qidx
        ]
        t_exact.append(time.perf_counter() - t)
        errs.append((table.decoder(codes) - ce).abs().reshape(-1))
        t = time.perf_counter()
        rb = table.answer_view(view)
        t_table.append(time.perf_counter() - t)
        gts = load_labels(sc, view, ra[0].mask.shape)
        for q, a, b in zip(queries, ra, rb, strict=True):
            changed += int((a.mask != b.mask).sum())
            total += a.mask.size
            smax = max(smax, float(np.abs(a.smoothed - b.smoothed).max()))
            if q in gts and gts[q].any():
                ious["exact"].append(pair_metrics(a.mask, gts[q])["iou"])
                ious["table"].append(pair_metrics(b.mask, gts[q])["iou"])
    e = torch.cat(errs)
    res = {
        "table_size": table.decoder.size,
        "table_build_s": round(build, 3),
        "cos_err_max": float(e.max()),
        "cos_err_mean": float(e.mean()),
        "smoothed_err_max": smax,
        "mask_pixels_changed": changed,
        "mask_pixels": total,
        "mask_changed_fraction": changed / max(total, 1),
        "miou_exact": float(np.mean(ious["exact"])),
        "miou_table": float(np.mean(ious["table"])),
        "query_ms_per_view_exact": 1e3 * float(np.median(t_exact)),
        "query_ms_per_view_table": 1e3 * float(np.median(t_table)),
        "views": len(sc.labelled_views()),
    }
    print("decode", json.dumps(res), flush=True)
    return res


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
    ap.add_argument("--parts", nargs="+", default=["decode", "speed"],
                    choices=["decode", "speed"])  # fmt: skip
    ap.add_argument("--data", type=Path, default=ROOT / "data")
    ap.add_argument("--work", type=Path, default=ROOT / "work" / "bench")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    results = Results(args.work / "bench_query.json")
    save = results.save

    work = args.work / "default"
    for seed in args.seeds:
        scene = bench_scene(args.data, seed)
        if "decode" in args.parts:
            results[f"decode_s{seed}"] = decode_part(work, scene)
            save()
        if "speed" in args.parts:
            results[f"speed_s{seed}"] = speed_part(work, scene)
            save()


if __name__ == "__main__":
    main()
