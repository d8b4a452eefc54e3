"""The real-class chain measured end to end: photos to query and select.

    python bench/real_chain.py --photos 200 --work work/real_chain     # make bench-real-chain

The scene is the `landmark` preset's world with --photos train photos (about 700 px
on the long side, as PT-OVS's; generated under <work>/data when missing). The
encoder is MobileCLIP2-S0 with random weights (seeded) written to a local
`.safetensors` checkpoint, exactly as a user's own file is read: the arithmetic of
the trained model, not its accuracy. The segmenter is `hier`. Every stage runs in its
own process as a user runs it (`ptovs --config <cfg> <stage> --variant V`), on
--threads threads, and is timed from outside (wall s, peak RSS of that process, CPU s,
the machine's 1-min load before and after):

  full    the paper's recipe (`--variant male`): the photo and its N = 4 renders
          encoded, uncertainty, train-ae, train-male, query, evaluate, select
  photo   the photo alone (`--variant langsplat-wild`): originals only, one
          appearance; reconstruct is shared with `full` (same key, cached), and is
          counted in both chains' totals

`--sam2 K` also times SAM 2.1 tiny (random weights, --sam2-points² prompts, no crop
layer, LangSplat's filters) on the first K photos of the scene, photo by photo in one
process, with its user and system CPU seconds: the segmenter's cost a photo. (Random
weights give no mask past the filters, so extract-features itself would rightly stop
at its empty-segment guard; with a trained checkpoint the stage adds the encoder's
seconds of the masks found.)

Results go to <work>/real_chain.json after every stage (a stage measured earlier with
the same commit, photos, precision and machine is kept unless --fresh), then a table.
`--project 763` adds each stage's seconds at that many photos, **projected** from this
run: the per-view stages (render-appearances, extract-features, uncertainty) linearly
in photos, the others (reconstruct, a fixed step count; train-ae, train-male, query,
evaluate) with the exponent b of a·photos^b fitted to the stand-in's growth runs
(docs/results/growth_*.json), select linearly. A projection is
labelled as one wherever it is printed.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, machine_facts, run_stage, save_json, thread_env  # noqa: E402

MODEL = "MobileCLIP2-S0"
FULL = ["reconstruct", "render-appearances", "extract-features", "uncertainty",
        "train-ae", "train-male", "query", "evaluate", "select"]  # fmt: skip
PHOTO = ["reconstruct", "extract-features", "train-ae", "train-male", "query",
         "evaluate", "select"]  # fmt: skip
RECIPES = {"full": ("male", FULL), "photo": ("langsplat-wild", PHOTO)}
PER_VIEW = {"render-appearances", "extract-features", "uncertainty"}


def scene(data: Path, photos: int) -> Path:
    path = data / f"landmark_s0_p{photos}"
    if not (path / "dense").is_dir():
        subprocess.run(
            [sys.executable, "-m", "ptovs", "-q", "synth-scene", str(data),
             "--preset", "landmark", "--seed", "0", "--photos", str(photos)],
            check=True,
        )  # fmt: skip
    return path


def random_clip(path: Path) -> Path:
    """MobileCLIP2-S0 with seeded random weights, saved as a user's .safetensors.

    Built in a child process: this process stays small, since a stage's peak RSS
    (wait4's ru_maxrss) starts from what its parent held when it forked."""
    if path.is_file():
        return path
    path.parent.mkdir(parents=True, exist_ok=True)
    code = f"""
import os, torch
from safetensors.torch import save_file
from ptovs.compat import import_backend
open_clip = import_backend("open_clip")  # PyPI's torchvision stubbed as ptovs does
torch.manual_seed(0)
net = open_clip.create_model({MODEL!r}, pretrained=None)
tmp = {str(path.with_suffix(".tmp"))!r}
save_file({{k: v.contiguous() for k, v in net.state_dict().items()}}, tmp)
os.replace(tmp, {str(path)!r})
"""
    subprocess.run([sys.executable, "-c", code], check=True)
    return path


def write_config(work: Path, ckpt: Path, precision: str) -> Path:
    """configs/photos-cpu.toml with the random checkpoint and `precision`."""
    text = (ROOT / "configs" / "photos-cpu.toml").read_text()
    text = text.replace(
        'clip_checkpoint = "ckpt/MobileCLIP2-S0-OpenCLIP/open_clip_model.safetensors"',
        f'clip_checkpoint = "{ckpt}"',
    ).replace('precision = "auto"', f'precision = "{precision}"')
    if f'"{ckpt}"' not in text or f'precision = "{precision}"' not in text:
        raise SystemExit("configs/photos-cpu.toml changed: update bench/real_chain.py")
    # a synthetic scene's query would take the stand-in's text side by default
    text += '\n[query]\nencoder = "openclip"\n'
    path = work / f"real_{precision}.toml"
    path.write_text(text)
    return path


def command(work: Path, cfg: Path, stage: str, sc: Path, variant: str,
            threads: int, sets: list[str], phrase: str) -> list[str]:  # fmt: skip
    cmd = [sys.executable, "-m", "ptovs", "--work-dir", str(work / "runs"),
           "--config", str(cfg), "-q", "--threads", str(threads)]  # fmt: skip
    if stage == "select":
        out = work / "out" / f"select_{sc.name}_{variant}.ply"
        out.parent.mkdir(parents=True, exist_ok=True)
        return [*cmd, "select", phrase, "--scene", sc.name, "--data", str(sc),
                "--variant", variant, "--out", str(out), *sets]  # fmt: skip
    if stage == "query":
        out = work / "out" / f"query_{sc.name}_{variant}"
        return [*cmd, "query", "--scene", sc.name, "--data", str(sc), "--variant",
                variant, "--out", str(out), *sets]  # fmt: skip
    return [*cmd, stage, "--scene", sc.name, "--data", str(sc),
            *variant_sets(variant, stage), *sets]  # fmt: skip


def variant_sets(variant: str, stage: str) -> list[str]:
    """The recipe as --set items for a stage command without --variant: its own
    and its upstream stages' values (`ptovs.variants`)."""
    from ptovs.variants import VARIANTS

    upto = FULL[: FULL.index(stage) + 1]
    return [f"--set={st}.{kv}" for st, kvs in VARIANTS[variant].items()
            if st in upto for kv in kvs]  # fmt: skip


def first_phrase(sc: Path) -> str:
    vocab = json.loads((sc / "synthetic" / "vocabulary.json").read_text())
    names = vocab.get("parts") or vocab.get("phrases") or vocab
    if isinstance(names, dict):
        names = list(names)
    return str(names[0])


def project(stage: str, seconds: float, photos: int, to: int, growth: dict) -> float:
    if stage in PER_VIEW or stage not in growth:
        return seconds * to / photos
    return seconds * (to / photos) ** growth[stage]


def growth_exponents() -> dict[str, float]:
    """Each stage's exponent b of a·photos^b in the stand-in's growth runs."""
    import math

    out: dict[str, float] = {}
    for f in sorted((ROOT / "docs" / "results").glob("growth_*.json")):
        runs = json.loads(f.read_text()).get("runs", {})
        pts: dict[str, list[tuple[float, float]]] = {}
        for run in runs.values():
            for st, rec in run.get("stages", {}).items():
                if rec.get("exit") == 0:
                    pts.setdefault(st, []).append((run["photos_asked"], rec["wall_s"]))
        for st, p in pts.items():
            if len(p) >= 2:
                xs = [math.log(x) for x, _ in p]
                ys = [math.log(y) for _, y in p]
                mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
                den = sum((x - mx) ** 2 for x in xs)
                if den > 0:
                    out[st] = (
                        sum((x - mx) * (y - my) for x, y in zip(xs, ys, strict=True))
                        / den
                    )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--photos", type=int, default=200)
    ap.add_argument("--recipes", nargs="*", default=["full", "photo"],
                    choices=list(RECIPES))  # fmt: skip
    ap.add_argument("--precision", default="fp32", choices=["fp32", "bf16", "auto"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--sam2", type=int, default=0, metavar="K",
                    help="also SAM 2.1 tiny's extract-features on K photos")  # fmt: skip
    ap.add_argument("--sam2-points", type=int, default=8)
    ap.add_argument("--project", type=int, default=763)
    ap.add_argument("--work", type=Path, default=ROOT / "work" / "real_chain")
    ap.add_argument("--fresh", action="store_true")
    ap.add_argument("--until", default="", metavar="STAGE",
                    help="stop each recipe after this stage")  # fmt: skip
    ap.add_argument("--resume", action="store_true",
                    help="keep stages measured at another commit (each record "
                         "names its own commit)")  # fmt: skip
    ap.add_argument("--set", action="append", default=[], metavar="STAGE.KEY=VALUE")
    a = ap.parse_args()
    a.work.mkdir(parents=True, exist_ok=True)
    out_json = a.work / "real_chain.json"
    facts = machine_facts()
    old = {} if a.fresh or not out_json.is_file() else json.loads(out_json.read_text())
    kept = (
        ("cpu_model", "cpu_count") if a.resume else ("cpu_model", "cpu_count", "commit")
    )
    same = all(old.get("machine", {}).get(k) == facts.get(k) for k in kept)
    results = {"machine": facts, "photos": a.photos, "precision": a.precision,
               "threads": a.threads, "model": MODEL, "set": a.set,
               "runs": old.get("runs", {}) if same else {}}  # fmt: skip
    sc = scene(a.work / "data", a.photos)
    ckpt = random_clip(a.work / "ckpt" / "mobileclip2_s0_random.safetensors")
    cfg = write_config(a.work, ckpt, a.precision)
    env = thread_env(a.threads)
    logs = a.work / "logs"
    logs.mkdir(exist_ok=True)
    phrase = first_phrase(sc)
    sets = [f"--set={s}" for s in a.set]
    print(f"real chain: {sc.name}, {MODEL} (random weights, {a.precision}), "
          f"{a.threads} threads, select {phrase!r}", file=sys.stderr)  # fmt: skip

    def step(label: str, st: str, scn: Path, variant: str, config: Path) -> bool:
        run = results["runs"].setdefault(
            label, {"scene": scn.name, "precision": a.precision, "stages": {}}
        )
        if run["stages"].get(st, {}).get("exit") == 0:
            return True
        cmd = command(a.work, config, st, scn, variant, a.threads, sets, phrase)
        rec = run_stage(cmd, env, logs, f"{label}-{st}")
        rec["date"] = time.strftime("%Y-%m-%d %H:%M")
        rec["commit"] = facts.get("commit")
        run["stages"][st] = rec
        save_json(out_json, results)
        print(f"{label:<7} {st:<20} {rec['wall_s']:9.1f} s {rec['peak_rss_mb']:7.0f} MB"
              f"  load {rec['load']}  exit {rec['exit']}", file=sys.stderr, flush=True)  # fmt: skip
        if rec["exit"] != 0:
            print(rec.get("stderr_tail", "")[-1500:], file=sys.stderr)
        return rec["exit"] == 0

    for name in a.recipes:
        variant, stages = RECIPES[name]
        for st in stages:
            if not step(name, st, sc, variant, cfg) or st == a.until:
                break
    if a.sam2:
        results["sam2"] = sam2_seconds(sc, a.sam2, a.sam2_points, a.threads)
        save_json(out_json, results)
    report(results, a.project)


def sam2_seconds(sc: Path, k: int, points: int, threads: int) -> dict:
    """SAM 2.1 tiny's seconds a photo on the first k photos of the scene."""
    import cv2
    import torch

    from ptovs.segment.sam2 import Sam2Segmenter, build_sam2_model

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    seg = Sam2Segmenter(model=build_sam2_model("tiny", "cpu"),
                        points_per_side=points, crop_n_layers=0)  # fmt: skip
    files = sorted((sc / "dense" / "images").glob("*.jpg"))[:k]
    rows = []
    for f in files:
        img = cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2RGB)
        c0, t0 = os.times(), time.perf_counter()
        levels = seg.segment(img)
        c1, wall = os.times(), time.perf_counter() - t0
        rows.append({"photo": f.name, "size": list(img.shape[:2]), "wall_s": wall,
                     "user_s": c1.user - c0.user, "sys_s": c1.system - c0.system,
                     "segments": [lv.n for lv in levels]})  # fmt: skip
        print(f"sam2    {f.name} {wall:6.1f} s (user {rows[-1]['user_s']:.1f}, "
              f"sys {rows[-1]['sys_s']:.1f})", file=sys.stderr, flush=True)  # fmt: skip
    walls = sorted(r["wall_s"] for r in rows[1:] or rows)  # the first warms up
    return {"photos": len(rows), "points": points, "median_s": walls[len(walls) // 2],
            "user_s": sum(r["user_s"] for r in rows),
            "sys_s": sum(r["sys_s"] for r in rows), "rows": rows}  # fmt: skip


def report(results: dict, to: int) -> None:
    growth = growth_exponents()
    n = results["photos"]
    print(f"\n| stage | recipe | seconds ({n} photos, measured) | peak MB | "
          f"seconds at {to} photos (projected) |\n|---|---|---|---|---|")  # fmt: skip
    for label, run in results["runs"].items():
        total, proj = 0.0, 0.0
        full = run["stages"]
        # the shared reconstruct counts in both chains, as measured (the other
        # chain finds it cached)
        ran = [r["stages"]["reconstruct"] for r in results["runs"].values()
               if "reconstruct" in r["stages"]]  # fmt: skip
        if ran:
            full = {**full, "reconstruct": max(ran, key=lambda r: r["wall_s"])}
        for st, rec in full.items():
            if rec.get("exit") != 0:
                continue
            total += rec["wall_s"]
            p = project(st, rec["wall_s"], n, to, growth)
            proj += p
            print(f"| {st} | {label} | {rec['wall_s']:.0f} | {rec['peak_rss_mb']:.0f} "
                  f"| {p:.0f} |")  # fmt: skip
        print(f"| **whole chain** | {label} | **{total:.0f}** ({total / 3600:.2f} h) | "
              f"| **{proj:.0f}** ({proj / 3600:.2f} h, projected) |")  # fmt: skip
    if "sam2" in results:
        r = results["sam2"]
        print(f"\nSAM 2.1 tiny, {r['points']}² points, {r['photos']} photos: "
              f"{r['median_s']:.1f} s a photo (median), CPU user {r['user_s']:.0f} s, "
              f"system {r['sys_s']:.0f} s")  # fmt: skip


if __name__ == "__main__":
    main()
