"""Segments against the truth, and the 2-D ceiling they allow (issue 40).

    python bench/segments.py --seeds 0-8                    # dev: choose
    python bench/segments.py --seeds 9-17                   # test: report
    python bench/segments.py --seeds 0-8 --candidates graph hier --filters paper image
    python bench/segments.py --seeds 0-8 --candidates sweep  # every candidate measured

For every evaluation photo of each `small` seed (the accuracy instrument's scenes,
`data/accuracy`), each candidate segmenter's levels are measured against the truth
parts (segment covering and boundary F, per level; seconds per photo, scaled to
512×384 by area), and the same features and query as the pipeline's (the stand-in
encoder on each segment's crop, `ptovs.field.relevancy.answer`) give per (view,
query) pair:

    2d        the pipeline's relevancy and mask on that segmenter's segments
    2d-best   the best union of that segmenter's segments per query (the union of
              segments in order of their share inside the truth mask that
              maximises IoU, best level): no classifier error
under each query filter setting (`--filters`): `paper` (box 20, majority 7 px),
`image` (the same at a 340-px short side, scaled with the image's; `image680`,
`image1360`: half and a quarter of that), `none`.
Segmenter `truth` is the generator's part masks (`ptovs.segment.truth`).

Per seed the rows go to <work>/segments/<scene>.json; the report is mIoU as the mean
of (seed, query) cluster means with 95 % cluster-bootstrap intervals, and the
covering / boundary F / time means.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, seed_list  # noqa: E402  (same folder)

FILTERS = {  # name -> (smooth_kernel, majority, filter_ref)
    "paper": (20, 7, 0.0),
    "image": (20, 7, 340.0),
    "image680": (20, 7, 680.0),
    "image1360": (20, 7, 1360.0),
    "none": (1, 1, 0.0),
}


def candidate(name: str, scene: Path):
    """A segmenter by name: ptovs's own, `truth`, or a bench-only candidate."""
    from ptovs.segment import get_segmenter
    from ptovs.segment.truth import TruthSegmenter

    if name == "truth":
        return TruthSegmenter(scene)
    if name in EXTRA:
        return EXTRA[name]()
    return get_segmenter(name)


def _hier(texture: float, edge: float, cuts: tuple, min_size: int = 100):
    from ptovs.segment.hier import HierSegmenter

    th = dict(zip(("s", "m", "l"), map(float, cuts), strict=True))
    return lambda: HierSegmenter(
        texture=texture, edge=edge, thresholds=th, min_size=min_size
    )


def _sweep() -> dict:
    """The candidates issue 40 measured on the dev seeds (`--candidates sweep`):
    hier over texture window, edge weight, cuts and speck size; graph with finer
    k; `tex`: Felzenszwalb on the texture features alone."""
    from ptovs.segment.graph import GraphSegmenter
    from ptovs.segment.hier import texture_features

    out = {}
    for tex in (1.0, 2.5):
        for edge in (0.0, 1.0):
            for cuts in ((4, 10, 25), (8, 20, 45), (12, 30, 70)):
                out[f"h_t{tex}_e{edge}_{cuts[0]}-{cuts[1]}-{cuts[2]}"] = _hier(
                    tex, edge, cuts
                )
    out["h_t0.5_e0.0_12-30-70"] = _hier(0.5, 0.0, (12, 30, 70))
    out["h_t1.0_e0.0_16-40-90"] = _hier(1.0, 0.0, (16, 40, 90))
    for ms in (200, 300, 600):
        out[f"h_t1.0_e0.0_12-30-70_ms{ms}"] = _hier(1.0, 0.0, (12, 30, 70), ms)
    out["h_t1.0_e0.0_8-20-45_ms300"] = _hier(1.0, 0.0, (8, 20, 45), 300)
    out["h_t1.0_e0.0_12-30-50_ms300"] = _hier(1.0, 0.0, (12, 30, 50), 300)
    out["graph_fine"] = lambda: GraphSegmenter(k={"s": 100.0, "m": 300.0, "l": 1000.0})

    class Tex:  # Felzenszwalb on the texture features, no hierarchy
        name, levels = "tex", ("s", "m", "l")

        def segment(self, image):
            import cv2

            from ptovs.segment import Level

            h, w = image.shape[:2]
            f = (h * w / (512 * 384)) ** 0.5
            feat = texture_features(image, 2.0 * max(f, 0.35))
            ms = max(4, round(100 * h * w / (512 * 384)))
            out = []
            for k in (100.0, 300.0, 1000.0):
                gs = cv2.ximgproc.segmentation.createGraphSegmentation(
                    sigma=0.0, k=k, min_size=ms
                )
                lab = gs.processImage(feat).astype(np.int32)
                out.append(
                    Level(
                        np.unique(lab, return_inverse=True)[1]
                        .reshape(h, w)
                        .astype(np.int32)
                    )
                )
            return out

    out["tex2"] = Tex
    return out


EXTRA: dict = {}  # bench-only candidates: name -> constructor (filled by _sweep)


def seed_rows(scene: Path, config: Path, candidates: list[str], filters: list[str]):
    import dataclasses

    from accuracy import best_union, dense_cos, phrase_table

    from ptovs.config import load_config
    from ptovs.encoders import get_encoder
    from ptovs.field.relevancy import answer
    from ptovs.metrics import pair_metrics
    from ptovs.scene import load_labels
    from ptovs.segment.quality import boundary_f, covering
    from ptovs.segment.truth import truth_ids
    from ptovs.stage import Chain, RunContext, resolve_scene
    from ptovs.stages.extract_features import encode_levels

    ctx = RunContext(ROOT / "work" / "segments-tmp", load_config(config))
    ref = resolve_scene(ctx, None, scene)
    base = Chain(ctx, ref).config("query").settings()
    sc = ref.load()
    encoder = get_encoder("synthetic")
    emb, idx, canon, bg = phrase_table(sc)
    sets = {
        f: dataclasses.replace(base, smooth_kernel=FILTERS[f][0],
                               majority=FILTERS[f][1], filter_ref=FILTERS[f][2])
        for f in filters
    }  # fmt: skip
    truth_dir = scene / "synthetic" / "truth"
    rows = []
    for name in candidates:
        seg = candidate(name, scene)
        for view in sc.labelled_views():
            img = (sc.load_image(view) * 255.0 + 0.5).astype(np.uint8)
            with np.load(truth_dir / f"{view.stem}.npz") as z:
                pid = truth_ids(z["part_id"], z["depth"]).astype(np.int64)
                pid[
                    z["transient"]
                ] = -3  # occluders: a region (not a part) of their own
            if hasattr(seg, "select"):
                seg.select(view.stem, True)
            t0 = time.perf_counter()
            levels = seg.segment(img)
            secs = time.perf_counter() - t0
            h, w = img.shape[:2]
            rows.append({"segmenter": name, "view": view.name, "kind": "segments",
                         "seconds": secs, "seconds_512": secs * 512 * 384 / (h * w),
                         "covering": [covering(lv.labels, pid) for lv in levels],
                         "boundary_f": [boundary_f(lv.labels, pid)[0] for lv in levels],
                         "segments": [lv.n for lv in levels]})  # fmt: skip
            cos = dense_cos(encode_levels(img, levels, encoder), emb)
            gts = load_labels(sc, view, (h, w))
            qidx = [idx[c] for c in gts]
            for cat, gt in gts.items():
                if not gt.any():
                    continue
                best = max(best_union(lv.labels, gt)[0] for lv in levels)
                for fname, st in sets.items():
                    r = answer(cos, idx[cat], canon, bg, st, qidx)
                    m = pair_metrics(r.mask, gt)
                    rows.append({"segmenter": name, "view": view.name, "query": cat,
                                 "kind": "2d", "filter": fname, **m})  # fmt: skip
                rows.append({"segmenter": name, "view": view.name, "query": cat,
                             "kind": "2d-best", "iou": best})  # fmt: skip
    return rows


def report(results: dict[str, list[dict]], candidates, filters) -> str:
    from ptovs.stats import bootstrap_mean

    out = []
    out.append("| segmenter | covering s / m / l | boundary F s / m / l | segments "
               "s / m / l | s per photo (512×384) | "
               + " | ".join(f"2d {f}" for f in filters) + " | 2d-best |")  # fmt: skip
    out.append("|---" * (5 + len(filters)) + "|")
    for name in candidates:
        seg = [r for rows in results.values() for r in rows
               if r["segmenter"] == name and r["kind"] == "segments"]  # fmt: skip
        if not seg:
            continue
        cov = np.nanmean([r["covering"] for r in seg], 0)
        bf = np.nanmean([r["boundary_f"] for r in seg], 0)
        ns = np.mean([r["segments"] for r in seg], 0)
        t = np.median([r["seconds_512"] for r in seg])
        cells = []
        for kind, fname in [*(("2d", f) for f in filters), ("2d-best", None)]:
            clusters = {}
            for seed, rows in results.items():
                for r in rows:
                    if r["segmenter"] != name or r["kind"] != kind:
                        continue
                    if fname is not None and r.get("filter") != fname:
                        continue
                    clusters.setdefault((seed, r["query"]), []).append(r["iou"])
            means = np.array([np.mean(v) for v in clusters.values()])
            if len(means):
                e = bootstrap_mean(means)
                cells.append(f"{e.mean:.3f} [{e.lo:.3f}, {e.hi:.3f}]")
            else:
                cells.append("–")
        out.append(
            f"| {name} | {' / '.join(f'{c:.3f}' for c in cov)} | "
            f"{' / '.join(f'{c:.3f}' for c in bf)} | "
            f"{' / '.join(f'{c:.0f}' for c in ns)} | {t:.3f} | "
            + " | ".join(cells)
            + " |"
        )
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--seeds", default="0-8")
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "accuracy")
    ap.add_argument("--work", type=Path, default=ROOT / "work" / "accuracy")
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "accuracy.toml")
    ap.add_argument("--candidates", nargs="+", default=["graph", "truth"])
    ap.add_argument("--filters", nargs="+", default=list(FILTERS))
    ap.add_argument("--report-only", action="store_true")
    args = ap.parse_args()
    if "sweep" in args.candidates:
        EXTRA.update(_sweep())
        i = args.candidates.index("sweep")
        args.candidates[i : i + 1] = ["graph", "hier", "truth", *EXTRA]
    from ptovs.artifacts import write_atomic
    from ptovs.synthetic import generate_scene

    results = {}
    for seed in seed_list([args.seeds]):
        scene = args.data / f"small_s{seed}"
        path = args.work / "segments" / f"{scene.name}.json"
        done = json.loads(path.read_text()) if path.is_file() else {}
        missing = (
            [c for c in args.candidates if c not in done]
            if not args.report_only
            else []
        )
        if missing:
            if not (scene / "synthetic" / "truth" / "cameras.json").is_file():
                generate_scene(args.data, "small", seed, progress=False)
            rows = seed_rows(scene, args.config, missing, args.filters)
            for c in missing:
                done[c] = [r for r in rows if r["segmenter"] == c]
            write_atomic(path, json.dumps(done))
        results[seed] = [r for c in args.candidates for r in done.get(c, [])]
        print(f"seed {seed}: done", flush=True)
    print(report(results, args.candidates, args.filters))


if __name__ == "__main__":
    main()
