"""Where the field loses on truth segments: the 3-d code (issue 41, amendment 5).

    python bench/ae_probe.py --data data/accuracy-v5 --work work/accuracy-v5 \\
        --preset small --standin 5 --seeds 220-228          # after the truth chains
    python bench/ae_probe.py --data DIR --work DIR --preset small --standin 1 \\
        --seeds 0 --no-ae                                   # another world, PCA only

Diagnostic on dev seeds only. On the evaluation photos' truth-segment features (the
`2d-truth` label's), the mean IoU over (view, query) pairs of the `2d` rule with each
segment's 512-d feature read three ways: as extracted ("raw"), through the
autoencoder `male-truth` trained ("ae", the 3-d code every field renders), and
through the scene's top-k principal components ("pca-k", fitted on every view's
truth-segment features, the reconstruction L2-normalised). With it, the share of the
features' variance the top k components hold. Nothing is chosen from it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import accuracy as A  # noqa: E402  (same folder)
from common import probe_parser, seed_list  # noqa: E402

KS = (3, 8, 16, 32, 64)


class PCA:
    """encode/decode like the AE: the top-k components of `x` [n, d]."""

    def __init__(self, x: np.ndarray, k: int) -> None:
        import torch

        mean = x.mean(0)
        _, s, vt = np.linalg.svd(x - mean, full_matrices=False)
        self.held = float((s[:k] ** 2).sum() / max((s**2).sum(), 1e-300))
        self.mean = torch.from_numpy(mean.astype(np.float32))
        self.basis = torch.from_numpy(vt[:k].T.astype(np.float32))

    def encode(self, x):
        return (x - self.mean) @ self.basis

    def decode(self, h):
        y = h @ self.basis.T + self.mean
        return y / y.norm(dim=1, keepdim=True).clamp_min(1e-12)


def probe(args: argparse.Namespace, seed: int) -> dict:
    from ptovs.config import load_config
    from ptovs.features import SegmentFeatures
    from ptovs.field.relevancy import answer
    from ptovs.metrics import pair_metrics
    from ptovs.nets.autoencoder import load_autoencoder
    from ptovs.scene import load_labels
    from ptovs.stage import Chain, RunContext, resolve_scene
    from ptovs.variants import variant_sets

    scene = A._scene(args.data, args.preset, seed, args.standin)
    ctx = RunContext(
        args.work / "runs", load_config(A.ROOT / "configs" / "accuracy.toml")
    )
    ref = resolve_scene(ctx, None, scene)
    settings = Chain(ctx, ref).config("query").settings()
    fe, _ = A._build(
        Chain(ctx, ref, {"extract-features": A.TRUTH_SEGMENTS}), "extract-features"
    )
    readers: dict = {}
    if not args.no_ae:
        truth = variant_sets(*A.CHAIN_LABELS["male-truth"])
        art, _ = A._build(Chain(ctx, ref, truth), "train-ae")
        readers["ae"] = load_autoencoder(art).eval()
        art.close()
    sc = ref.load()
    views = [
        SegmentFeatures.from_view(fe[v.name], "orig") for v in sc.views if v.name in fe
    ]
    rows = [sf.level_table(lv) for sf in views for lv in range(sf.levels)]
    x = np.concatenate(rows).astype(np.float64)
    pcas = {k: PCA(x, k) for k in KS if k < min(x.shape)}
    readers.update({f"pca-{k}": p for k, p in pcas.items()})
    emb, idx, canon, bg = A.phrase_table(sc)
    ious: dict[str, list[float]] = {"raw": [], **{k: [] for k in readers}}
    for view in sc.labelled_views():
        sf = SegmentFeatures.from_view(fe[view.name], "orig")
        gts = load_labels(sc, view, sf.seg.shape[1:])
        qidx = [idx[q] for q in gts]
        runs = [("raw", A.dense_cos(sf, emb))]
        runs += [(k, A.dense_cos(sf, emb, r)) for k, r in readers.items()]
        for key, cos in runs:
            for cat, gt in gts.items():
                if gt.any():
                    r = answer(cos, idx[cat], canon, bg, settings, qidx)
                    ious[key].append(pair_metrics(r.mask, gt)["iou"])
    fe.close()
    return {
        "segments": len(x),
        "variance held": {k: round(p.held, 3) for k, p in pcas.items()},
        "mIoU": {k: round(float(np.mean(v)), 3) for k, v in ious.items()},
    }


def main(argv: list[str] | None = None) -> None:
    ap = probe_parser(__doc__, "small")
    ap.add_argument("--no-ae", action="store_true",
                    help="PCA only (no chain to train the AE on)")  # fmt: skip
    args = ap.parse_args(argv)
    for seed in seed_list(args.seeds):
        print(seed, probe(args, seed), flush=True)


if __name__ == "__main__":
    main()
