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
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, seed_list  # noqa: E402  (same folder)

VERSION = 1  # bump when what a seed's results mean changes

TRUTH_EACH = ["segmenter=truth", "segment=each"]  # each image's own truth parts
# label -> (ptovs.variants name, extra --set items per stage); the order is the
# order a seed computes them in (the full method's chain first: most reuse it)
CHAIN_LABELS: dict[str, tuple[str, dict[str, list[str]]]] = {
    "male": ("male", {}),
    "paper": ("paper", {}),
    "optimise": ("optimise", {}),
    **{
        f"slot-{a}": ("male", {"query": [f'appearances=["{a}"]']})
        for a in ("orig", "nov1", "nov2", "nov3")
    },
    **{
        v: (v, {})
        for v in (
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
            "langsplat-wild",
            "langsplat",
        )
    },
    "oracle": ("male", {}),  # + the clean features' import_dir (`import_features`)
    # Table 3 rows with perfect segments: the synthetic truth's part masks of each
    # image (`segmenter = "truth"`, `segment = "each"`: the paper's own SAM setting
    # as an upper bound)
    **{
        f"{v}-truth": (v, {"extract-features": TRUTH_EACH})
        for v in ("male", "langsplat", "no-multi-appearance")
    },
}
# Table 4 on truth segments: `male-truth` with one change of render-appearances
# (the same appearance in every novel slot; random targets), so that the paired
# difference is the selection's alone
CHAIN_LABELS.update({
    f"{k}-truth": ("male", {"render-appearances": [item],
                            "extract-features": TRUTH_EACH})
    for k, item in (("same-appearance", "targets=same"),
                    ("select-random", "selection=random"))
})  # fmt: skip
# extract-features' segments and economies, each against `male` (one segmentation
# per view, from the photo): every image segmented (the paper's), one segmentation
# from the self render, and no crops under 16 or 32 px
CHAIN_LABELS.update({
    "male-segment-each": ("male", {"extract-features": ["segment=each"]}),
    "male-segment-once-self": ("male", {"extract-features": ["segment_from=self"]}),
    **{f"male-min-crop-{px}": ("male", {"extract-features": [f"min_crop_px={px}"]})
       for px in (16, 32)},
})  # fmt: skip


# the recipes of the speed-against-error front (bench/speed_error.py): the
# scene-fitted recipe (configs/auto.toml's values over this instrument's config),
# the full method on plain-3DGS geometry, and two Gaussian budgets
def _auto_sets() -> dict[str, list[str]]:
    import tomllib

    with open(ROOT / "configs" / "auto.toml", "rb") as f:
        auto = tomllib.load(f)
    return {stage: [f"{k}={json.dumps(v)}" for k, v in items.items()]
            for stage, items in auto.items() if stage != "scene"}  # fmt: skip


CHAIN_LABELS.update({
    "auto": ("male", _auto_sets()),
    "plain": ("male", {"reconstruct": ["wild=false"]}),
    **{f"gauss-{k}k": ("male", {"reconstruct": [f"max_gaussians={k * 1000}"]})
       for k in (3, 5)},
})  # fmt: skip
# the steadier query rules, each against `male` (query only: the chain's artifacts
# are shared): a soft level choice, a robust peak, the cut where the area is steadiest
STEADY_QUERY = {
    "level-soft": ["level_softness=0.02"],
    "level-soft-05": ["level_softness=0.05"],
    "level-soft-10": ["level_softness=0.1"],
    "peak-q": ["peak_quantile=0.995"],
    "thr-stable": ["threshold_mode=stable"],
}
CHAIN_LABELS.update({k: ("male", {"query": v}) for k, v in STEADY_QUERY.items()})
# the novel targets drawn in a name-hashed order (render-appearances.order)
CHAIN_LABELS["order-names"] = ("male", {"render-appearances": ["order=names"]})
CHAIN_LABELS["names-stable"] = (
    "male",
    {"render-appearances": ["order=names"], "query": ["threshold_mode=stable"]},
)
CHAIN_LABELS["no-multi-appearance-stable"] = (
    "no-multi-appearance", {"query": ["threshold_mode=stable"]})  # fmt: skip
# measured only when asked for (--labels), kept out of the default run so that
# `make bench-accuracy` stays within its time: Table 3 row 3, the code-space lift,
# and Table 3 and 4 rows under truth segments (`make bench-multiapp`)
OPTIONAL_LABELS = (
    "no-uncertainty-ae", "lift-codes", "male-truth", "langsplat-truth",
    "no-multi-appearance-truth", "same-appearance-truth", "select-random-truth",
    "male-segment-each", "male-segment-once-self", "male-min-crop-16",
    "male-min-crop-32", "auto", "plain", "gauss-3k", "gauss-5k", *STEADY_QUERY,
    "order-names", "names-stable", "no-multi-appearance-stable",
)  # fmt: skip
CHAIN_LABELS.update({v: (v, {}) for v in ("no-uncertainty-ae", "lift-codes")})
FEATURE_LABELS = ("2d", "2d-ae", "2d-nosmooth", "2d-best", "2d-truth")
TRUTH_SEGMENTS = ["images=orig", "segmenter=truth"]  # extract-features, for 2d-truth
ALL_LABELS = ("male", *FEATURE_LABELS, *(k for k in CHAIN_LABELS if k != "male"))
LABELS = tuple(k for k in ALL_LABELS if k not in OPTIONAL_LABELS)  # the default run
CHAIN_LOSS = (  # the chain from the photo's features to the fused field
    "2d-truth", "2d-best", "2d-nosmooth", "2d", "2d-ae",
    "slot-orig", "slot-nov1", "slot-nov2", "slot-nov3",
    "male", "imglvlmax", "pixmax", "pixavg", "pixweighted",
)  # fmt: skip
CEILINGS = ("oracle", "2d")
ANSWERED = 0.1  # a cluster some method answers has a mean IoU of at least this


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


def _result_path(work: Path, scene: str) -> Path:
    return work / "results" / f"{scene}.json"


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


# ---------------------------------------------------------------- the report --


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
