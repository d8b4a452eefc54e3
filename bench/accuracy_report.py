"""The accuracy instrument's report (bench/accuracy.py): its results read back, per
label the cluster-mean mIoU with its bootstrap interval and the paired difference
to the base, the tables of accuracy.md and the speed-against-error plot.

    from accuracy import load_results, summarise   # (bench/ is on sys.path)
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from accuracy_labels import ANSWERED, CEILINGS, CHAIN_LOSS, FEATURE_LABELS  # noqa: E402
from common import ROOT  # noqa: E402  (same folder)


def _result_path(work: Path, scene: str) -> Path:
    return work / "results" / f"{scene}.json"


def load_results(work: Path, preset: str, seeds: list[int]) -> dict[int, dict]:
    out = {}
    for s in seeds:
        path = _result_path(work, f"{preset}_s{s}")
        if path.is_file():
            out[s] = json.loads(path.read_text())
    return out


def _records(results: dict[int, dict], label: str, hard: bool | None = None) -> list:
    recs = []
    for seed, res in results.items():
        entry = res["labels"].get(label)
        if entry is None:
            continue
        for p in entry["pairs"]:
            if hard is not None and res["hard"].get(p["view"], False) != hard:
                continue
            recs.append({**p, "seed": seed})
    return recs


def summarise(results: dict[int, dict], labels: list[str], base: str = "male") -> dict:
    """Per label: cluster-mean mIoU / mPA / mP with CIs, the paired difference to
    `base` (the full method, or `male-truth` on truth segments), easy and hard views
    apart, and the language-stage time."""
    from ptovs.stats import bootstrap_mean, cluster_means, paired_difference

    out: dict = {}
    full = cluster_means(_records(results, base))
    for label in labels:
        recs = _records(results, label)
        if not recs:
            continue
        row: dict = {"seeds": len({r["seed"] for r in recs}), "pairs": len(recs)}
        for key, name in (("iou", "miou"), ("pa", "mpa"), ("p", "mp")):
            cm = cluster_means(recs, key)
            row[name] = bootstrap_mean(np.array(list(cm.values())))
        cm = cluster_means(recs)
        row["clusters"] = len(cm)
        if label != base and full:
            row["diff"] = paired_difference(cm, full)
        for hard in (False, True):
            sub = cluster_means(_records(results, label, hard))
            row["hard" if hard else "easy"] = (
                float(np.mean(list(sub.values()))) if sub else float("nan")
            )
        secs = [
            sum(
                v
                for k, v in res["labels"][label]["stage_s"].items()
                if k in ("train-ae", "train-male", "query", "evaluate")
            )
            if res["labels"][label]["stage_s"]
            else res["labels"][label]["wall_s"]
            for res in results.values()
            if label in res["labels"]
        ]
        row["language_s"] = float(np.mean(secs))
        out[label] = row
    return out


def unanswered(results: dict[int, dict], labels: list[str]) -> tuple[int, int, list]:
    """Clusters where every label's mean IoU is below ANSWERED."""
    from ptovs.stats import cluster_means

    per = {lab: cluster_means(_records(results, lab)) for lab in labels}
    clusters = sorted(set().union(*(set(v) for v in per.values())))
    bad = [c for c in clusters if all(per[lab].get(c, 0.0) < ANSWERED for lab in per)]
    return len(bad), len(clusters), bad


def chain_loss(results: dict[int, dict]) -> list[str]:
    """Per seed and overall: mIoU at each step of CHAIN_LOSS (cluster means)."""
    from ptovs.stats import cluster_means

    head = "| seed | " + " | ".join(CHAIN_LOSS) + " |"
    lines = [head, "|" + "---|" * (len(CHAIN_LOSS) + 1)]

    def cells(res_sub: dict[int, dict]) -> list[str]:
        out = []
        for lab in CHAIN_LOSS:
            cm = cluster_means(_records(res_sub, lab))
            out.append(f"{np.mean(list(cm.values())):.3f}" if cm else "–")
        return out

    for seed, res in results.items():
        lines.append(f"| {seed} | " + " | ".join(cells({seed: res})) + " |")
    lines.append("| **all** | " + " | ".join(cells(results)) + " |")
    return lines


def report(args: argparse.Namespace) -> str:
    results = load_results(args.work, args.preset, args.seeds)
    if not results:
        raise SystemExit(f"no results under {args.work / 'results'}; run first")
    dev = [s for s in args.dev if s in results]
    test = [s for s in args.seeds if s not in args.dev and s in results]
    labels = list(args.labels)
    md = [
        f"Preset `{args.preset}`, seeds {sorted(results)} (dev {dev}, test {test}); "
        f"config `{_rel(args.config)}`; {os.cpu_count()} cores "
        f"({platform.machine()}), {time.strftime('%Y-%m-%d')}.",
        "",
    ]
    md += _screen_lines(results)
    summaries = {}
    for half, seeds in (("dev", dev), ("test", test)):
        if not seeds:
            continue
        sub = {s: results[s] for s in seeds}
        summ = summarise(sub, labels, args.base)
        summaries[half] = summ
        md += ["", f"### {half} seeds {seeds}", ""]
        md += _main_table(summ, args.base)
        bad, total, which = unanswered(sub, labels)
        md += [
            "",
            f"Clusters no variant answers (every mean IoU < {ANSWERED}, oracle and "
            f"2-D ceiling included): **{bad} of {total} ({bad / max(total, 1):.1%})**"
            + (f": {', '.join(f'{s}/{q}' for s, q in which)}" if which else "."),
        ]
        md += _ceiling_lines(summ)
        md += _resolution_lines(sub, args.base, _baseline(args.base))
    md += _render_lines(results, labels)
    md += ["", "### Where mIoU is lost (all seeds)", ""]
    md += chain_loss(results)
    md += ["", "### Time", ""]
    md += _time_lines(results)
    out = "\n".join(md) + "\n"
    (args.work / "accuracy.json").write_text(json.dumps(_jsonable(summaries), indent=1))
    (args.work / "accuracy.md").write_text(out)
    if "test" in summaries and args.plot:
        _plot(summaries["test"], args.plot)
    return out


def _render_lines(results: dict[int, dict], labels: list[str]) -> list[str]:
    """What each label's novel slots were rendered from: the field's
    test PSNR and the truth appearance of the chosen targets, over all seeds."""
    from collections import Counter

    rows = []
    for lab in labels:
        got = [r["labels"][lab]["renders"] for r in results.values()
               if "renders" in r.get("labels", {}).get(lab, {})]  # fmt: skip
        if not got:
            continue
        psnr = [g["psnr_test"] for g in got if g.get("psnr_test") is not None]
        kinds = Counter(
            t["sky"] + ("" if t["filter"] in (None, "none") else f"+{t['filter']}")
            for g in got for t in g["targets"] if t.get("id") and t.get("sky")
        )  # fmt: skip
        same = sum(1 for g in got for t in g["targets"] if not t.get("id"))
        if same:
            kinds["(the view's own)"] = same
        mix = ", ".join(f"{k} {n}" for k, n in kinds.most_common())
        fit = f"{np.mean(psnr):.1f} dB" if psnr else "-"
        rows.append(f"| `{lab}` | {len(got)} | {fit} | {mix} |")
    if not rows:
        return []
    return [
        "",
        "### The novel slots' renders (all seeds)",
        "",
        "| label | seeds | field's test PSNR | chosen targets' truth appearance |",
        "|---|---|---|---|",
        *rows,
    ]


def _rel(path: Path | None) -> str:
    if path is None:
        return "none"
    try:
        return str(Path(path).resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


def _baseline(base: str) -> str:
    """LangSplat's label on the same segments as `base`."""
    return "langsplat-truth" if base.endswith("-truth") else "langsplat"


def _resolution_lines(
    results: dict[int, dict], base: str = "male", other: str = "langsplat"
) -> list[str]:
    """How wide the base − baseline interval is, and how many clusters ±0.03 needs."""
    from ptovs.stats import cluster_means, paired_difference

    a = cluster_means(_records(results, base))
    b = cluster_means(_records(results, other))
    common = [c for c in a if c in b]
    if len(common) < 2:
        return []
    d = np.array([a[c] - b[c] for c in common])
    sd = float(d.std(ddof=1))
    est = paired_difference(a, b)
    need = int(np.ceil((1.96 * sd / 0.03) ** 2))
    per_seed = len(common) / len(results)
    return [
        "",
        f"Resolution: {base} − {other} = {est.fmt(True)}, half-width "
        f"**{est.half_width:.3f}** over {len(common)} clusters (SD of the per-cluster "
        f"difference {sd:.3f}); a half-width of 0.03 needs about {need} clusters, "
        f"i.e. {need / per_seed:.0f} seeds in this half at {per_seed:.1f} queries "
        "per seed.",
    ]


def _jsonable(x):
    from ptovs.stats import Estimate

    if isinstance(x, Estimate):
        return {"mean": x.mean, "lo": x.lo, "hi": x.hi, "n": x.n}
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    return x


def _screen_lines(results: dict[int, dict]) -> list[str]:
    counts: dict[str, int] = {}
    attempts = []
    for res in results.values():
        for p in res["screen"]["parts"].values():
            counts[p["status"]] = counts.get(p["status"], 0) + 1
            if p["status"] == "redrawn":
                attempts.append(p["attempt"])
    total = sum(counts.values())
    seen = total - counts.get("unseen", 0)
    return [
        f"Screen: {seen} parts labelled in {len(results)} scenes; "
        f"{counts.get('pass', 0)} passed as drawn, {counts.get('redrawn', 0)} "
        f"redrawn ({np.mean(attempts) if attempts else 0:.1f} draws on average), "
        f"{counts.get('dropped', 0)} dropped; {counts.get('unseen', 0)} parts "
        "unlabelled (not queries).",
    ]


def _main_table(summ: dict, base: str = "male") -> list[str]:
    from ptovs.variants import TABLE3_ROWS

    lines = [
        f"| variant | Table 3 row | mIoU [95 % CI] | mPA | mP | Δ mIoU vs {base} "
        "[95 % CI] | CI excludes 0 | easy / hard views | language stages (s) | "
        "clusters |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for label, row in summ.items():
        diff = row.get("diff")
        lines.append(
            f"| {label} | {TABLE3_ROWS.get(label, '')} | {row['miou'].fmt()} | "
            f"{row['mpa'].mean:.3f} | {row['mp'].mean:.3f} | "
            + (
                f"{diff.fmt(True)} | {'yes' if diff.excludes_zero else 'no'}"
                if diff
                else "– | –"
            )  # fmt: skip
            + f" | {row['easy']:.3f} / {row['hard']:.3f} | {row['language_s']:.0f} | "
            f"{row['clusters']} |"
        )
    return lines


def _ceiling_lines(summ: dict) -> list[str]:
    if "oracle" not in summ:
        return []
    o = summ["oracle"]["miou"].mean
    above = [
        f"{lab} ({r['miou'].mean:.3f})"
        for lab, r in summ.items()
        if lab != "oracle" and r["miou"].mean > o
    ]
    return [
        "",
        f"Oracle mean {o:.3f} "
        + (
            "is at least every variant's mean."
            if not above
            else f"is below: {', '.join(above)}."
        ),
    ]


def _time_lines(results: dict[int, dict]) -> list[str]:
    walls = {
        s: sum(e["wall_s"] for e in r["labels"].values()) for s, r in results.items()
    }
    tot = sum(walls.values())
    return [
        f"Summed job time per seed (one thread): mean {np.mean(list(walls.values())):.0f} s, "
        f"max {max(walls.values()):.0f} s; {tot / 60:.0f} min over {len(walls)} seeds "
        "(two seeds run at a time on two cores; the wall time of the whole run is "
        "printed by the runner and recorded in docs/results.md)."
    ]


def _plot(summ: dict, path: Path) -> None:
    """Language-stage time (log x) against the paired mIoU difference to the full
    method, with its 95 % cluster-bootstrap interval (OpenCV)."""
    import cv2

    pts = [
        (lab, max(r["language_s"], 1.0), r["diff"])
        for lab, r in summ.items()
        if lab not in FEATURE_LABELS and "diff" in r
    ]
    if not pts or "male" not in summ:
        return
    male = summ["male"]
    W, H, m = 1000, 640, 90
    img = np.full((H, W, 3), 255, np.uint8)
    ts = np.log10([p[1] for p in pts] + [max(male["language_s"], 1.0)])
    lo = min(0.0, *(p[2].lo for p in pts))
    hi = max(0.0, *(p[2].hi for p in pts))
    x0, x1 = ts.min() - 0.1, ts.max() + 0.25
    y0, y1 = lo - 0.01, hi + 0.01

    def px(t: float, y: float) -> tuple[int, int]:
        return (
            int(m + (t - x0) / (x1 - x0) * (W - 2 * m)),
            int(H - m - (y - y0) / (y1 - y0) * (H - 2 * m)),
        )

    font, black, grey = cv2.FONT_HERSHEY_SIMPLEX, (0, 0, 0), (170, 170, 170)
    cv2.rectangle(img, (m, m), (W - m, H - m), black, 1)
    cv2.line(img, px(x0, 0.0), px(x1, 0.0), grey, 1)
    for k in range(6):
        y = y0 + (y1 - y0) * k / 5
        cv2.putText(img, f"{y:+.3f}", (12, px(x0, y)[1] + 4), font, 0.45, black, 1,
                    cv2.LINE_AA)  # fmt: skip
        t = x0 + (x1 - x0) * k / 5
        cv2.putText(img, f"{10**t:.0f}s", (px(t, y0)[0] - 15, H - m + 22), font, 0.45,
                    black, 1, cv2.LINE_AA)  # fmt: skip
    cv2.putText(img, "language stages per scene: train-ae + train-male + query + "
                "evaluate (s, log; one thread)", (m + 20, H - 30), font, 0.5, black, 1,
                cv2.LINE_AA)  # fmt: skip
    cv2.putText(img, f"mIoU - full method's ({male['miou'].mean:.3f}), test seeds: "
                "paired over (seed, query) clusters, 95% cluster-bootstrap CI",
                (m - 60, m - 30), font, 0.5, black, 1, cv2.LINE_AA)  # fmt: skip
    p0 = px(ts[-1], 0.0)
    cv2.circle(img, p0, 5, (0, 0, 200), -1, cv2.LINE_AA)
    cv2.putText(img, "male", (p0[0] - 45, p0[1] - 6), font, 0.45, (0, 0, 200), 1,
                cv2.LINE_AA)  # fmt: skip
    order = sorted(range(len(pts)), key=lambda i: (pts[i][1], pts[i][2].mean))
    for rank, i in enumerate(order):
        lab, _, est = pts[i]
        colour = (0, 140, 0) if lab in CEILINGS else (200, 80, 0)
        jitter = (rank % 5 - 2) * 0.006 * (x1 - x0)  # equal times: spread the bars
        t = ts[i] + jitter
        p, a, b = px(t, est.mean), px(t, est.lo), px(t, est.hi)
        cv2.line(img, a, b, colour, 1, cv2.LINE_AA)
        cv2.line(img, (a[0] - 4, a[1]), (a[0] + 4, a[1]), colour, 1)
        cv2.line(img, (b[0] - 4, b[1]), (b[0] + 4, b[1]), colour, 1)
        cv2.circle(img, p, 4, colour, -1, cv2.LINE_AA)
        cv2.putText(img, lab, (p[0] + 7, p[1] + 4), font, 0.4, colour, 1, cv2.LINE_AA)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), img)
