"""The accuracy instrument: it can see a 0.05 mIoU difference.

    make bench-accuracy                                   # what docs/results.md reports
    python bench/accuracy.py --preset small --seeds 0-17  # the same, by hand
    python bench/accuracy.py --report-only                # tables and plot from the results
    make bench-multiapp                                   # in stand-in 5's world (--standin 5)

Every seed is a new synthetic landmark (`ptovs synth-scene`, written for the
stand-in `--standin`): every part labelled in its evaluation views is a query
unless the generator's screen finds its phrase unanswerable
(`ptovs.synthetic.screen`). Per seed, in a subprocess of its own (two at a time
on two cores, one thread each), the instrument measures, on every (evaluation
view, query) pair:

  male                the full method (ptovs defaults: the paper's method with the
                      authors' code's AE weighting and the training-free lift)
  optimise            the same with train-male's optimiser (`--variant optimise`)
  paper               the paper's text exactly (`--variant paper`)
  langsplat           LangSplat's recipe on plain-3DGS geometry
  langsplat-wild      the same recipe on the in-the-wild geometry
  oracle              the full method's language recipe on clean features: every
                      photo re-rendered at its camera under neutral light without
                      occluders, its features imported in every appearance slot
  2d                  2-D ceiling: the pipeline's relevancy on the raw 512-d segment
                      features of the evaluation photo itself (no field, no AE)
  2d-ae               the same features through the full method's autoencoder
  2d-nosmooth         2d without the query's mean and majority filters
  2d-best             the best union of the pipeline's segments per query (best
                      prefix by share inside the truth mask, best level)
  2d-truth            2d on the truth part masks' features (`segmenter = "truth"`)
  slot-orig, slot-nov1..3   the full method's field, one appearance slot alone
  no-multi-appearance, no-tum-aum, no-tum, no-aum, no-bg-filter, imglvlmax,
  pixmax, pixavg, pixweighted   Table 3 rows 1 and 6-13 (ptovs.variants)
  budget-300, budget-3k         train-male's optimiser at two fixed iteration budgets
  on request only (--labels):
  no-uncertainty-ae, lift-codes   Table 3 row 3 (train-ae unweighted), the
                      code-space lift (each Gaussian's mean target code)
  male-truth, langsplat-truth, no-multi-appearance-truth   Table 3 rows with the
                      truth part masks as segments (the paper's SAM setting's bound)
  same-appearance-truth, select-random-truth   Table 4 on truth segments (one
                      appearance, random targets; compare with --base male-truth)
  male-segment-each, male-segment-once-self   the full method segmenting every
                      image of a view (the paper's), or the view once from its self
                      render instead of its photo (extract-features.segment, _from)
  male-min-crop-16, male-min-crop-32   the full method without the segments
                      whose crop is under 16 / 32 px (extract-features.min_crop_px)

A finished seed's pairs go to <work>/results/<scene>.json (atomically), each label
with the artifact key of what it measured. A rerun drops every label whose key the
code or config no longer gives and computes the missing ones; an interrupted seed
resumes from the artifact cache, so an unchanged label costs a cache lookup.

The report treats each (seed, query) as one cluster: mIoU is the mean of cluster
means; a comparison with the full method is the mean paired per-cluster
difference with a 95 % cluster-bootstrap interval (`ptovs.stats`). Seeds are split
into a fixed dev half (the first half of the list: for choosing anything) and a
test half (for reporting only).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from accuracy_labels import (  # noqa: E402  (same folder)
    ALL_LABELS,
    CHAIN_LABELS,
    FEATURE_LABELS,
    LABELS,
    TRUTH_SEGMENTS,
)
from accuracy_report import (  # noqa: E402, F401  (importers read the report's here)
    _baseline,
    _ceiling_lines,
    _main_table,
    _render_lines,
    _result_path,
    load_results,
    report,
    summarise,
    unanswered,
)
from common import ROOT, seed_list  # noqa: E402  (same folder)

VERSION = 1  # bump when what a seed's results mean changes


# ------------------------------------------------------------------ one seed --


def _scene(data: Path, preset: str, seed: int, standin: int = 1) -> Path:
    """The seed's scene in the world of stand-in `standin`, generated if missing;
    a scene made for another stand-in is an error (another --data folder)."""
    from ptovs.encoders import standin_version

    scene = data / f"{preset}_s{seed}"
    if not (scene / "synthetic" / "truth" / "cameras.json").is_file():
        from ptovs.synthetic import generate_scene

        generate_scene(data, preset, seed, progress=False, standin=standin)
    vocab = json.loads((scene / "synthetic" / "vocabulary.json").read_text())
    if standin_version(vocab) != standin:
        raise SystemExit(
            f"{scene} was generated for stand-in {standin_version(vocab)}, not "
            f"{standin}: give another --data folder (e.g. data/accuracy-v{standin})"
        )
    return scene


def chosen_targets(ctx, ref, variant: str, sets: dict, cams: dict) -> dict | None:
    """The novel targets the chain's render-appearances chose, each with its
    truth appearance (sky, film filter, exposure), and the fidelity of the field
    they were rendered from (reconstruct's own PSNR, train and test photos): None
    where the chain renders no appearances."""
    from ptovs.artifacts import read_json_dataset
    from ptovs.stage import Chain
    from ptovs.variants import variant_sets

    chain = Chain(ctx, ref, variant_sets(variant, sets))
    if "render-appearances" not in chain.closure("evaluate"):
        return None
    art = chain.inputs_of("render-appearances")
    try:
        slots = read_json_dataset(art.root()["slots_json"])
    finally:
        art.close()
    art = chain.inputs_of("reconstruct")  # the renders' fidelity
    try:
        root = art.root()
        fit = read_json_dataset(root["metrics_json"]) if "metrics_json" in root else {}
    finally:
        art.close()
    truth = {r["name"]: r.get("appearance", {}) for r in cams["images"]}
    out = []
    for t in slots["targets"]:
        a = truth.get(f"{t}.jpg", truth.get(t, {})) if t is not None else {}
        out.append({"id": t, "sky": a.get("sky"), "filter": a.get("filter"),
                    "exposure": a.get("exposure")})  # fmt: skip
    return {"targets": out, "psnr_train": fit.get("psnr_train"),
            "psnr_test": fit.get("psnr_test")}  # fmt: skip


def _run_s(art) -> float:
    return float(json.loads(art.attrs["timings_json"])["run_s"])


def _build(chain, stage: str) -> tuple[object, dict[str, float]]:
    """Every stage `stage` needs, then `stage` (cached ones return at once):
    its open artifact and each stage's recorded run time."""
    from ptovs.stage import execute

    secs = {}
    for st in chain.closure(stage):
        art = execute(chain, st)
        secs[st] = _run_s(art)
        if st == stage:
            return art, secs
        art.close()
    raise AssertionError(f"{stage} not in its own closure")


def _chain_pairs(ctx, ref, variant: str, sets: dict) -> tuple[list[dict], dict]:
    """The variant's chain through evaluate, then its pairs."""
    from ptovs.metrics import read_metrics
    from ptovs.stage import Chain
    from ptovs.variants import variant_sets

    art, secs = _build(Chain(ctx, ref, variant_sets(variant, sets)), "evaluate")
    _, pairs = read_metrics(art)
    art.close()
    return pairs, secs


def _oracle_folder(ref, scene: Path, work: Path) -> Path:
    return work / "oracle" / f"{scene.name}-{ref.key()[:12]}" / "features"


def _label_chain(ref, scene: Path, work: Path, label: str) -> tuple[str, dict]:
    """The ptovs.variants name and the --set items a chain label runs."""
    variant, sets = CHAIN_LABELS[label]
    if label == "oracle":
        folder = _oracle_folder(ref, scene, work).resolve()
        sets = {"extract-features": [f"import_dir={folder}"]}
    return variant, sets


def label_key(ctx, ref, scene: Path, work: Path, label: str) -> str:
    """The artifact key of what `label` measures under today's code and config:
    a result stored under another key is stale."""
    from ptovs.config import canonical_json
    from ptovs.stage import Chain
    from ptovs.variants import variant_sets

    if label in FEATURE_LABELS:
        items = TRUTH_SEGMENTS if label == "2d-truth" else ["images=orig"]
        keys = [Chain(ctx, ref, {"extract-features": items}).key("extract-features")]
        if label == "2d-ae":
            keys.append(Chain(ctx, ref).key("train-ae"))
        if label != "2d-best":  # the query's knobs decide the mask
            query = canonical_json(Chain(ctx, ref).config("query"))
            keys.append(hashlib.sha256(query.encode()).hexdigest()[:16])
        return "+".join(keys)
    variant, sets = _label_chain(ref, scene, work, label)
    return Chain(ctx, ref, variant_sets(variant, sets)).key("evaluate")


def import_features(ctx, ref, scene: Path, work: Path) -> Path:
    """The LangSplat folder `oracle`'s chain reads (cached): every photo re-rendered
    clean (`clean_scene`), its segment features extracted exactly as the photos'
    are, written for the original and every render slot of the full method's chain
    (so uncertainty is 0 and every slot sees clean features)."""
    from ptovs.artifacts import read_json_dataset
    from ptovs.features import SegmentFeatures, langsplat_suffix, write_langsplat
    from ptovs.stage import Chain, RunContext, resolve_scene
    from ptovs.synthetic.generate import clean_scene

    folder = _oracle_folder(ref, scene, work)
    if (folder / "done").is_file():
        return folder
    clean = clean_scene(scene, folder.parent / "data" / scene.name)
    octx = RunContext(folder.parent / "work", ctx.config)
    oref = resolve_scene(octx, None, clean)
    art, _ = _build(Chain(octx, oref, {"extract-features": ["images=orig"]}),
                    "extract-features")  # fmt: skip
    levels = tuple(read_json_dataset(art.root()["levels_json"])["levels"])
    renders, _ = _build(Chain(ctx, ref), "render-appearances")
    slots = read_json_dataset(renders.root()["slots_json"])["slots"]
    renders.close()
    novel = [s for s in slots if s != "self"]
    for name in art.names():
        feats = SegmentFeatures.from_view(art[name], "orig")
        for app in ["orig", *slots]:
            write_langsplat(folder, Path(name).stem, feats, levels,
                            langsplat_suffix(app, novel))  # fmt: skip
    art.close()
    (folder / "done").write_text("ok\n")
    return folder


def best_union(labels: np.ndarray, gt: np.ndarray) -> tuple[float, np.ndarray]:
    """(IoU, mask) of the union of `labels`' segments (ids >= 0) that best matches
    `gt`: segments taken in order of their share inside gt, the best prefix (for
    IoU the optimum is such a prefix)."""
    lab = labels.ravel().astype(np.int64)
    ok = lab >= 0
    n = int(lab.max()) + 1 if ok.any() else 0
    if n == 0:
        return 0.0, np.zeros(labels.shape, bool)
    g = gt.ravel().astype(np.float64)
    area = np.bincount(lab[ok], minlength=n).astype(np.float64)
    inside = np.bincount(lab[ok], weights=g[ok], minlength=n)
    order = np.argsort(-(inside / np.maximum(area, 1)), kind="stable")
    inter = np.cumsum(inside[order])
    iou = inter / np.maximum(g.sum() + np.cumsum(area[order]) - inter, 1)
    k = int(np.argmax(iou))
    keep = np.zeros(n, bool)
    keep[order[: k + 1]] = True
    return float(iou[k]), (ok & keep[np.where(ok, lab, 0)]).reshape(labels.shape)


def phrase_table(sc):
    """The stand-in's embeddings of every query of a synthetic scene, then the
    canonical and background phrases: (emb [K, D], index by phrase, canonical
    indices, background indices)."""
    import torch

    from ptovs.encoders import scene_encoder
    from ptovs.field.relevancy import BACKGROUND_PHRASES, CANONICAL
    from ptovs.scene import load_labels

    queries = sorted({q for v in sc.labelled_views() for q in load_labels(sc, v)})
    phrases = list(dict.fromkeys([*queries, *CANONICAL, *BACKGROUND_PHRASES]))
    emb = torch.from_numpy(scene_encoder(sc.root).encode_texts(phrases))
    idx = {p: i for i, p in enumerate(phrases)}
    return emb, idx, [idx[p] for p in CANONICAL], [idx[p] for p in BACKGROUND_PHRASES]


def dense_cos(sf, emb, ae=None):
    """[L, 1, H, W, K]: each segment's cosines with every phrase (its feature row
    through `ae` when given), painted over its pixels."""
    import torch

    maps = []
    for lv in range(sf.levels):
        rows = torch.from_numpy(sf.level_table(lv).astype(np.float32))
        if ae is not None:
            with torch.no_grad():
                rows = ae.decode(ae.encode(rows))
        c = rows @ emb.float().T  # [n, K]
        local = torch.from_numpy(sf.local(lv).astype(np.int64))
        dense = torch.zeros((*local.shape, c.shape[1]))
        dense[local >= 0] = c[local[local >= 0]]
        maps.append(dense)
    return torch.stack(maps)[:, None]


def feature_pairs(ctx, ref, labels: list[str]) -> dict[str, list[dict]]:
    """The 2-D labels `labels` asks for, on the evaluation photos' own segment
    features (no field): "2d" (the pipeline's relevancy and mask), "2d-ae" (the
    features through the full method's AE), "2d-nosmooth" (2d without the
    query's mean and majority filters), "2d-truth" (2d on the truth part masks'
    features), "2d-best" (the best union of the pipeline's segments per query,
    best level: no classifier error)."""
    import dataclasses

    from ptovs.features import SegmentFeatures
    from ptovs.field.relevancy import answer
    from ptovs.metrics import pair_metrics
    from ptovs.nets.autoencoder import load_autoencoder
    from ptovs.scene import load_labels
    from ptovs.stage import Chain

    fe, _ = _build(Chain(ctx, ref, {"extract-features": ["images=orig"]}),
                   "extract-features")  # fmt: skip
    truth = None  # 2d-truth reads the truth part masks' features
    if "2d-truth" in labels:
        truth_chain = Chain(ctx, ref, {"extract-features": TRUTH_SEGMENTS})
        truth, _ = _build(truth_chain, "extract-features")
    male = Chain(ctx, ref)
    ae = None
    if "2d-ae" in labels:
        ae_art, _ = _build(male, "train-ae")
        ae = load_autoencoder(ae_art).eval()
        ae_art.close()
    settings = male.config("query").settings()
    raw = dataclasses.replace(settings, smooth_kernel=1, majority=1)
    sc = ref.load()
    emb, idx, canon, bg = phrase_table(sc)
    out: dict[str, list[dict]] = {lab: [] for lab in FEATURE_LABELS if lab in labels}

    for view in sc.labelled_views():
        sf = SegmentFeatures.from_view(fe[view.name], "orig")
        gts = load_labels(sc, view, sf.seg.shape[1:])
        qidx = [idx[q] for q in gts]
        runs = []  # (label, cosines, settings)
        if {"2d", "2d-nosmooth"} & set(out):
            cos = dense_cos(sf, emb)
            runs += [(lab, cos, st) for lab, st in
                     (("2d", settings), ("2d-nosmooth", raw)) if lab in out]  # fmt: skip
        if "2d-ae" in out:
            runs.append(("2d-ae", dense_cos(sf, emb, ae), settings))
        if truth is not None:
            other = SegmentFeatures.from_view(truth[view.name], "orig")
            runs.append(("2d-truth", dense_cos(other, emb), settings))
        for cat, gt in gts.items():
            if not gt.any():
                continue
            for label, cos, st in runs:
                r = answer(cos, idx[cat], canon, bg, st, qidx)
                m = pair_metrics(r.mask, gt)
                out[label].append({"view": view.name, "query": cat, **m})
            if "2d-best" in out:
                best = max((best_union(sf.local(lv), gt) for lv in range(sf.levels)),
                           key=lambda t: t[0])  # fmt: skip
                m = pair_metrics(best[1], gt)
                out["2d-best"].append({"view": view.name, "query": cat, **m})
    fe.close()
    if truth is not None:
        truth.close()
    return out


def run_seed(args: argparse.Namespace, seed: int) -> None:
    """Every missing label of one seed; results written after each label."""
    import logging

    import torch

    from ptovs.artifacts import write_atomic
    from ptovs.config import load_config
    from ptovs.stage import RunContext, resolve_scene

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s: %(message)s")
    torch.set_num_threads(max(1, args.threads))
    scene = _scene(args.data, args.preset, seed, args.standin)
    path = _result_path(args.work, scene.name)
    res = _load_result(path, _digest(args))
    cams = json.loads((scene / "synthetic" / "truth" / "cameras.json").read_text())
    res.update(
        seed=seed,
        preset=args.preset,
        scene=scene.name,
        digest=_digest(args),
        hard={r["name"]: bool(r["hard"]) for r in cams["images"] if r["eval"]},
        screen=json.loads((scene / "synthetic/truth/parts.json").read_text())["screen"],
    )
    res.setdefault("labels", {})
    ctx = RunContext(args.work / "runs", load_config(args.config))
    ref = resolve_scene(ctx, None, scene)
    keys = {lab: label_key(ctx, ref, scene, args.work, lab)
            for lab in {*res["labels"], *args.labels} if lab in ALL_LABELS}  # fmt: skip
    stale = [lab for lab, e in res["labels"].items()
             if lab not in keys or e.get("key") != keys[lab]]  # fmt: skip
    for lab in stale:  # measured under other code or config: not reported again
        del res["labels"][lab]
    if stale:
        write_atomic(path, json.dumps(res))
        print(f"{scene.name}: dropped stale {', '.join(stale)}", flush=True)
    todo = [lab for lab in args.labels if lab not in res["labels"]]
    for label in todo:
        if label in res["labels"]:  # computed with the other feature label
            continue
        t0 = time.perf_counter()
        if label in FEATURE_LABELS:
            feats = [lab for lab in FEATURE_LABELS if lab in todo]
            for lab, pairs in feature_pairs(ctx, ref, feats).items():
                wall = time.perf_counter() - t0
                res["labels"][lab] = _entry(pairs, {}, wall, keys[lab])
        else:
            if label == "oracle":
                import_features(ctx, ref, scene, args.work)
            variant, sets = _label_chain(ref, scene, args.work, label)
            pairs, secs = _chain_pairs(ctx, ref, variant, sets)
            wall = time.perf_counter() - t0
            res["labels"][label] = _entry(pairs, secs, wall, keys[label])
            renders = chosen_targets(ctx, ref, variant, sets, cams)
            if renders is not None:  # what the selection picked
                res["labels"][label]["renders"] = renders
        write_atomic(path, json.dumps(res))
        print(f"{scene.name} {label}: {time.perf_counter() - t0:.1f} s", flush=True)


def _entry(pairs: list[dict], secs: dict, wall: float, key: str) -> dict:
    keep = ("view", "query", "iou", "pa", "p")
    return {
        "pairs": [{k: p[k] for k in keep} for p in pairs],
        "stage_s": secs,
        "wall_s": round(wall, 2),
        "key": key,
    }


def _digest(args: argparse.Namespace) -> str:
    """What a seed's results depend on besides the code: the config file and
    the instrument's version (artifact keys cover the rest)."""
    cfg = Path(args.config).read_bytes() if args.config else b""
    return hashlib.sha256(cfg + f"v{VERSION}".encode()).hexdigest()[:16]


def _load_result(path: Path, digest: str) -> dict:
    if path.is_file():
        try:
            res = json.loads(path.read_text())
        except ValueError:
            return {}
        if res.get("digest") == digest:
            return res
    return {}


# ------------------------------------------------------------------ the runs --


def run_all(args: argparse.Namespace) -> None:
    """Seeds in `args.jobs` subprocesses. Every seed is visited: only there can
    stale labels be told (their keys need the scene); a seed with nothing to do
    returns in seconds."""
    pending = list(args.seeds)
    threads = max(1, (os.cpu_count() or 1) // args.jobs)
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), PYTHONUNBUFFERED="1")
    logs = args.work / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    running: dict[int, tuple[subprocess.Popen, float]] = {}
    t_all = time.perf_counter()
    failed = []
    while pending or running:
        while pending and len(running) < args.jobs:
            seed = pending.pop(0)
            cmd = [sys.executable, __file__, *_forward(args), "--one-seed", str(seed),
                   "--threads", str(threads)]  # fmt: skip
            log = open(logs / f"{args.preset}_s{seed}.log", "a")  # noqa: SIM115
            running[seed] = (
                subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env),
                time.perf_counter(),
            )
            log.close()
            print(f"seed {seed}: started", flush=True)
        time.sleep(1.0)
        for seed, (proc, t0) in list(running.items()):
            if proc.poll() is None:
                continue
            del running[seed]
            dt = time.perf_counter() - t0
            if proc.returncode:
                failed.append(seed)
                print(f"seed {seed}: FAILED after {dt:.0f} s; see "
                      f"{logs / f'{args.preset}_s{seed}.log'}", flush=True)  # fmt: skip
            else:
                print(f"seed {seed}: done in {dt:.0f} s", flush=True)
    print(f"all seeds: {time.perf_counter() - t_all:.0f} s", flush=True)
    if failed:
        raise SystemExit(f"seeds {failed} failed; rerun to resume them")


def _forward(args: argparse.Namespace) -> list[str]:
    out = ["--preset", args.preset, "--data", str(args.data), "--work", str(args.work)]
    out += ["--labels", *args.labels, "--standin", str(args.standin)]
    if args.config:
        out += ["--config", str(args.config)]
    return out


# ---------------------------------------------------------------------- main --


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--preset", default="small")
    ap.add_argument("--seeds", nargs="+", default=["0-17"],
                    help="seeds or ranges (0-17)")  # fmt: skip
    ap.add_argument("--dev", nargs="+", default=None,
                    help="dev seeds (default: the first half of --seeds)")  # fmt: skip
    ap.add_argument("--labels", nargs="+", default=list(LABELS), choices=ALL_LABELS)
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "accuracy.toml")
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "accuracy")
    ap.add_argument("--standin", type=int, default=1, choices=(1, 5),
                    help="the stand-in for CLIP the scenes are made for (5: with its "
                         "own --data and --work)")  # fmt: skip
    ap.add_argument("--work", type=Path, default=ROOT / "work" / "accuracy")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--threads", type=int, default=1, help=argparse.SUPPRESS)
    ap.add_argument("--one-seed", type=int, default=None, help=argparse.SUPPRESS)
    ap.add_argument("--report-only", action="store_true")
    ap.add_argument("--base", default="male", choices=ALL_LABELS,
                    help="the label every difference is paired against (male-truth "
                         "for the rows on truth segments)")  # fmt: skip
    ap.add_argument("--plot", type=Path, default=None,
                    help="write the speed-against-error plot here")  # fmt: skip
    args = ap.parse_args(argv)
    args.seeds = seed_list(args.seeds)
    args.dev = seed_list(args.dev) if args.dev else args.seeds[: len(args.seeds) // 2]
    args.work.mkdir(parents=True, exist_ok=True)
    if args.one_seed is not None:
        run_seed(args, args.one_seed)
        return
    if not args.report_only:
        run_all(args)
    print(report(args))


if __name__ == "__main__":
    main()
