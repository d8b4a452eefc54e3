"""Stability: the answers a user reads when the input moves by what no user would notice.

    make bench-stability                               # the demo, the dev seeds, where it grows
    python bench/stability.py --part demo              # the demo scene alone
    python bench/stability.py --part dev --seeds 0-8   # the accuracy instrument's dev seeds
    python bench/stability.py --part attribute         # which stage turns a small change large
    python bench/stability.py --part attribute-dev --seeds 0-2   # the same on dev seeds
    python bench/stability.py --report-only            # tables from the results file

Perturbations (the headline four run by default; the rest on request):

  t2           the reference: 2 threads, the photos as written, native float paths
  jpeg95       the same photos re-saved as JPEG quality 95 (a copy of the scene)
  floats       torch's float paths moved: ATen's portable kernels
               (ATEN_CPU_CAPABILITY=default), MKL's compatible path (MKL_CBWR=COMPATIBLE),
               oneDNN held to SSE4.1 (ONEDNN_MAX_CPU_ISA=SSE41), the compiled
               rasterizer built for x86-64-v2 (PTOVS_MARCH)
  seed1        the chain's own seeds changed: reconstruct's and the target draw's
  t1, t3       --threads 1 / 3 (ptovs gives the same bits at every count)
  avx2         2 threads, every kernel held to AVX2 as on a CPU without AVX-512
  avx2-t1      the same on 1 thread
  torch        2 threads, the pure-PyTorch rasterizer in every stage that renders
               (demo only: several times slower)

Each perturbation runs the whole chain in a work folder of its own (artifacts are keyed
by data and config, not by rounding, so a shared folder would hand one run's answers
to the next), then reads what a user reads, stage by stage: held-out PSNR (as is,
NeRF-W), the Gaussians, the novel targets render-appearances chose, per (view, query)
the chosen level, the peak score and the mask's area, mIoU / mPA / mP, `select TEXT`'s
count, level and score, and the style vote.

The report gives each answer's spread over the perturbations (the range of a number,
max / min of a count, the share of runs that agree with the most common choice) in the
chain's order, so the first stage whose answer moves a lot is the one that amplified
the change. On the dev seeds: each seed's mIoU range, their mean, and beside it the
seed-to-seed spread of mIoU (the standard deviation over seeds), which is what a single
scene's figure is already subject to. `--set KEY=VALUE --name N --out F` measures a rule
under every perturbation, starting from each perturbation's trained chain.

`--part attribute` says which stage turns a small change into a large one. For each
demo perturbation that leaves the photos alone it reruns the chain with the
reference's (t2's) artifacts hard-linked up to a stage (`--after`; default
reconstruct, extract-features, train-ae), so the perturbation acts only on the stages
after it: a stage whose inclusion moves mIoU most is where the change grows. Every
run, attributed or whole, is also compared with the reference map by map: the
median Pearson correlation of the chosen relevancy maps and the median IoU between
the two masks, so a threshold that turns nearly equal maps into different masks shows.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, Results, seed_list  # noqa: E402  (same folder)

from ptovs.registry import stages_between  # noqa: E402  (light: no torch)

AVX2_ENV = {
    "ATEN_CPU_CAPABILITY": "avx2",
    "ONEDNN_MAX_CPU_ISA": "AVX2",
    "MKL_CBWR": "AVX2",
    "MKL_ENABLE_INSTRUCTIONS": "AVX2",
    "PTOVS_MARCH": "x86-64-v3",
}
RENDERING_STAGES = ("reconstruct", "render-appearances", "train-male", "query")
FLOAT_PATH_ENV = {
    "ATEN_CPU_CAPABILITY": "default",
    "MKL_CBWR": "COMPATIBLE",
    "ONEDNN_MAX_CPU_ISA": "SSE41",
    "PTOVS_MARCH": "x86-64-v2",
}
PERTURBATIONS: dict[str, dict] = {
    "t2": {"threads": 2},
    "jpeg95": {"threads": 2, "photos": 95},
    "floats": {"threads": 2, "env": FLOAT_PATH_ENV},
    "seed1": {
        "threads": 2,
        "sets": ["reconstruct.seed=1", "render-appearances.seed=1"],
    },
    "t1": {"threads": 1},
    "t3": {"threads": 3},
    "avx2": {"threads": 2, "env": AVX2_ENV},
    "avx2-t1": {"threads": 1, "env": AVX2_ENV},
    "torch": {"threads": 2, "sets": [f"{s}.backend=torch" for s in RENDERING_STAGES]},
}
HEADLINE = ("t2", "jpeg95", "floats", "seed1")
DEMO_TEXT = "Minaret"  # make demo's DEMO_TEXT
DEMO_CONFIG = str(ROOT / "configs" / "demo.toml")  # and its DEMO_CONFIG


def _ptovs(work: Path, threads: int, env: dict, sets: list[str], *args: str) -> str:
    """`ptovs ARGS` in a fresh process with this perturbation; its stdout."""
    cmd = [sys.executable, "-m", "ptovs", "-q", "--work-dir", str(work),
           "--threads", str(threads), *(f"--set={s}" for s in sets), *args]  # fmt: skip
    full_env = dict(os.environ, **env, PYTHONUNBUFFERED="1")
    proc = subprocess.run(cmd, capture_output=True, text=True, env=full_env)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
    return proc.stdout


def answers(work: Path, scene: Path, text: str | None, style: bool) -> dict:
    """What a user reads from a finished chain in `work` (this process reads only)."""
    from ptovs.artifacts import Artifact, read_json_dataset
    from ptovs.metrics import read_metrics

    name = scene.name
    out: dict = {}
    (recon,) = sorted((work / name / "reconstruct").glob("*.h5"))
    with Artifact(recon) as a:
        m = read_json_dataset(a.root()["metrics_json"])
    out["psnr_test"] = m.get("psnr_test")
    out["psnr_test_nerfw"] = m.get("psnr_test_nerfw")
    out["gaussians"] = m.get("gaussians")
    for path in sorted((work / name / "render-appearances").glob("*.h5"))[:1]:
        with Artifact(path) as a:
            sel = read_json_dataset(a.root()["selection_json"])
        out["targets"] = sorted(t for t in sel.get("targets", []) if t)
    (ev,) = sorted((work / name / "evaluate").glob("*.h5"))
    with Artifact(ev) as a:
        summary, pairs = read_metrics(a)
    out["miou"], out["mpa"], out["mp"] = (summary[k] for k in ("miou", "mpa", "mp"))
    (qa,) = sorted((work / name / "query").glob("*.h5"))
    with Artifact(qa) as a:
        meta = read_json_dataset(a.root()["meta_json"])
        scores = {v: a.read(v, ("score",))["score"] for v in meta["views"] if v in a}
    qi = {q: i for i, q in enumerate(meta["queries"])}
    out["pairs"] = {
        f"{p['view']}|{p['query']}": {
            "level": p["level"],
            "iou": round(p["iou"], 4),
            "area": p["pred_pixels"],
            "score": round(float(scores[p["view"]][qi[p["query"]]]), 4),
        }
        for p in pairs
    }
    if text:
        out["select"] = json.loads((work / name / "select.json").read_text())
    if style:
        rec = json.loads(
            (work / name / "style-out" / "male" / "style.json").read_text()
        )
        out["style"] = {"winner": rec["winner"], "votes": rec["votes"]}
    return out


def run_scene(
    label: str,
    scene: Path,
    work: Path,
    text: str | None,
    style: bool,
    config: str | None,
    extra: tuple[str, ...] = (),
    after: str | None = None,
) -> dict:
    """The whole chain on `scene` under perturbation `label` (and the `--set`s
    `extra`), then its answers. `after`: the perturbation acts only on the stages
    after this one (`work` already holds the reference's artifacts up to it)."""
    p = PERTURBATIONS[label]
    env, sets, threads = p.get("env", {}), [*p.get("sets", []), *extra], p["threads"]
    if after is not None:
        if p.get("photos"):
            raise ValueError(f"{label}: moved photos act from the first stage on")
        done = CHAIN[: CHAIN.index(after) + 1]
        sets = [x for x in sets if x.split(".", 1)[0] not in done]
    if p.get("photos"):
        scene = resaved(scene, work.parent / f"photos-q{p['photos']}", p["photos"])
    cfg = ["--config", config] if config else []
    t0 = time.perf_counter()
    _ptovs(work, threads, env, sets, *cfg, "evaluate", "--data", str(scene))
    if text:
        # writes select.json beside the PLY: count, level, score
        _ptovs(work, threads, env, sets, *cfg, "select", text, "--data", str(scene),
               "--out", str(work / scene.name / "select.ply"))  # fmt: skip
    if style:
        _ptovs(work, threads, env, sets, *cfg, "style", "--data", str(scene))
    res = answers(work, scene, text, style)
    res["seconds"] = round(time.perf_counter() - t0, 1)
    return res


def resaved(scene: Path, root: Path, quality: int) -> Path:
    """A copy of `scene` under `root` (same name; its labels folder beside it, as
    `synth-scene` writes them) with every photo in dense/images decoded and
    written again as JPEG of `quality`: pixels a viewer cannot tell apart,
    different bytes and a few rounding steps of difference."""
    import shutil

    import cv2

    dst = root / scene.name
    done = dst / ".resaved"
    if done.is_file():
        return dst
    if dst.exists():
        shutil.rmtree(dst)
    shutil.copytree(scene, dst)
    labels = scene.parent / "label" / scene.name  # the labels beside the scene
    if labels.is_dir() and not (root / "label" / scene.name).exists():
        shutil.copytree(labels, root / "label" / scene.name)
    for img in sorted((dst / "dense" / "images").iterdir()):
        pixels = cv2.imread(str(img), cv2.IMREAD_UNCHANGED)
        if pixels is None:
            raise RuntimeError(f"{img}: not an image OpenCV can read")
        if not cv2.imwrite(str(img.with_suffix(".tmp.jpg")), pixels,
                           [cv2.IMWRITE_JPEG_QUALITY, quality]):  # fmt: skip
            raise RuntimeError(f"{img}: could not write it again")
        img.with_suffix(".tmp.jpg").replace(img)
    done.write_text(str(quality))
    return dst


CHAIN = stages_between("reconstruct", "train-male")  # the stages before the answers
ATTRIBUTE_AFTER = ("reconstruct", "extract-features", "train-ae")


def seeded_work(base: Path, work: Path, stages: tuple[str, ...] = CHAIN) -> Path:
    """`work` holding the base run's artifacts of `stages` (default: the chain up
    to train-male), hard-linked (artifacts are replaced, never written in place),
    so only the stages after them run again. Files already there are kept."""
    import os

    for src in sorted(base.rglob("*")) if base.is_dir() else []:
        rel = src.relative_to(base)
        if len(rel.parts) < 2 or rel.parts[1] not in stages:
            continue
        dst = work / rel
        if src.is_dir():
            dst.mkdir(parents=True, exist_ok=True)
        elif not dst.exists():
            dst.parent.mkdir(parents=True, exist_ok=True)
            os.link(src, dst)
    return work


# ------------------------------------------------------------------ spreads --
def spread_numbers(values: list[float]) -> float:
    v = [x for x in values if x is not None]
    return float(max(v) - min(v)) if v else float("nan")


def ratio_counts(values: list[int]) -> float:
    v = [x for x in values if x is not None]
    return float(max(v) / max(min(v), 1)) if v else float("nan")


def agreement(choices: list) -> float:
    """Share of runs that give the most common choice."""
    return Counter(choices).most_common(1)[0][1] / len(choices) if choices else 1.0


def scene_spread(runs: dict[str, dict]) -> dict:
    """Per answer, its spread over the perturbations of one scene."""
    rs = list(runs.values())
    out = {
        "runs": list(runs),
        "miou": [r["miou"] for r in rs],
        "miou_range": spread_numbers([r["miou"] for r in rs]),
        "psnr_test_range": spread_numbers([r["psnr_test"] for r in rs]),
        "psnr_nerfw_range": spread_numbers([r["psnr_test_nerfw"] for r in rs]),
        "gaussians_ratio": ratio_counts([r["gaussians"] for r in rs]),
    }
    if all("targets" in r for r in rs):
        sets = [set(r["targets"]) for r in rs]
        ref = sets[0]
        out["targets_same"] = [s == ref for s in sets]
        out["targets_shared"] = [len(s & ref) / max(len(ref), 1) for s in sets]
    keys = sorted(set.intersection(*(set(r["pairs"]) for r in rs)))
    if keys:
        lv = [agreement([r["pairs"][k]["level"] for r in rs]) for k in keys]
        out["level_agreement"] = float(np.mean(lv))
        out["level_flips"] = int(sum(a < 1 for a in lv))
        out["score_range_mean"] = float(
            np.mean(
                [spread_numbers([r["pairs"][k]["score"] for r in rs]) for k in keys]
            )
        )
        out["area_ratio_median"] = float(
            np.median([ratio_counts([r["pairs"][k]["area"] for r in rs]) for k in keys])
        )
        out["iou_range_mean"] = float(
            np.mean([spread_numbers([r["pairs"][k]["iou"] for r in rs]) for k in keys])
        )
        out["pairs"] = len(keys)
    if all("select" in r for r in rs):
        out["select"] = [r["select"]["selected"] for r in rs]
        out["select_ratio"] = ratio_counts(out["select"])
        out["select_levels"] = [r["select"]["level"] for r in rs]
    if all("style" in r for r in rs):
        out["style_winners"] = [r["style"]["winner"] for r in rs]
        out["style_agreement"] = agreement(out["style_winners"])
    return out


def map_agreement(ref: Path, work: Path) -> dict:
    """A run's query against the reference's, pair by pair (view, query): the
    Pearson correlation of the two relevancy maps at the reference's level and
    the IoU of the two masks; medians over the pairs both answered."""
    from ptovs.artifacts import Artifact
    from ptovs.field.query import read_results

    def load(w: Path) -> tuple[dict, dict]:
        (path,) = sorted(w.glob("query/*.h5"))
        with Artifact(path) as a:
            return read_results(a, ("mask", "level", "smoothed"))

    (ma, va), (mb, vb) = load(ref), load(work)
    corr, iou = [], []
    for name in sorted(set(va) & set(vb)):
        for qi, text in enumerate(ma["queries"]):
            if text not in mb["queries"]:
                continue
            qj, lv = mb["queries"].index(text), int(va[name]["level"][qi])
            a = va[name]["smoothed"][qi, lv].astype(np.float64).ravel()
            b = vb[name]["smoothed"][qj, lv].astype(np.float64).ravel()
            if a.std() > 0 and b.std() > 0:
                corr.append(float(np.corrcoef(a, b)[0, 1]))
            m1, m2 = va[name]["mask"][qi] > 0, vb[name]["mask"][qj] > 0
            union = int((m1 | m2).sum())
            iou.append(float((m1 & m2).sum() / union) if union else 1.0)
    return {
        "map_corr_median": float(np.median(corr)) if corr else None,
        "mask_iou_median": float(np.median(iou)) if iou else None,
        "pairs": len(iou),
    }


def compare_maps(args: argparse.Namespace, root: Path, runs: dict, scene: str) -> None:
    """Adds `map_agreement` against the reference to each finished run of `runs`
    (the perturbations' work folders under `root`) that lacks it."""
    ref = _work(args, root, HEADLINE[0]) / scene
    for label, r in runs.items():
        work = _work(args, root, label) / scene
        if "maps" not in r and label != HEADLINE[0] and ref.is_dir() and work.is_dir():
            r["maps"] = map_agreement(ref, work)


# -------------------------------------------------------------------- parts --
def _work(args: argparse.Namespace, root: Path, label: str) -> Path:
    """The perturbation's work folder; under `--set`s (`--name`) a folder of its
    own that starts from the plain run's chain."""
    if not args.set:
        return root / label
    return seeded_work(root / label, root / f"{label}+{args.name}")


def part_demo(args: argparse.Namespace, res: Results) -> None:
    data = args.data / "demo"
    scene = data / "demo_s0"
    if not scene.is_dir():
        subprocess.run([sys.executable, "-m", "ptovs", "synth-scene", str(data),
                        "--preset", "demo", "--seed", "0"], check=True)  # fmt: skip
    demo = res.setdefault("demo", {})
    for label in args.demo_perturbations:
        if label in demo:
            continue
        print(f"demo {label} ...", flush=True)
        work = _work(args, args.work / "demo", label)
        demo[label] = run_scene(label, scene, work, args.text, True, DEMO_CONFIG,
                                tuple(args.set))  # fmt: skip
        res.save()
    compare_maps(args, args.work / "demo", demo, scene.name)
    res.save()


def part_attribute(args: argparse.Namespace, res: Results, dev: bool = False) -> None:
    """The perturbations that leave the photos alone, each acting only after each
    stage of `--after` (the reference's chain linked up to it): on the demo, or
    (`dev`) on each dev seed of `--seeds` whose reference chain `--part dev` made
    (under `--set`s, the reference is that rule's chain and every run keeps them)."""
    suffix = f"+{args.name}" if args.set else ""  # a --set rule's own chains
    if dev:
        ref = args.work / "dev" / (HEADLINE[0] + suffix)
        config, text, labels = (
            str(ROOT / "configs" / "accuracy.toml"),
            None,
            args.dev_perturbations,
        )
        scenes = {str(s): args.acc_data / f"small_s{s}" for s in seed_list(args.seeds)}
    else:
        ref = args.work / "demo" / (HEADLINE[0] + suffix)
        config, text, labels = DEMO_CONFIG, args.text, args.demo_perturbations
        scenes = {"demo": args.data / "demo" / "demo_s0"}
    for name, scene in scenes.items():
        if not (ref / scene.name).is_dir():
            raise SystemExit(f"{ref / scene.name}: run --part {'dev' if dev else 'demo'} "
                             "first (the reference's chain)")  # fmt: skip
        attr = res.setdefault("attribute", {}).setdefault(name, {})
        for label in labels:
            if label == HEADLINE[0] or PERTURBATIONS[label].get("photos"):
                continue
            for stage in args.after:
                key = f"{label}@{stage}"
                if key in attr:
                    continue
                print(f"{name} {label}, after {stage} ...", flush=True)
                work = seeded_work(ref, args.work / "attribute" / name / (key + suffix),
                                   CHAIN[: CHAIN.index(stage) + 1])  # fmt: skip
                attr[key] = run_scene(label, scene, work, text, False, config,
                                      tuple(args.set), after=stage)  # fmt: skip
                attr[key]["maps"] = map_agreement(ref / scene.name, work / scene.name)
                res.save()


def part_dev(args: argparse.Namespace, res: Results) -> None:
    dev = res.setdefault("dev", {})
    config = str(ROOT / "configs" / "accuracy.toml")
    for seed in seed_list(args.seeds):
        scene = args.acc_data / f"small_s{seed}"
        if not scene.is_dir():
            subprocess.run([sys.executable, "-m", "ptovs", "synth-scene", str(args.acc_data),
                            "--preset", "small", "--seed", str(seed)], check=True)  # fmt: skip
        runs = dev.setdefault(str(seed), {})
        for label in args.dev_perturbations:
            if label in runs:
                continue
            print(f"dev seed {seed} {label} ...", flush=True)
            work = _work(args, args.work / "dev", label)
            runs[label] = run_scene(label, scene, work, None, False, config,
                                    tuple(args.set))  # fmt: skip
            res.save()
        compare_maps(args, args.work / "dev", runs, scene.name)
        res.save()


# ------------------------------------------------------------------- report --
def print_stages(s: dict) -> None:
    """One scene's spreads in the chain's order: where a small change grows."""
    print("\nStage by stage (spread over the runs):")
    print(f"  reconstruct         held-out PSNR range {s['psnr_test_range']:.2f} dB, "
          f"Gaussians max/min {s['gaussians_ratio']:.2f}")  # fmt: skip
    if "targets_same" in s:
        same = sum(s["targets_same"]) - 1
        shared = np.mean(s["targets_shared"][1:]) if len(s["targets_shared"]) > 1 else 1
        print(f"  render-appearances  targets equal to the reference in {same} of "
              f"{len(s['targets_same']) - 1} runs; {shared:.0%} shared on average")  # fmt: skip
    if "pairs" in s:
        print(f"  query               level agreement {s['level_agreement']:.2f} "
              f"({s['level_flips']} of {s['pairs']} pairs flip); peak score range "
              f"{s['score_range_mean']:.3f}; mask area max/min (median) "
              f"{s['area_ratio_median']:.2f}")  # fmt: skip
    print(f"  evaluate            mIoU range {s['miou_range']:.3f}")
    if "select_ratio" in s:
        print(f"  select              count max/min {s['select_ratio']:.2f} "
              f"({s['select']})")  # fmt: skip


def report(res: Results) -> None:
    demo = res.get("demo", {})
    if len(demo) >= 2:
        s = scene_spread(demo)
        res["demo_spread"] = s
        print("\nDemo (the demo scene), per perturbation:")
        print(
            "| run | mIoU / mPA / mP | select | level | style | held-out PSNR / NeRF-W |"
        )
        print("|---|---|---|---|---|---|")
        for k, r in demo.items():
            sel = r.get("select", {})
            print(f"| {k} | {r['miou']:.3f} / {r['mpa']:.3f} / {r['mp']:.3f} | "
                  f"{sel.get('selected')} of {sel.get('gaussians')} | {sel.get('level')} | "
                  f"{r.get('style', {}).get('winner')} | "
                  f"{r['psnr_test']:.2f} / {r['psnr_test_nerfw']:.2f} |")  # fmt: skip
        print_stages(s)
        print(f"\nmIoU range {s['miou_range']:.3f}; select max/min {s.get('select_ratio', 0):.2f}; "
              f"level agreement {s.get('level_agreement', 1):.2f} ({s.get('level_flips')} "
              f"pairs flip); score range {s.get('score_range_mean', 0):.3f}; "
              f"mask area max/min (median) {s.get('area_ratio_median', 0):.2f}")  # fmt: skip
    for name, attr in res.get("attribute", {}).items():
        runs = demo if name == "demo" else res.get("dev", {}).get(name, {})
        if HEADLINE[0] not in runs:
            continue
        base = runs[HEADLINE[0]]["miou"]
        print(f"\nWhere the change grows ({'the demo' if name == 'demo' else 'dev seed ' + name}): "
              f"the perturbation acting only after a stage; {HEADLINE[0]} reads {base:.3f}")  # fmt: skip
        print("| perturbation | acts after | mIoU | Δ | map correlation | mask IoU |")
        print("|---|---|---|---|---|---|")
        for label in (k for k in runs if k != HEADLINE[0]):
            rows = [(k.split("@")[1], r) for k, r in attr.items()
                    if k.split("@")[0] == label]  # fmt: skip
            for stage, r in [*rows, ("(whole chain)", runs[label])]:
                m = r.get("maps", {})
                corr, iou = m.get("map_corr_median"), m.get("mask_iou_median")
                print(f"| {label} | {stage} | {r['miou']:.3f} | {r['miou'] - base:+.3f} | "
                      f"{'–' if corr is None else f'{corr:.3f}'} | "
                      f"{'–' if iou is None else f'{iou:.2f}'} |")  # fmt: skip
    dev = res.get("dev", {})
    per_seed = {k: scene_spread(v) for k, v in dev.items() if len(v) >= 2}
    if per_seed:
        ranges = [s["miou_range"] for s in per_seed.values()]
        base = [v[next(iter(v))]["miou"] for v in dev.values() if v]
        res["dev_spread"] = {
            "seeds": list(per_seed),
            "miou_range": ranges,
            "miou_range_mean": float(np.mean(ranges)),
            "seed_sd": float(np.std(base, ddof=1)) if len(base) > 1 else None,
            "level_flips": [s.get("level_flips") for s in per_seed.values()],
            "pairs": [s.get("pairs") for s in per_seed.values()],
        }
        d = res["dev_spread"]
        print(
            "\nDev seeds, per seed: mIoU per perturbation, range, level flips / pairs"
        )
        for k, s in per_seed.items():
            print(f"  seed {k}: {' '.join(f'{x:.3f}' for x in s['miou'])}  range "
                  f"{s['miou_range']:.3f}  flips {s.get('level_flips')}/{s.get('pairs')}")  # fmt: skip
        print(f"mean range {d['miou_range_mean']:.3f}; seed-to-seed SD {d['seed_sd']}")
    res.save()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--part", choices=("demo", "dev", "attribute", "attribute-dev"), nargs="*",
        default=["demo", "dev", "attribute"],
    )  # fmt: skip
    ap.add_argument("--after", nargs="+", default=list(ATTRIBUTE_AFTER), choices=CHAIN,
                    help="attribute: the stages after which the perturbation acts")  # fmt: skip
    ap.add_argument("--seeds", nargs="+", default=["0-8"], help="dev seeds")
    ap.add_argument("--demo-perturbations", nargs="+", default=list(HEADLINE),
                    choices=list(PERTURBATIONS))  # fmt: skip
    ap.add_argument("--dev-perturbations", nargs="+", default=list(HEADLINE),
                    choices=list(PERTURBATIONS))  # fmt: skip
    ap.add_argument("--text", default=DEMO_TEXT, help="the demo's select phrase")
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "stability")
    ap.add_argument("--acc-data", type=Path, default=ROOT / "data" / "accuracy")
    ap.add_argument("--work", type=Path, default=ROOT / "work" / "stability")
    ap.add_argument(
        "--out", type=Path, default=ROOT / "work" / "stability" / "stability.json"
    )
    ap.add_argument("--report-only", action="store_true")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="STAGE.KEY=VALUE",
        help="a setting for every run (e.g. query.threshold_mode=stable); give "
        "--name and --out too: the runs start from the plain runs' chains",
    )
    ap.add_argument("--name", default="set", help="names the --set runs' work folders")
    ap.add_argument("--merge", type=Path, nargs="*", default=[],
                    help="results files of runs made apart (e.g. one per perturbation, "
                    "in parallel), merged into --out first")  # fmt: skip
    args = ap.parse_args()
    res = Results(args.out)
    for extra in args.merge:
        other = json.loads(extra.read_text())
        for part in ("demo", "dev"):
            for k, v in other.get(part, {}).items():
                if part == "dev":
                    res.setdefault(part, {}).setdefault(k, {}).update(v)
                else:
                    res.setdefault(part, {})[k] = v
    if not args.report_only:
        if "demo" in args.part:
            part_demo(args, res)
        if "dev" in args.part:
            part_dev(args, res)
        if "attribute" in args.part:
            part_attribute(args, res)
        if "attribute-dev" in args.part:
            part_attribute(args, res, dev=True)
    report(res)


if __name__ == "__main__":
    main()
