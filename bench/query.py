"""Benchmark query and evaluate (issue 11 targets).

python bench/query.py --parts decode speed --seeds 0       # table vs exact decode; one text, one view
python bench/query.py --parts eval --seeds 0 1 2           # every variant through the CLI
python bench/query.py --parts report                       # tables + plot from the JSON

Parts:
  decode  on the labelled views of bench seed s (the default chain): cosines of the
          table decode against exact decoding (max / mean error), how many mask
          pixels change, mIoU both ways, and the decode time of each
  speed   one text on one view (4 appearances × 3 levels, bench resolution): render,
          decode, relevancy-to-mask, median of 10 warm runs; and the cold start
          (loading the field and the AE, the text embeddings, the table)
  features2d  the same query pipeline on the photos' 2-D segment features (raw and
          through the AE; originals and all appearances): what the encoder allows
  eval    per seed, `ptovs evaluate --variant V` in a fresh process for every
          variant (full method, LangSplat baselines, Table 3 rows, budgets) and the
          clean-feature oracle (features of the world re-rendered at the train
          cameras, neutral light, no occluders, imported into the langsplat-wild
          recipe); metrics and the summed stage times of each variant's chain
  report  mean ± spread over seeds as Markdown, and a speed-against-error plot
          (PNG: time of the language stages vs mIoU, one point per variant)

Results go to <work>/bench_query.json; the plot to docs/img/speed_vs_miou.png.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from reconstruct import _ptovs, _scene  # noqa: E402  (same folder)

ROOT = Path(__file__).resolve().parents[1]

EVAL_VARIANTS = (  # cheapest and most telling first: a cut-short run keeps them
    "male",
    "langsplat",
    "langsplat-wild",
    "oracle",  # the clean-feature oracle (built by make_oracle)
    "no-bg-filter",
    "imglvlmax",
    "pixmax",
    "pixavg",
    "pixweighted",
    "no-multi-appearance",
    "no-tum-aum",
    "no-tum",
    "no-aum",
    "budget-300",
    "budget-3k",
    "no-uncertainty-ae",
    "tau-0.85",
    "tau-0.95",
    "no-tau-u",
)


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

    from ptovs.field.relevancy import answer
    from ptovs.scene import load_labels
    from ptovs.stages.evaluate import pair_metrics
    from ptovs.stages.query import Config, Querier, resolve_queries

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
    from ptovs.field.relevancy import finish
    from ptovs.stages.query import Config, Querier, resolve_queries

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


def features2d_part(work: Path, scene: Path) -> dict:
    """The query pipeline on the photos' own 2-D segment features (no field):
    raw 512-d features and AE-reconstructed ones, originals and all 4 appearances.
    An upper bound of what the 3-D field can answer with this encoder."""
    import torch

    from ptovs.encoders.synthetic import SyntheticEncoder
    from ptovs.features import SegmentFeatures
    from ptovs.field.relevancy import (
        BACKGROUND_PHRASES,
        CANONICAL,
        QuerySettings,
        answer,
    )
    from ptovs.scene import label_categories, load_labels
    from ptovs.stages.evaluate import pair_metrics
    from ptovs.stages.train_ae import load_autoencoder

    chain = _chain(work, scene, "male")
    sc = chain.scene.load()
    fe, ae_art = chain.inputs_of("extract-features"), chain.inputs_of("train-ae")
    ae = load_autoencoder(ae_art).eval()
    queries = label_categories(sc)
    phrases = list(dict.fromkeys([*queries, *CANONICAL, *BACKGROUND_PHRASES]))
    emb = torch.from_numpy(SyntheticEncoder.from_scene(sc.root).encode_texts(phrases))
    idx = {p: i for i, p in enumerate(phrases)}
    canon = [idx[p] for p in CANONICAL]
    bg = [idx[p] for p in BACKGROUND_PHRASES]
    res = {}
    for mode in ("raw_orig", "raw_all", "ae_orig", "ae_all"):
        ious = []
        apps = ["orig"] if mode.endswith("orig") else ["orig", "nov1", "nov2", "nov3"]
        for view in sc.labelled_views():
            d = fe[view.name]
            maps = []
            for a in apps:
                sf = SegmentFeatures.from_view(d, a)
                levels = []
                for lv in range(sf.levels):
                    f, valid = sf.dense(lv)
                    f = torch.from_numpy(f).float()
                    if mode.startswith("ae"):
                        with torch.no_grad():
                            flat = f.reshape(-1, f.shape[-1])
                            f = ae.decode(ae.encode(flat)).reshape(f.shape)
                    c = f @ emb.float().T
                    c[~torch.from_numpy(valid)] = 0
                    levels.append(c)
                maps.append(torch.stack(levels))
            cos = torch.stack(maps, 1)  # [L, N, H, W, K]
            gts = load_labels(sc, view, cos.shape[2:4])
            qidx = [idx[q] for q in gts]
            for cat, gt in gts.items():
                r = answer(cos, idx[cat], canon, bg, QuerySettings(), qidx)
                ious.append(pair_metrics(r.mask, gt)["iou"])
        res[mode] = float(np.mean(ious))
        print("features2d", mode, round(res[mode], 3), flush=True)
    return res


def make_oracle(work: Path, scene: Path) -> Path:
    """LangSplat feature folder of the clean re-rendered train views (cached)."""
    import cv2

    from ptovs.synthetic.generate import load_truth, rerender

    feats = work / "oracle" / scene.name / "features"
    if (feats / "done").exists():
        return feats
    clean = work / "oracle" / "data" / scene.name
    if clean.exists():
        shutil.rmtree(clean)
    shutil.copytree(scene, clean, ignore=shutil.ignore_patterns("images"))
    (clean / "dense" / "images").mkdir(parents=True)
    world, cams = load_truth(scene)
    for rec in cams["images"]:
        view, _ = rerender(world, rec, appearance="neutral", occluders="none")
        cv2.imwrite(
            str(clean / "dense" / "images" / rec["name"]),
            cv2.cvtColor(view.image, cv2.COLOR_RGB2BGR),
            [cv2.IMWRITE_JPEG_QUALITY, 95],
        )
    ow = work / "oracle" / "work"
    sets = ["--set", "extract-features.images=orig"]
    _ptovs(ow, *sets, "extract-features", "--data", str(clean))
    _ptovs(ow, *sets, "export-features", "--data", str(clean), "--out", str(feats))
    (feats / "done").write_text("ok")
    return feats


def eval_part(
    work: Path, scene: Path, variants: list[str], oracle: bool, res: dict, save
) -> dict:
    """Fills `res` {label: figures} one variant at a time, calling save() after each."""
    runs = []
    for v in variants:
        if v != "oracle":
            runs.append((v, v, []))
        elif oracle:
            feats = make_oracle(work.parent, scene)
            sets = ["--set", f"extract-features.import_dir={feats}"]
            runs.append(("oracle", "langsplat-wild", sets))
    for label, variant, sets in runs:
        out_dir = work.parent / "eval" / scene.name / label
        wall, rss, _ = _ptovs(
            work, "evaluate", "--data", str(scene), "--variant", variant, *sets,
            "--out", str(out_dir),
        )  # fmt: skip
        report = json.loads((out_dir / "evaluate.json").read_text())
        metrics = report["results"][variant][scene.name]
        extra = {}
        for item in sets[1::2]:
            stage, _, kv = item.partition(".")
            extra.setdefault(stage, []).append(kv)
        chain = _chain(work, scene, variant, extra)
        secs = _stage_seconds(chain, "evaluate")
        res[label] = {
            "variant": variant,
            "miou": metrics["miou"],
            "mpa": metrics["mpa"],
            "mp": metrics["mp"],
            "pairs": metrics["pairs"],
            "per_query_miou": metrics["per_query_miou"],
            "stage_s": secs,
            "total_s": round(sum(secs.values()), 1),
            "wall_s": round(wall, 1),
            "peak_rss_mb": round(rss),
        }
        print(label, json.dumps(res[label]), flush=True)
        save()
    return res


LANGUAGE = ("train-ae", "train-male", "query", "evaluate")


def report(results: dict, plot: Path) -> str:
    """Markdown rows (mean ± half-range over seeds) and the speed-against-error plot.

    Time is given twice: the language stages (train-ae, train-male, query, evaluate:
    what differs between most variants) and the whole chain as recorded in the
    artifacts (each stage's own run time when it was built).
    """
    from ptovs.variants import TABLE3_ROWS

    seeds = sorted(k for k in results if k.startswith("eval_s"))
    labels = list(dict.fromkeys(lab for s in seeds for lab in results[s]))
    lines = [
        "| variant | Table 3 row | mIoU | mPA | mP | language stages (s) | whole chain (s) | seeds |",
        "|---|---|---|---|---|---|---|---|",
    ]
    points = []
    for lab in labels:
        rows = [results[s][lab] for s in seeds if lab in results[s]]
        for r in rows:
            r["language_s"] = sum(r["stage_s"].get(k, 0.0) for k in LANGUAGE)

        def ms(key, rows=rows):
            v = np.array([r[key] for r in rows], float)
            return v.mean(), (v.max() - v.min()) / 2 if len(v) > 1 else 0.0

        cells = [f"{m:.3f} ± {d:.3f}" for m, d in (ms("miou"), ms("mpa"), ms("mp"))]
        lang, dl = ms("language_s")
        tot, dt = ms("total_s")
        row = TABLE3_ROWS.get(lab, "")
        lines.append(
            f"| {lab} | {row} | "
            + " | ".join(cells)
            + f" | {lang:.0f} ± {dl:.0f} | {tot:.0f} ± {dt:.0f} | {len(rows)} |"
        )
        # paired: the full method's mean over every seed plus this variant's mean
        # difference to it on the seeds the variant has, so a variant measured on
        # fewer seeds is not compared with a different set of landmarks
        full = {s: results[s]["male"]["miou"] for s in seeds if "male" in results[s]}
        diffs = [results[s][lab]["miou"] - full[s] for s in seeds
                 if lab in results[s] and s in full]  # fmt: skip
        y = np.mean(list(full.values())) + np.mean(diffs) if diffs else ms("miou")[0]
        points.append(
            (f"{lab} ({len(rows)})" if len(rows) < len(seeds) else lab, lang, y)
        )
    if points:
        _plot(points, plot)
    return "\n".join(lines)


def _plot(points: list[tuple[str, float, float]], path: Path) -> None:
    """Total time (log x) against mIoU, one labelled point per variant (OpenCV)."""
    import cv2

    W, H, m = 900, 560, 70
    img = np.full((H, W, 3), 255, np.uint8)
    ts = np.log10([max(p[1], 1.0) for p in points])
    ys = np.array([p[2] for p in points])
    x0, x1 = np.floor(ts.min() * 10) / 10 - 0.05, np.ceil(ts.max() * 10) / 10 + 0.05
    y0, y1 = max(0.0, ys.min() - 0.05), min(1.0, ys.max() + 0.05)

    def px(t, y):
        return (
            int(m + (t - x0) / (x1 - x0) * (W - 2 * m)),
            int(H - m - (y - y0) / (y1 - y0) * (H - 2 * m)),
        )

    cv2.rectangle(img, (m, m), (W - m, H - m), (0, 0, 0), 1)
    font = cv2.FONT_HERSHEY_SIMPLEX
    for k in range(5):
        y = y0 + (y1 - y0) * k / 4
        p = px(x0, y)
        cv2.putText(
            img, f"{y:.2f}", (8, p[1] + 4), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA
        )
        t = x0 + (x1 - x0) * k / 4
        q = px(t, y0)
        cv2.putText(
            img,
            f"{10**t:.0f}s",
            (q[0] - 15, H - m + 18),
            font,
            0.4,
            (0, 0, 0),
            1,
            cv2.LINE_AA,
        )
    cv2.putText(
        img,
        "train-ae + train-male + query + evaluate (s, log)",
        (W // 2 - 200, H - 20),
        font,
        0.5,
        (0, 0, 0),
        1,
        cv2.LINE_AA,
    )
    cv2.putText(img, "mIoU (paired with the full method over seeds; (n): seeds measured)",
                (10, m - 20), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)  # fmt: skip
    order = sorted(range(len(points)), key=lambda i: points[i][0] == "male")
    for i in order:  # the full method last, on top
        (lab, _, y), t = points[i], ts[i]
        p = px(t, y)
        colour = (0, 0, 200) if lab == "male" else (200, 80, 0)
        cv2.circle(img, p, 5, colour, -1)
        cv2.putText(img, lab, (p[0] + 7, p[1] - 5), font, 0.38, colour, 1, cv2.LINE_AA)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), img)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--parts", nargs="+", default=["decode", "speed", "eval", "report"])
    ap.add_argument("--variants", nargs="+", default=list(EVAL_VARIANTS))
    ap.add_argument("--no-oracle", action="store_true")
    ap.add_argument("--data", type=Path, default=ROOT / "data")
    ap.add_argument("--work", type=Path, default=ROOT / "work" / "bench")
    ap.add_argument(
        "--plot", type=Path, default=ROOT / "docs" / "img" / "speed_vs_miou.png"
    )
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    out_path = args.work / "bench_query.json"
    results = json.loads(out_path.read_text()) if out_path.exists() else {}
    results["machine"] = dict(
        platform=platform.platform(),
        cpus=os.cpu_count(),
        date=time.strftime("%Y-%m-%d"),
    )

    def save():
        tmp = out_path.with_suffix(".tmp")
        tmp.write_text(json.dumps(results, indent=1))
        os.replace(tmp, out_path)

    work = args.work / "default"
    for seed in args.seeds:
        scene = _scene(args.data, seed)
        if "decode" in args.parts:
            results[f"decode_s{seed}"] = decode_part(work, scene)
            save()
        if "features2d" in args.parts:
            results[f"features2d_s{seed}"] = features2d_part(work, scene)
            save()
        if "speed" in args.parts:
            results[f"speed_s{seed}"] = speed_part(work, scene)
            save()
        if "eval" in args.parts:
            prev = results.setdefault(f"eval_s{seed}", {})
            eval_part(work, scene, args.variants, not args.no_oracle, prev, save)
    if "report" in args.parts or "eval" in args.parts:
        print(report(results, args.plot))


if __name__ == "__main__":
    main()
