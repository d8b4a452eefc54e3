"""Where the 2-D ceiling is lost: the query on one level's segments alone (issue 41).

    python bench/level_probe.py --data data/accuracy-v3 --work work/accuracy-v3 \\
        --preset small-3x --standin 3 --seeds 140 141

Diagnostic on dev seeds only, after `bench/accuracy.py` has built their
extract-features: for the pipeline's segments and the truth masks, the mean IoU
over (view, query) pairs of the `2d` rule with the query's own level choice
("auto") and with each level fixed. Nothing is chosen from it.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy as A  # noqa: E402  (same folder)
from common import probe_parser, seed_list  # noqa: E402


def probe(data: Path, work: Path, preset: str, standin: int, seed: int) -> dict:
    """{segments: {"auto" | "level-k": mean IoU}} for one seed."""
    from ptovs.config import load_config
    from ptovs.features import SegmentFeatures
    from ptovs.field.relevancy import answer
    from ptovs.metrics import pair_metrics
    from ptovs.scene import load_labels
    from ptovs.stage import Chain, RunContext, resolve_scene

    scene = A._scene(data, preset, seed, standin)
    ctx = RunContext(work / "runs", load_config(A.ROOT / "configs" / "accuracy.toml"))
    ref = resolve_scene(ctx, None, scene)
    settings = Chain(ctx, ref).config("query").settings()
    sc = ref.load()
    emb, idx, canon, bg = A.phrase_table(sc)
    out = {}
    for name, items in (("pipeline", ["images=orig"]), ("truth", A.TRUTH_SEGMENTS)):
        fe, _ = A._build(
            Chain(ctx, ref, {"extract-features": items}), "extract-features"
        )
        ious: dict[str, list[float]] = {}
        for view in sc.labelled_views():
            sf = SegmentFeatures.from_view(fe[view.name], "orig")
            gts = load_labels(sc, view, sf.seg.shape[1:])
            qidx = [idx[q] for q in gts]
            cos = A.dense_cos(sf, emb)
            for cat, gt in gts.items():
                if not gt.any():
                    continue
                runs = [("auto", cos)] + [
                    (f"level-{k}", cos[k : k + 1]) for k in range(cos.shape[0])
                ]
                for key, c in runs:
                    r = answer(c, idx[cat], canon, bg, settings, qidx)
                    ious.setdefault(key, []).append(pair_metrics(r.mask, gt)["iou"])
        fe.close()
        out[name] = {k: round(float(np.mean(v)), 3) for k, v in ious.items()}
    return out


def main(argv: list[str] | None = None) -> None:
    ap = probe_parser(__doc__, "small-3x")
    args = ap.parse_args(argv)
    for seed in seed_list(args.seeds):
        res = probe(args.data, args.work, args.preset, args.standin, seed)
        for name, row in res.items():
            print(seed, name, row, flush=True)


if __name__ == "__main__":
    main()
