"""Speed against error: every recipe as a point, one front per question.

    make bench-speed-error                       # both fronts from scratch, then the report
    python bench/speed_error.py --report-only    # tables, CSVs and the picture from the results

Two questions, two fronts:

1. The whole chain's seconds (every stage from the photos' reconstruct to the
   evaluation, one thread, the sum of each stage's recorded run time) against
   mIoU: the accuracy instrument's (bench/accuracy.py) results of each recipe
   label, test seeds, with the cluster-bootstrap interval and the paired
   difference to the default (`male`). Recipes: the default (`male`: the
   paper's model, each view segmented once), the scene-fitted one (`auto`: configs/auto.toml's values), the full method on
   plain 3DGS (`plain`), photo alone (`langsplat-wild`), LangSplat's recipe
   (`langsplat`) and one appearance (`no-multi-appearance`).
2. reconstruct's seconds (the stage's recorded run time; SfM, shared by every
   recipe, excluded) against held-out PSNR (the held-out photos as they are),
   per scene: bench seeds (synthetic, changing light and occluders),
   herzjesu_p8 and fountain_p11 (real, from the photos alone). Recipes: the
   in-the-wild model (`wild`), plain 3DGS (`plain`), the colour rung (`colour`:
   plain 3DGS with a photo-wide colour map and sky), the scene-fitted reconstruct
   (`auto`: `wild = "auto"`, `stop = "plateau"`) and, on the bench seeds, two
   Gaussian budgets of the wild model (`wild-10k`, `wild-5k`), all at
   `--iterations` steps.

A point is on its front when no other point of the same front is both faster
and at least as accurate. Raw rows go to docs/results/speed_error_chain.csv and
speed_error_reconstruct.csv; the picture to docs/img/speed_error.png.
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, run_ptovs, seed_list  # noqa: E402  (same folder)

CHAIN_RECIPES = {
    "male": "the default (the paper's model, each view segmented once)",
    "auto": "scene-fitted (configs/auto.toml)",
    "plain": "the full method on plain 3DGS",
    "no-multi-appearance": "one appearance in the field",
    "langsplat-wild": "photo alone (in-the-wild geometry)",
    "langsplat": "LangSplat's recipe (plain 3DGS, photo alone)",
}
# each recipe sets every key below: a scene run without --config adopts the settings
# of its last run, so a key left out would be inherited from the recipe before
_RECON_BASE = {"wild": "true", "sky_stride": "0", "seed": "0", "stop": '"fixed"',
               "max_gaussians": "25000"}  # fmt: skip
_RECON_KEYS = {
    "wild": {},
    "plain": {"wild": "false"},
    "colour": {"wild": '"colour"'},
    "auto": {"wild": '"auto"', "stop": '"plateau"'},
    "wild-10k": {"max_gaussians": "10000"},
    "wild-5k": {"max_gaussians": "5000"},
    "wild-sky4": {"sky_stride": "4"},
    "wild-sky2": {"sky_stride": "2"},
    "wild-seed1": {"seed": "1"},
}
RECON_RECIPES = {
    name: [f"reconstruct.{k}={v}" for k, v in {**_RECON_BASE, **keys}.items()]
    for name, keys in _RECON_KEYS.items()
}
REAL_SETS = ("herzjesu_p8", "fountain_p11")
BUDGETS = ("wild-10k", "wild-5k")


def pareto(points: list[tuple[float, float]]) -> list[bool]:
    """Whether each (seconds, score) is on the front: no other point is faster
    (or as fast) and at least as good, one of the two strictly."""
    out = []
    for i, (t, s) in enumerate(points):
        dominated = any(
            (t2 <= t and s2 >= s) and (t2 < t or s2 > s)
            for j, (t2, s2) in enumerate(points)
            if j != i
        )
        out.append(not dominated)
    return out


# ------------------------------------------------------------- chain front --
def chain_rows(work: Path, seeds: list[int], base: str = "male") -> list[dict]:
    import accuracy

    results = accuracy.load_results(work, "small", seeds)
    labels = [
        lab
        for lab in CHAIN_RECIPES
        if any(lab in r["labels"] for r in results.values())
    ]
    summ = accuracy.summarise(results, labels, base=base)
    rows = []
    for lab in labels:
        r = summ[lab]
        chain_s = [
            sum(res["labels"][lab]["stage_s"].values())
            for res in results.values()
            if lab in res["labels"]
        ]
        row = {
            "recipe": lab,
            "what": CHAIN_RECIPES[lab],
            "seeds": r["seeds"],
            "clusters": r["clusters"],
            "chain_s": round(float(np.mean(chain_s)), 1),
            "miou": round(r["miou"].mean, 4),
            "ci_low": round(r["miou"].lo, 4),
            "ci_high": round(r["miou"].hi, 4),
        }
        if "diff" in r:
            d = r["diff"]
            row.update(delta=round(d.mean, 4), delta_low=round(d.lo, 4),
                       delta_high=round(d.hi, 4))  # fmt: skip
        rows.append(row)
    base_s = next((r["chain_s"] for r in rows if r["recipe"] == base), None)
    front = pareto([(r["chain_s"], r["miou"]) for r in rows])
    for r, f in zip(rows, front, strict=True):
        r["time_ratio"] = round(r["chain_s"] / base_s, 3) if base_s else None
        r["on_front"] = f
    return rows


def run_chain_front(args: argparse.Namespace) -> None:
    """The accuracy instrument over dev and test seeds, the recipes' labels only."""
    cmd = [sys.executable, str(ROOT / "bench" / "accuracy.py"), "--preset", "small",
           "--seeds", *args.dev, *args.test, "--dev", *args.dev,
           "--work", str(args.acc_work), "--data", str(args.acc_data),
           "--labels", *CHAIN_RECIPES]  # fmt: skip
    subprocess.run(cmd, check=True)


# ------------------------------------------------------- reconstruct front --
def _scene_dirs(args: argparse.Namespace) -> dict[str, Path]:
    from common import bench_scene
    from real import copy_photos

    dirs = {f"bench_s{s}": bench_scene(args.data, s) for s in args.bench_seeds}
    for name in args.real_sets:
        src, dst = args.real / name, args.data / "photos" / name
        want = sorted(p.name for p in (src / "images").glob("*.jpg"))
        have = sorted(p.name for p in (dst / "images").glob("*.jpg"))
        if want != have:  # copied once: the same files keep SfM's cache
            copy_photos(src, dst, 0.0)
        dirs[name] = dst
    return dirs


def recon_point(work: Path, scene: Path, recipe: str, iterations: int) -> dict:
    from ptovs.artifacts import Artifact, read_json_dataset

    sets = [f"--set=reconstruct.iterations={iterations}"]
    sets += [f"--set={kv}" for kv in RECON_RECIPES[recipe]]
    wall, rss, out = run_ptovs(work, *sets, "reconstruct", "--data", str(scene))
    path = Path(out.strip().splitlines()[-1].split(": ", 1)[1])
    with Artifact(path) as a:
        m = read_json_dataset(a.root()["metrics_json"])
        cfg = json.loads(a.attrs["config_json"])  # every artifact stores its config
        secs = float(json.loads(a.attrs["timings_json"])["run_s"])
    return {
        "recipe": recipe,
        "wild": cfg.get("wild"),
        "reconstruct_s": round(secs, 1),
        "steps": m.get("iterations"),
        "gaussians": m.get("gaussians"),
        "psnr_test": m.get("psnr_test"),
        "psnr_test_nerfw": m.get("psnr_test_nerfw"),
        "psnr_test_clean": m.get("psnr_test_clean"),
        "peak_rss_mb": round(rss),
        "key": path.stem,
    }


def run_recon_front(args: argparse.Namespace) -> None:
    out = Path(args.recon_json)
    done = json.loads(out.read_text()) if out.is_file() else {}
    for name, scene in _scene_dirs(args).items():
        for recipe in args.recon_recipes:
            if recipe in BUDGETS and name in args.real_sets:
                continue  # budgets on the synthetic scenes only (their clouds are small)
            tag = f"{name}/{recipe}/{args.iterations}"
            if tag in done:
                continue
            print(f"reconstruct {name} {recipe} ...", flush=True)
            done[tag] = {
                "scene": name,
                **recon_point(args.work, scene, recipe, args.iterations),
            }
            out.parent.mkdir(parents=True, exist_ok=True)
            out.write_text(json.dumps(done, indent=1))


def recon_rows(path: Path) -> list[dict]:
    done = json.loads(path.read_text()) if path.is_file() else {}
    rows = sorted(done.values(), key=lambda r: (r["scene"], r["reconstruct_s"]))
    for name in {r["scene"] for r in rows}:
        sub = [r for r in rows if r["scene"] == name and r["psnr_test"] is not None]
        for r, f in zip(sub, pareto([(r["reconstruct_s"], r["psnr_test"]) for r in sub]),
                        strict=True):  # fmt: skip
            r["on_front"] = f
        fitted = next((r for r in sub if r["recipe"] == "auto"), None)
        pair = [r for r in sub if r["recipe"] in ("wild", "plain")]
        if (
            fitted and len(pair) == 2
        ):  # the target: the better − 0.3 dB, ≤ 1.2× the faster
            best = max(r["psnr_test"] for r in pair)
            fastest = min(r["reconstruct_s"] for r in pair)
            fitted["vs_best_db"] = round(fitted["psnr_test"] - best, 2)
            fitted["vs_fastest_time"] = round(fitted["reconstruct_s"] / fastest, 2)
    return rows


# ------------------------------------------------------------------ report --
def write_csv(path: Path, rows: list[dict]) -> None:
    if not rows:
        return
    fields = list(dict.fromkeys(k for r in rows for k in r))
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        w.writerows(rows)


def picture(chain: list[dict], recon: list[dict], path: Path) -> None:
    """Two panels (OpenCV): the chain's seconds (log) against mIoU with its 95 %
    interval, and reconstruct's seconds (log) against held-out PSNR per scene;
    each front joined by a line."""
    import cv2

    W, H, m = 1400, 640, 80
    img = np.full((H, W, 3), 255, np.uint8)
    font, black = cv2.FONT_HERSHEY_SIMPLEX, (0, 0, 0)
    colours = [(200, 80, 0), (0, 140, 0), (0, 0, 200), (150, 0, 150), (0, 140, 160)]

    def panel(x0: int, rows, xkey, ykey, group, title, ylab, lo=None, hi=None):
        pw = W // 2 - m - 20
        if not rows:
            return
        ts = np.log10([max(r[xkey], 1.0) for r in rows])
        ys = [r[ykey] for r in rows]
        ylo = min(ys + ([r[lo] for r in rows] if lo else []))
        yhi = max(ys + ([r[hi] for r in rows] if hi else []))
        tx0, tx1 = ts.min() - 0.1, ts.max() + 0.15
        ypad = 0.05 * (yhi - ylo or 1.0)
        y0, y1 = ylo - ypad, yhi + ypad

        def px(t, y):
            return (int(x0 + (t - tx0) / (tx1 - tx0) * pw),
                    int(H - m - (y - y0) / (y1 - y0) * (H - 2 * m)))  # fmt: skip

        cv2.rectangle(img, (x0, m), (x0 + pw, H - m), black, 1)
        cv2.putText(img, title, (x0, m - 20), font, 0.5, black, 1, cv2.LINE_AA)
        cv2.putText(img, ylab, (x0, H - 25), font, 0.45, black, 1, cv2.LINE_AA)
        for k in range(5):
            y = y0 + (y1 - y0) * k / 4
            cv2.putText(img, f"{y:.3g}", (x0 - 55, px(tx0, y)[1] + 4), font, 0.4,
                        black, 1, cv2.LINE_AA)  # fmt: skip
            t = tx0 + (tx1 - tx0) * k / 4
            cv2.putText(img, f"{10**t:.0f}s", (px(t, y0)[0] - 15, H - m + 20), font,
                        0.4, black, 1, cv2.LINE_AA)  # fmt: skip
        groups = list(dict.fromkeys(group(r) for r in rows))
        for gi, g in enumerate(groups):
            col = colours[gi % len(colours)]
            sub = sorted([r for r in rows if group(r) == g], key=lambda r: r[xkey])
            front = [r for r in sub if r.get("on_front")]
            for a, b in zip(front, front[1:], strict=False):
                cv2.line(img, px(np.log10(max(a[xkey], 1)), a[ykey]),
                         px(np.log10(max(b[xkey], 1)), b[ykey]), col, 1, cv2.LINE_AA)  # fmt: skip
            for k, r in enumerate(sub):
                p = px(np.log10(max(r[xkey], 1)), r[ykey])
                if lo:
                    cv2.line(img, px(np.log10(max(r[xkey], 1)), r[lo]),
                             px(np.log10(max(r[xkey], 1)), r[hi]), col, 1)  # fmt: skip
                cv2.circle(img, p, 5 if r.get("on_front") else 3, col, -1, cv2.LINE_AA)
                label = r["recipe"] + ("" if len(groups) == 1 else f" ({g})")
                # labels of near points stacked, not drawn over each other
                cv2.putText(img, label, (p[0] + 7, p[1] - 4 + 13 * (k % 3)), font, 0.38, col, 1,
                            cv2.LINE_AA)  # fmt: skip

    panel(m + 20, chain, "chain_s", "miou", lambda r: "test seeds",
          "whole chain (s, log; one thread) vs mIoU, test seeds, 95% CI",
          "mIoU; large dots: on the front", "ci_low", "ci_high")  # fmt: skip
    panel(W // 2 + m, [r for r in recon if r.get("psnr_test") is not None],
          "reconstruct_s", "psnr_test", lambda r: r["scene"],
          "reconstruct (s, log; 2 threads) vs held-out PSNR (dB)",
          "held-out PSNR (dB), photos as they are")  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), img)


def read_csv(path: Path) -> list[dict]:
    """Rows of a CSV this script wrote, numbers as numbers (empty cells dropped)."""

    def num(v: str):
        if v in ("True", "False"):
            return v == "True"
        try:
            return float(v)
        except ValueError:
            return v

    with path.open(newline="") as f:
        return [{k: num(v) for k, v in r.items() if v != ""} for r in csv.DictReader(f)]


def report(args: argparse.Namespace) -> None:
    chain = chain_rows(args.acc_work, seed_list(args.test))
    dev = chain_rows(args.acc_work, seed_list(args.dev))
    recon = recon_rows(Path(args.recon_json))
    chain_csv = ROOT / "docs" / "results" / "speed_error_chain.csv"
    if chain or dev or args.only != "reconstruct":
        write_csv(chain_csv, [dict(r, seeds_kind="test") for r in chain]
                  + [dict(r, seeds_kind="dev") for r in dev])  # fmt: skip
    elif chain_csv.is_file():  # one front re-run: the other's rows stay as recorded
        rows = read_csv(chain_csv)
        chain = [r for r in rows if r.get("seeds_kind") == "test"]
        dev = [r for r in rows if r.get("seeds_kind") == "dev"]
    write_csv(ROOT / "docs" / "results" / "speed_error_reconstruct.csv", recon)
    picture(chain, recon, ROOT / "docs" / "img" / "speed_error.png")
    for name, rows in (("test", chain), ("dev", dev)):
        _table(f"Whole chain against mIoU, {name} seeds:",
               ["recipe", "chain (s)", "× the default's", "mIoU [95 % CI]",
                "Δ vs the default [95 % CI]", "front"],
               [[f"`{r['recipe']}`", f"{r['chain_s']:.0f}", f"{r['time_ratio']:.2f}",
                 f"{r['miou']:.3f} [{r['ci_low']:.3f}, {r['ci_high']:.3f}]",
                 f"{r['delta']:+.3f} [{r['delta_low']:+.3f}, {r['delta_high']:+.3f}]"
                 if "delta" in r else "–", "yes" if r["on_front"] else ""]
                for r in rows])  # fmt: skip
    _table("reconstruct against held-out PSNR:",
           ["scene", "recipe", "reconstruct (s)", "steps", "Gaussians",
            "held-out PSNR (dB)", "front"],
           [[r["scene"], f"`{r['recipe']}`" + _chose(r), f"{r['reconstruct_s']:.0f}",
             str(r["steps"]), f"{r['gaussians']:,}",
             f"{r['psnr_test']:.2f}" + (f" ({r['vs_best_db']:+.2f} dB, "
                                        f"{r['vs_fastest_time']:.2f}× time)"
                                        if "vs_best_db" in r else ""),
             "yes" if r.get("on_front") else ""]
            for r in recon])  # fmt: skip


def _chose(r: dict) -> str:
    """What the fitted reconstruct chose, after its name."""
    if r["recipe"] != "auto" or r.get("wild") is None:
        return ""
    return " → wild" if r["wild"] else " → plain"


def _table(title: str, header: list[str], rows: list[list[str]]) -> None:
    print(f"\n{title}")
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    for cells in rows:
        print("| " + " | ".join(cells) + " |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dev", nargs="+", default=["0-8"], help="dev seeds (choose here)")
    ap.add_argument("--test", nargs="+", default=["9-17"], help="test seeds (report)")
    ap.add_argument("--acc-work", type=Path, default=ROOT / "work" / "accuracy")
    ap.add_argument("--acc-data", type=Path, default=ROOT / "data" / "accuracy")
    ap.add_argument("--bench-seeds", type=int, nargs="*", default=[0])
    ap.add_argument("--real-sets", nargs="*", default=list(REAL_SETS))
    ap.add_argument(
        "--real",
        type=Path,
        default=ROOT / "data" / "real",
        help="folder of real photo sets (herzjesu_p8/, fountain_p11/)",
    )
    ap.add_argument("--recon-recipes", nargs="+", default=list(RECON_RECIPES),
                    choices=list(RECON_RECIPES))  # fmt: skip
    ap.add_argument("--iterations", type=int, default=500)
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "speed_error")
    ap.add_argument("--work", type=Path, default=ROOT / "work" / "speed_error")
    ap.add_argument("--recon-json", type=Path,
                    default=ROOT / "work" / "speed_error" / "reconstruct.json")  # fmt: skip
    ap.add_argument("--only", choices=("chain", "reconstruct"), default=None)
    ap.add_argument("--report-only", action="store_true")
    args = ap.parse_args()
    if not args.report_only:
        if args.only in (None, "chain"):
            run_chain_front(args)
        if args.only in (None, "reconstruct"):
            run_recon_front(args)
    report(args)


if __name__ == "__main__":
    main()
