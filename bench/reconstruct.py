"""Benchmark the `reconstruct` stage on the bench preset.

python bench/reconstruct.py                         # default and plain, seeds 0 1 2
python bench/reconstruct.py --parts default --seeds 0
python bench/reconstruct.py --parts variants --seeds 0 1 2 \
    --variant delta:appearance=delta-sh,color_map=false

Parts:
  default  the default config through the CLI: wall time, peak RSS, Gaussians;
           test-view PSNR with the image's own embedding (true transient pixels
           excluded), and on the right half with the embedding fitted to the left
           half (NeRF-W's protocol: `test_psnr_fit`; f_α's reading of the same half:
           `test_psnr_right`); appearance transfer (view i with image j's embedding
           against the world re-rendered with j's appearance and no occluders);
           transient mask AUROC against the true masks of the train images
  plain    the same with --set wild=false (plain 3DGS, same code and budget)
  variants one run per --variant LABEL:KEY=V[,KEY=V...] (reconstruct --set values),
           the default's figures each

Results go to <work>/bench_reconstruct.json and are printed as markdown rows.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, Results, bench_scene, run_ptovs  # noqa: E402  (same folder)


def clean_view(world, record: dict, view, **kw) -> tuple[np.ndarray, object]:
    """The generator's re-render of a truth camera without occluders, as float32
    RGB in [0, 1] at the view's size, and its appearance (`rerender`'s keywords)."""
    import cv2

    from ptovs.synthetic.generate import rerender

    target, app = rerender(world, record, occluders="none", **kw)
    image = target.image.astype(np.float32) / 255.0
    size = (view.width, view.height)
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA), app


def evaluate(art_path: Path, scene_dir: Path, n_transfer: int = 8) -> dict:
    """Test PSNR (own embedding, transients excluded), transfer PSNR, mask AUROC."""
    import cv2
    import torch

    from ptovs.artifacts import Artifact
    from ptovs.field.losses import auroc, psnr
    from ptovs.field.render import WildField
    from ptovs.raster import Camera
    from ptovs.scene import load_scene
    from ptovs.synthetic.generate import load_truth
    from ptovs.synthetic.world import Appearance

    scene = load_scene(scene_dir)
    with Artifact(art_path) as art:
        field = WildField.from_artifact(art)
        masks = {n: art[n].get("transient") for n in art.names()}
    truth_dir = scene_dir / "synthetic" / "truth"
    world, cams = load_truth(scene_dir)
    records = {r["name"]: r for r in cams["images"]}
    out: dict = {"gaussians": len(field)}
    test_psnr, right_psnr, fit_psnr = [], [], []
    for v in scene.test_views():
        cam = Camera.from_view(v)
        img = scene.load_image(v)
        emb = field.embeddings_of([v.name]) if field.wild else None
        rgb = field.render(cam, emb)[0].numpy()
        transient = np.load(truth_dir / f"{v.stem}.npz")["transient"] > 0.5
        test_psnr.append(psnr(rgb, img, ~transient))
        if field.wild:  # NeRF-W's protocol: fit l on the left half, score the right
            half = img.shape[1] // 2
            left, right = ~transient, ~transient
            left[:, half:] = right[:, :half] = False
            fit = field.fit_embedding(cam, img, left, init=emb[0])
            right_psnr.append(psnr(rgb, img, right))
            fit_psnr.append(psnr(field.render(cam, fit[None])[0].numpy(), img, right))
    out["test_psnr"] = float(np.nanmean(test_psnr))
    if fit_psnr:
        out["test_psnr_right"] = float(np.nanmean(right_psnr))
        out["test_psnr_fit"] = float(np.nanmean(fit_psnr))
    # appearance transfer: test view i under train image j's appearance
    train = scene.train_views()
    rng = np.random.default_rng(0)
    tr = []
    for k, v in enumerate(scene.test_views()[:n_transfer]):
        j = train[int(rng.integers(len(train)))]
        cam = Camera.from_view(v)
        emb = field.embeddings_of([j.name]) if field.wild else None
        rgb = field.render(cam, emb)[0].numpy()
        target, _ = clean_view(
            world,
            records[v.name],
            v,
            appearance=Appearance.from_dict(records[j.name]["appearance"]),
            seed=k,
        )
        tr.append(psnr(rgb, target))
    out["transfer_psnr"] = float(np.mean(tr))
    scores, labels = [], []
    for v in train:
        m = masks.get(v.name)
        if m is None:
            continue
        t = np.load(truth_dir / f"{v.stem}.npz")["transient"].astype(np.float32)
        scores.append(cv2.resize(m.astype(np.float32), t.shape[::-1]).ravel())
        labels.append(t.ravel() > 0.5)
    out["mask_auroc"] = (
        float(auroc(np.concatenate(scores), np.concatenate(labels))) if scores else None
    )
    out.update(
        {
            k: field.metrics.get(k)
            for k in (
                "train_seconds",
                "seconds_per_iteration",
                "psnr_train",
                "gaussians_unseen_removed",
            )
        }
    )
    del torch
    return out


def run_config(work: Path, scene: Path, sets: list[str]) -> dict:
    args = ["reconstruct", "--data", str(scene)]
    for s in sets:
        args += ["--set", s]
    wall, rss, stdout = run_ptovs(work, *args)
    art = Path(stdout.strip().splitlines()[-1].split(": ", 1)[1])
    res = evaluate(art, scene)
    res.update(wall_s=round(wall, 1), peak_rss_mb=round(rss), sets=sets)
    return res


def _variant_row(label: str, seed: int, r: dict) -> str:
    fit = (
        f"{r['test_psnr_right']:.2f} → {r['test_psnr_fit']:.2f}"
        if "test_psnr_fit" in r
        else "–"
    )
    return (
        f"| {label} | {seed} | {r['wall_s']} | {r['psnr_train']:.2f} | "
        f"{r['test_psnr']:.2f} | {fit} | {r['transfer_psnr']:.2f} | "
        f"{r['mask_auroc']:.3f} | {r['gaussians']} |"
    )


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument(
        "--parts",
        nargs="+",
        default=["default", "plain"],
        choices=["default", "plain", "variants"],
    )
    ap.add_argument(
        "--variant",
        action="append",
        default=[],
        help="variants: LABEL:KEY=V[,KEY=V...] (reconstruct --set values)",
    )
    ap.add_argument("--data", type=Path, default=ROOT / "data")
    ap.add_argument("--work", type=Path, default=ROOT / "work" / "bench")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    results = Results(args.work / "bench_reconstruct.json")
    save = results.save

    for seed in args.seeds:
        scene = bench_scene(args.data, seed)
        for part, sets in (("default", []), ("plain", ["wild=false"])):
            if part not in args.parts:
                continue
            r = run_config(args.work / part, scene, sets)
            results[f"{part}_s{seed}"] = r
            save()
            auroc = "–" if r["mask_auroc"] is None else f"{r['mask_auroc']:.3f}"
            print(
                f"| {part} | {seed} | {r['wall_s']} | {r['test_psnr']:.2f} | "
                f"{r['transfer_psnr']:.2f} | {auroc} | {r['gaussians']} | "
                f"{r['peak_rss_mb']} |",
                flush=True,
            )
        if "variants" in args.parts:
            for spec in args.variant:
                label, _, sets = spec.partition(":")
                r = run_config(
                    args.work / "variants" / label,
                    scene,
                    [x for x in sets.split(",") if x],
                )
                results[f"variant_{label}_s{seed}"] = r
                save()
                print(_variant_row(label, seed, r), flush=True)


if __name__ == "__main__":
    main()
