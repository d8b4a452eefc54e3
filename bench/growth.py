"""How every stage's time, memory and quality grow with the collection.

python bench/growth.py --preset landmark --seed 0 --photos 100 200 400 763 --threads 2 \
    --work work/growth --plot                          # what `make bench-growth` runs
python bench/growth.py --preset small --photos 20 28 --set reconstruct.iterations=100 \
    --work /tmp/growth_try --plot                      # a short trial

A size is N train photos of the preset's world (`ptovs synth-scene --preset P --seed S
--photos N`: the labelled and test views, then the first other train photos, so a
smaller collection is a subset of a larger one); an item PRESET:N of --photos is that
preset's only. The scene <preset>_s<seed>_p<N> is generated under --data (default
<work>/data) when missing and kept. Then, one size at a time, every stage of the chain
(src/ptovs/pipeline.py's PIPELINE) runs in its own process exactly as `make all` runs
it, on --threads threads, in the work folder <work>/<scene> emptied first:

    OMP_NUM_THREADS=T python -m ptovs --work-dir <work>/<scene> --config <config> -q \
        --threads T [--set STAGE.KEY=VALUE ...] <stage> --scene <scene> --data <scene dir>

Per stage: wall s, peak RSS MB (os.wait4's ru_maxrss of its process), CPU s, the
1-min load before and after, the exit status, and its output's quality figure (QUALITY;
read in a separate process, so this script's pages never count in a stage's peak RSS;
U_T's AUROC is counted from histograms of its float16 values: exact, memory-flat at 763
photos). A failed stage ends that size's chain. Logs: <work>/<scene>/logs/.

Results: <work>/growth.json (written after every stage; sizes an earlier run measured
with the same seed, --set items, config content, threads and CPU are kept; a file of
another setup is moved aside to growth.<date>.json), then markdown tables: per stage
and size its seconds, peak MB and quality, and the exponent b of a·x^b fitted on
log-log to wall time and peak RSS, x the photos (per preset) and the train pixels.
`--plot` draws time and peak RSS against photos, log-log, to <work>/growth.png.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import (  # noqa: E402  (same folder)
    PRESETS,
    ROOT,
    SAME_MACHINE,
    SECTIONS,
    fmt_s,
    machine_facts,
    ok,
    report_stage,
    run_stage,
    save_json,
    stage_command,
    thread_env,
)

from ptovs.pipeline import PIPELINE  # noqa: E402  (stdlib only: torch stays out)

# an earlier growth.json's runs are kept when these (and the CPU) are the same
SAME = ("seed", "set", "config", "threads", "stages")


def config_id(config: str | Path) -> str:
    """A config as growth.json compares it: the sha256 of its content, so that the
    same file reached by another path (a git worktree, a copy) is the same setup.
    An id already made passes through; an older file's path is hashed if it is there."""
    text = str(config)
    if text.startswith("sha256:"):
        return text
    try:
        return "sha256:" + hashlib.sha256(Path(text).read_bytes()).hexdigest()[:16]
    except OSError:
        return text


QUALITY = {
    "reconstruct": ("test PSNR dB", "reconstruct artifact metrics_json['psnr_test']"),
    "uncertainty": (
        "U_T AUROC",
        "U_T against synthetic/truth/<stem>.npz 'transient', train views, every "
        "pixel (bench/extract.py's ut_auroc; counted by bench/growth.py)",
    ),
    "train-ae": ("held-out cos", "train-ae artifact metrics_json['heldout_cos']"),
    "evaluate": ("mIoU", "<work>/<scene>/<scene>/evaluate.json results[*][scene]['miou']"),
}  # fmt: skip


# ------------------------------------------------- measured in a separate process


def probe_scene(folder: str) -> dict:
    """Train photos, test views and total train pixels (working size) of a scene."""
    from ptovs.scene import load_scene

    scene = load_scene(folder)
    train = scene.train_views()
    px = [v.width * v.height for v in train]
    return {"photos": len(train), "test_views": len(scene.test_views()),
            "train_pixels": int(sum(px)),
            "photo_pixels": [min(px), max(px)] if px else None}  # fmt: skip


def probe_metric(artifact: str, key: str) -> float | None:
    """One figure of an artifact's root metrics_json."""
    from ptovs.artifacts import Artifact, read_json_dataset

    with Artifact(Path(artifact), verify=False) as art:
        value = read_json_dataset(art.root()["metrics_json"]).get(key)
    return None if value is None else float(value)


def probe_auroc(artifact: str, scene: str) -> dict:
    """AUROC of U_T against the true transient masks, over every pixel of every
    train view (ptovs.field.losses.auroc's definition, ties counted half), counted
    from histograms of U_T's float16 bit patterns: exact, one view in memory."""
    import numpy as np

    from ptovs.artifacts import Artifact

    truth = Path(scene) / "synthetic" / "truth"
    pos = np.zeros(1 << 16, np.int64)
    neg = np.zeros(1 << 16, np.int64)
    with Artifact(Path(artifact), verify=False) as art:
        for name in art.names():
            # |u| as float16: -0.0 becomes 0.0, and the bit patterns of values >= 0
            # are ordered as the values
            u = np.abs(art.read(name, ["u_t"])["u_t"].astype(np.float16)).ravel()
            bits = u.view(np.uint16)
            t = np.load(truth / f"{Path(name).stem}.npz")["transient"].ravel() > 0.5
            pos += np.bincount(bits[t], minlength=1 << 16)
            neg += np.bincount(bits[~t], minlength=1 << 16)
    n_pos, n_neg = int(pos.sum()), int(neg.sum())
    if n_pos == 0 or n_neg == 0:  # e.g. the smallest sizes: occluders only in test
        return {"auroc": None, "transient_share": n_pos / max(1, n_pos + n_neg),
                "note": "AUROC undefined: the train views' truth has "
                + ("no transient pixel" if n_pos == 0 else "only transient pixels")}  # fmt: skip
    below = np.cumsum(neg) - neg  # negatives scored below each value
    twice = int((pos * (2 * below + neg)).sum())
    return {"auroc": twice / (2.0 * n_pos * n_neg),
            "transient_share": n_pos / (n_pos + n_neg)}  # fmt: skip


def probe(kind: str, *paths: str) -> dict:
    if kind == "scene":
        return probe_scene(paths[0])
    if kind == "reconstruct":
        return {"value": probe_metric(paths[0], "psnr_test")}
    if kind == "train-ae":
        return {"value": probe_metric(paths[0], "heldout_cos")}
    if kind == "uncertainty":
        out = probe_auroc(paths[0], paths[1])
        return {"value": out.pop("auroc"), **out}
    raise SystemExit(f"unknown probe {kind!r}")


def run_probe(kind: str, *paths: str) -> dict:
    """probe() in a fresh process (numpy, h5py and pycolmap stay out of this one);
    {"error": ...} when it fails."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--probe", kind, *paths]
    out = subprocess.run(cmd, capture_output=True, text=True)
    if out.returncode != 0:
        return {"error": out.stderr[-1500:]}
    return json.loads(out.stdout.strip().splitlines()[-1])


def artifact_path(logs: Path, stage: str) -> str | None:
    """The artifact a stage wrote: its stdout's "<stage>: <path>" line."""
    try:
        lines = (logs / f"{stage}.out").read_text().splitlines()
    except OSError:
        return None
    for line in lines:
        if line.startswith(f"{stage}: "):
            return line.split(": ", 1)[1].strip()
    return None


def quality(stage: str, work: Path, scene: Path, logs: Path) -> dict:
    """The stage's quality figure {"value": ...} ({} for a stage without one)."""
    if stage not in QUALITY:
        return {}
    if stage == "evaluate":
        path = work / scene.name / "evaluate.json"
        try:
            rows = json.loads(path.read_text())["results"]
            (row,) = rows.values()  # the default chain: one variant
            return {"value": float(row[scene.name]["miou"])}
        except (OSError, KeyError, ValueError, TypeError) as exc:
            return {"error": f"{path}: {exc!r}"}
    art = artifact_path(logs, stage)
    if art is None:
        return {"error": f"no '{stage}: <artifact>' line in {logs / stage}.out"}
    extra = (str(scene),) if stage == "uncertainty" else ()
    return run_probe(stage, art, *extra)


# --------------------------------------------------------------------- the runs


def sizes(presets: list[str], items: list[str]) -> list[tuple[str, int]]:
    """(preset, photos) in order: an item N is every preset's, PRESET:N one's."""
    out = []
    for preset in presets:
        for it in items:
            name, colon, n = it.rpartition(":")
            if colon and name not in PRESETS:
                raise ValueError(f"{name!r} is no preset")
            if not colon or name == preset:
                out.append((preset, int(n)))
    return list(dict.fromkeys(out))


def scene_name(preset: str, seed: int, photos: int) -> str:
    return f"{preset}_s{seed}_p{photos}"  # synth-scene's name with --photos


def run_size(args, results, save, preset: str, photos: int, env: dict) -> None:
    """Generate (when missing) and run the chain on one size."""
    name = scene_name(preset, args.seed, photos)
    scene = args.data / name
    work = args.work / name
    logs = work / "logs"
    shutil.rmtree(work, ignore_errors=True)
    logs.mkdir(parents=True)
    run = results["runs"][name] = {
        "preset": preset, "photos_asked": photos, "scene": str(scene),
        "date": time.strftime("%Y-%m-%d %H:%M"),
        "commit": results["machine"].get("commit"),
        "cpu": results["machine"].get("cpu_model"), "stages": {},
    }  # fmt: skip
    # the last file synth-scene writes: a killed generation is made again
    if (scene / "synthetic" / "truth" / "cameras.json").is_file():
        run["synth"] = {"reused": True}
    else:
        cmd = [sys.executable, "-m", "ptovs", "-q", "synth-scene", str(args.data),
               "--preset", preset, "--seed", str(args.seed), "--photos", str(photos)]  # fmt: skip
        run["synth"] = run_stage(cmd, env, logs, "synth-scene")
        if report_stage(name, "synth-scene", run["synth"]):
            save()
            return
    facts = run_probe("scene", str(scene))
    if "error" in facts:
        facts["scene_error"] = facts.pop("error")
    run.update(facts)
    save()

    t0, stop = time.perf_counter(), ""
    for stage in PIPELINE:
        if stop:
            run["stages"][stage] = {"skipped": stop}
            continue
        cmd = stage_command(args, work, scene, args.threads, stage)
        rec = run["stages"][stage] = run_stage(cmd, env, logs, stage)
        rec["threads"] = args.threads
        if ok(rec):
            q = quality(stage, work, scene, logs)
            if "value" in q:
                rec["quality"] = q.pop("value")
            rec.update({f"quality_{k}": v for k, v in q.items()})
        save()
        qtxt = f"  {QUALITY[stage][0]} {fmt_q(stage, rec)}" if stage in QUALITY else ""
        stop = report_stage(name, stage, rec, qtxt)
    run["total_s"] = round(time.perf_counter() - t0, 1)
    save()


# ------------------------------------------------------------- fits and tables


def fit_exponent(points: list[tuple[float, float]]) -> float | None:
    """b of y = a·x^b, least squares on log-log; None with fewer than 2 distinct x."""
    pts = [(math.log(x), math.log(y)) for x, y in points if x > 0 and y > 0]
    if len({x for x, _ in pts}) < 2:
        return None
    mx = sum(x for x, _ in pts) / len(pts)
    my = sum(y for _, y in pts) / len(pts)
    sxx = sum((x - mx) ** 2 for x, _ in pts)
    return sum((x - mx) * (y - my) for x, y in pts) / sxx


def stage_rec(run: dict, stage: str) -> dict | None:
    """A stage's record, or the chain's ("chain": total wall s, largest peak RSS)."""
    if stage != "chain":
        return run.get("stages", {}).get(stage)
    recs = [run.get("stages", {}).get(s) for s in PIPELINE]
    if not all(ok(r) for r in recs):
        return None
    return {"wall_s": round(sum(r["wall_s"] for r in recs), 2), "exit": 0,
            "peak_rss_mb": max(r["peak_rss_mb"] for r in recs)}  # fmt: skip


def measured(runs: dict) -> list[str]:
    """The runs with a scene, ordered by preset then photos."""
    names = [n for n, r in runs.items() if r.get("photos")]
    order = {p: i for i, p in enumerate(PRESETS)}
    return sorted(names, key=lambda n: (order.get(runs[n]["preset"], 99),
                                        runs[n]["photos"]))  # fmt: skip


def exponents(runs: dict, names: list[str], stage: str) -> dict[str, float | None]:
    """b of time and of peak RSS in photos (per preset) and in train pixels (all)."""
    out: dict[str, float | None] = {}
    presets = list(dict.fromkeys(runs[n]["preset"] for n in names))
    for what, key in (("t", "wall_s"), ("MB", "peak_rss_mb")):
        for preset in presets:
            pts = [(runs[n]["photos"], r[key]) for n in names
                   if runs[n]["preset"] == preset and ok(r := stage_rec(runs[n], stage))]  # fmt: skip
            out[f"{what}/photos {preset}"] = fit_exponent(pts)
        pts = [(runs[n]["train_pixels"], r[key]) for n in names
               if ok(r := stage_rec(runs[n], stage))]  # fmt: skip
        out[f"{what}/px"] = fit_exponent(pts)
    return out


def fmt_q(stage: str, rec: dict | None) -> str:
    if not rec or rec.get("quality") is None:
        return "–" if stage in QUALITY and ok(rec) else ""
    return f"{rec['quality']:.{2 if stage == 'reconstruct' else 3}f}"


def print_tables(results: dict) -> None:
    runs = results["runs"]
    names = measured(runs)
    if not names:
        print("nothing measured")
        return
    one = len({runs[n]["preset"] for n in names}) == 1
    label = {n: (f"{runs[n]['photos']}" if one
                 else f"{runs[n]['preset']} {runs[n]['photos']}") for n in names}  # fmt: skip
    print(
        "| scene | train photos | test views | train Mpx | px a photo | synth s | chain s |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|")
    for n in names:
        r = runs[n]
        lo, hi = r.get("photo_pixels") or (0, 0)
        synth = r.get("synth", {})
        syn = "reused" if synth.get("reused") else fmt_s(synth)
        chain = stage_rec(r, "chain")
        print(f"| {n} | {r['photos']} | {r.get('test_views', '–')} | "
              f"{r['train_pixels'] / 1e6:.1f} | {lo:,}–{hi:,} | {syn} | "
              f"{fmt_s(chain) if chain else '–'} |")  # fmt: skip
    print()
    exps = {s: exponents(runs, names, s) for s in (*PIPELINE, "chain")}
    ekeys = [k for k in exps["chain"] if any(e[k] is not None for e in exps.values())]
    cols = [
        c for n in names for c in (f"{label[n]} s", f"{label[n]} MB", f"{label[n]} q")
    ]
    cols += [f"b {k}" for k in ekeys]
    print("| stage | " + " | ".join(cols) + " |")
    print("|---|" + "---:|" * len(cols))
    for stage in (*PIPELINE, "chain"):
        cells = []
        for n in names:
            rec = stage_rec(runs[n], stage)
            cells.append(fmt_s(rec))
            rss = rec.get("peak_rss_mb") if rec else None
            cells.append(f"{rss:.0f}" if rss is not None else "–")
            cells.append(fmt_q(stage, rec) if stage in QUALITY else "")
        cells += [f"{exps[stage][k]:.2f}" if exps[stage][k] is not None else "–"
                  for k in ekeys]  # fmt: skip
        print(f"| {stage} | " + " | ".join(cells) + " |")
    print()
    print("q: " + "; ".join(f"{s} {QUALITY[s][0]}" for s in QUALITY)
          + ". b: the exponent of a·x^b fitted to wall time (t) or peak RSS (MB), "
          "x the train photos (sizes of one preset) or train pixels (every size).")  # fmt: skip
    print(flush=True)


# --------------------------------------------------------------------- the plot

# a colour a stage (BGR: tab10's first eight), then black for the chain
COLOURS = [(180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214),
           (189, 103, 148), (75, 86, 140), (194, 119, 227), (34, 189, 188),
           (20, 20, 20)]  # fmt: skip


def _ticks(lo: float, hi: float) -> list[float]:
    """1-2-5 ticks between lo and hi (decades only when there are many)."""
    ks = range(math.floor(math.log10(lo)), math.ceil(math.log10(hi)) + 1)
    ticks = [m * 10.0**k for k in ks for m in (1, 2, 5) if lo <= m * 10.0**k <= hi]
    if len(ticks) > 9:
        ticks = [t for t in ticks if f"{t:g}".lstrip("0.").startswith("1")]
    if len(ticks) < 4:
        ticks = [m * 10.0**k for k in ks for m in (1, 1.5, 2, 3, 4, 5, 6, 7, 8)
                 if lo <= m * 10.0**k <= hi]  # fmt: skip
    return ticks


def _span(values: list[float], pad: float = 0.08) -> tuple[float, float]:
    lo, hi = math.log10(min(values)), math.log10(max(values))
    if hi - lo < 0.2:
        mid = (hi + lo) / 2
        lo, hi = mid - 0.1, mid + 0.1
    d = (hi - lo) * pad
    return 10 ** (lo - d), 10 ** (hi + d)


def _marker(img, x: int, y: int, shape: int, colour) -> None:
    import cv2

    if shape == 0:
        cv2.circle(img, (x, y), 4, colour, -1, cv2.LINE_AA)
    elif shape == 1:
        cv2.rectangle(img, (x - 4, y - 4), (x + 4, y + 4), colour, -1)
    else:
        import numpy as np

        pts = np.array([[x, y - 5], [x - 5, y + 4], [x + 5, y + 4]], np.int32)
        cv2.fillPoly(img, [pts], colour, cv2.LINE_AA)


def plot(results: dict, path: Path) -> None:
    """Wall time and peak RSS against photos, log-log, a line a stage (and preset):
    two panels side by side, 900 x 500 px, drawn with OpenCV."""
    import cv2
    import numpy as np

    from ptovs.atomic import atomic_file

    runs = results["runs"]
    names = measured(runs)
    presets = list(dict.fromkeys(runs[n]["preset"] for n in names))
    img = np.full((500, 900, 3), 255, np.uint8)
    font, grey, ink = cv2.FONT_HERSHEY_SIMPLEX, (225, 225, 225), (40, 40, 40)

    def text(s: str, org: tuple[int, int], scale: float = 0.4, colour=ink,
             anchor: str = "left") -> None:  # fmt: skip
        (w, h), _ = cv2.getTextSize(s, font, scale, 1)
        x, y = org
        x -= {"left": 0, "centre": w // 2, "right": w}[anchor]
        cv2.putText(img, s, (x, y + h // 2), font, scale, colour, 1, cv2.LINE_AA)

    machine = results.get("machine", {})
    title = (f"{' / '.join(presets)} seed {results['seed']}, {results['threads']} "
             f"threads, {machine.get('cpus', '?')} CPUs, {machine.get('date', '')}"
             + (f"; --set {' '.join(results['set'])}" if results.get("set") else ""))  # fmt: skip
    text(title, (450, 14), 0.45, anchor="centre")
    series = [*PIPELINE, "chain"]
    xs_all = [runs[n]["photos"] for n in names]
    for key, ylabel, left in (
        ("wall_s", "wall time, s", 70),
        ("peak_rss_mb", "peak RSS, MB", 525),
    ):
        x0, x1, y0, y1 = left, left + 355, 40, 380  # plot area
        stages = series if key == "wall_s" else list(PIPELINE)
        ys = [r[key] for n in names for s in stages
              if ok(r := stage_rec(runs[n], s)) and r[key] > 0]  # fmt: skip
        if not ys or not xs_all:
            text("nothing measured", ((x0 + x1) // 2, (y0 + y1) // 2), anchor="centre")
            continue
        xlo, xhi = _span(xs_all)
        ylo, yhi = _span(ys)

        def px(x: float, y: float, xlo=xlo, xhi=xhi, ylo=ylo, yhi=yhi, x0=x0, x1=x1,
               y0=y0, y1=y1) -> tuple[int, int]:  # fmt: skip
            fx = (math.log10(x) - math.log10(xlo)) / (math.log10(xhi) - math.log10(xlo))
            fy = (math.log10(y) - math.log10(ylo)) / (math.log10(yhi) - math.log10(ylo))
            return round(x0 + fx * (x1 - x0)), round(y1 - fy * (y1 - y0))

        for t in _ticks(ylo, yhi):
            _, y = px(xlo, t)
            cv2.line(img, (x0, y), (x1, y), grey, 1)
            text(f"{t:g}", (x0 - 5, y), anchor="right")
        last = -99
        for t in sorted(set(xs_all)):
            x, _ = px(t, ylo)
            cv2.line(img, (x, y0), (x, y1), grey, 1)
            if x - last >= 30:
                text(f"{t:g}", (x, y1 + 12), anchor="centre")
                last = x
        cv2.rectangle(img, (x0, y0), (x1, y1), ink, 1)
        text("train photos", ((x0 + x1) // 2, y1 + 30), anchor="centre")
        text(ylabel, (x0, y0 - 12), 0.45)
        for stage in stages:
            colour = COLOURS[series.index(stage)]
            for shape, preset in enumerate(presets):
                pts = [px(runs[n]["photos"], r[key]) for n in names
                       if runs[n]["preset"] == preset
                       and ok(r := stage_rec(runs[n], stage)) and r[key] > 0]  # fmt: skip
                thick = 2 if stage == "chain" else 1
                for a, b in zip(pts, pts[1:], strict=False):
                    cv2.line(img, a, b, colour, thick, cv2.LINE_AA)
                for p in pts:
                    _marker(img, *p, shape % 3, colour)
    # legend: a row of stages under the panels, then the presets' markers
    for i, stage in enumerate(series):
        x, y = 30 + (i % 5) * 170, 432 + (i // 5) * 22
        colour = COLOURS[i]
        cv2.line(img, (x, y), (x + 22, y), colour, 2, cv2.LINE_AA)
        label = "chain (total; time only)" if stage == "chain" else stage
        text(label, (x + 28, y))
    if len(presets) > 1:
        x = 30
        for shape, preset in enumerate(presets):
            _marker(img, x + 5, 480, shape % 3, ink)
            text(preset, (x + 14, 480))
            x += 30 + cv2.getTextSize(preset, font, 0.4, 1)[0][0]
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(path, keep_suffix=True) as tmp:
        if not cv2.imwrite(str(tmp), img):
            raise OSError(f"cv2.imwrite could not write {tmp}")
    print(f"plot: {path}")


# --------------------------------------------------------------------- main


def main() -> None:
    if len(sys.argv) > 2 and sys.argv[1] == "--probe":  # run_probe's fresh process
        print(json.dumps(probe(sys.argv[2], *sys.argv[3:])))
        return
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", nargs="+", choices=PRESETS, default=["landmark"])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--photos", nargs="+", default=["100", "200", "400", "763"],
                   metavar="[PRESET:]N", help="train photos a size")  # fmt: skip
    p.add_argument("--threads", type=int, default=os.cpu_count() or 1)
    p.add_argument("--work", type=Path, default=ROOT / "work" / "growth")
    p.add_argument("--data", type=Path, default=None,
                   help="where the scenes are generated (default <work>/data)")  # fmt: skip
    p.add_argument("--config", type=Path, default=ROOT / "configs" / "default.toml",
                   help="the --config every stage gets (make all's default)")  # fmt: skip
    p.add_argument("--set", action="append", default=[], metavar="STAGE.KEY=VALUE",
                   help="passed to every stage's command (repeatable)")  # fmt: skip
    p.add_argument("--plot", action="store_true",
                   help="draw the plot to <work>/growth.png")  # fmt: skip
    args = p.parse_args()
    for item in args.set:
        section, dot, _ = item.partition("=")[0].partition(".")
        if "=" not in item or not dot or section not in SECTIONS:
            p.error(f"--set {item!r}: write STAGE.KEY=VALUE, STAGE one of "
                    + ", ".join(SECTIONS))  # fmt: skip
    args.work = args.work.resolve()
    args.data = (args.data or args.work / "data").resolve()
    args.config = args.config.resolve()
    try:
        todo = sizes(args.preset, args.photos)
    except ValueError as exc:
        p.error(f"--photos {' '.join(args.photos)}: {exc} (give N or PRESET:N)")
    if args.threads < 1:
        p.error("--threads: at least 1")
    path = args.work / "growth.json"

    args.work.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    facts = machine_facts()
    results = {"machine": facts, "seed": args.seed, "set": list(args.set),
               "config": config_id(args.config), "config_path": str(args.config),
               "threads": args.threads,
               "stages": list(PIPELINE),
               "quality": {s: f"{q}: {src}" for s, (q, src) in QUALITY.items()},
               "runs": {}}  # fmt: skip
    if path.exists():
        prev = json.loads(path.read_text())
        prev["config"] = config_id(prev.get("config", ""))
        if all(prev.get(k) == results[k] for k in SAME) and all(
            prev.get("machine", {}).get(k) == facts[k] for k in SAME_MACHINE
        ):  # an earlier run of the same setup keeps its other sizes
            results["runs"] = prev.get("runs", {})
        else:  # another setup: its file is kept aside, never overwritten
            aside = path.with_name(f"growth.{time.strftime('%Y%m%d-%H%M%S')}.json")
            path.rename(aside)
            print(f"{path}: another setup (seed, --set, config, threads or CPU): "
                  f"kept as {aside}; this run starts a new file", file=sys.stderr)  # fmt: skip

    def save() -> None:
        save_json(path, results)

    cpus = os.cpu_count() or 1
    if args.threads > cpus:
        print(f"note: {args.threads} threads on {cpus} CPUs", file=sys.stderr)
    env = thread_env(args.threads)
    args.data.mkdir(parents=True, exist_ok=True)
    for preset, photos in todo:
        run_size(args, results, save, preset, photos, env)
    results["wall_s"] = round(time.perf_counter() - t_start, 1)
    save()

    print(f"\nseed {args.seed}, {args.threads} threads"
          + (f", --set {' '.join(args.set)}" if args.set else "")
          + f"; {facts['cpu_model'] or facts['processor']}, {cpus} CPUs; "
          f"torch {facts.get('torch')}\n")  # fmt: skip
    print_tables(results)
    if args.plot:
        plot(results, args.work / "growth.png")
    print(f"results: {path}")


if __name__ == "__main__":
    main()
