"""Benchmark the `reconstruct` stage on the bench preset (issue 8 targets).

python bench/reconstruct.py                         # everything, seeds 0 1 2
python bench/reconstruct.py --parts default plain --seeds 0
python bench/reconstruct.py --parts budgets sfm presets --seeds 0

Parts:
  default  the default config through the CLI: wall time, peak RSS, Gaussians;
           test-view PSNR with the image's own embedding (true transient pixels
           excluded), and on the right half with the embedding fitted to the left
           half (NeRF-W's protocol; `test_psnr_fit`, f_α's `test_psnr_right`); appearance transfer (view i with image j's embedding against
           the world re-rendered with j's appearance and no occluders); transient
           mask AUROC against the true masks of the train images
  plain    the same with --set wild=false (plain 3DGS, same code and budget)
  budgets  three iteration budgets (time, PSNR, transfer PSNR)
  sfm      the bench photos with the model withheld: registered, time, rotation and
           centre error after a Sim3 alignment; then PSNR trained on the SfM poses
  presets  s/iteration, Gaussians and peak RSS of the `cpu` and `authors` presets,
           and PSNR of both at equal (short) budgets
  variants one run per --variant LABEL:KEY=V[,KEY=V...] (e.g.
           --variant affine:appearance=affine), the default's figures each
  rescore  the same figures for fields trained earlier (--artifact SEED:PATH)
  photos   per photo, a stored field (--artifact) against the photo re-rendered
           without occluders, before and after the photo's best global colour map
  errors   the error budget (issue 24): today's field; the photos re-rendered
           without occluders; under one neutral appearance without occluders
           (the static ceiling); a larger Gaussian cap (--max-gaussians)

Results go to <work>/bench_reconstruct.json and are printed as markdown rows.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from collections.abc import Iterator
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


def sfm_part(work: Path, scene: Path) -> dict:
    import pycolmap

    from ptovs.scene import load_scene

    photos = work / "sfm_photos" / scene.name / "images"
    if photos.parent.exists():
        shutil.rmtree(photos.parent)
    shutil.copytree(scene / "dense" / "images", photos)
    t0 = time.perf_counter()
    wall, rss, _ = run_ptovs(work, "status", "--data", str(photos.parent))
    sfm_scene = next((work / scene.name).glob("sfm/*/sparse")).parent
    posed = load_scene(sfm_scene)
    truth = {
        r["name"]: r
        for r in json.loads(
            (scene / "synthetic" / "truth" / "cameras.json").read_text()
        )["images"]
    }
    names = [v.name for v in posed.views]
    est = np.array(
        [-(v.cam_from_world[:3, :3].T @ v.cam_from_world[:3, 3]) for v in posed.views]
    )
    gT = [np.array(truth[n]["cam_from_world"]) for n in names]
    gt = np.array([-(t[:3, :3].T @ t[:3, 3]) for t in gT])
    sim = pycolmap.estimate_sim3d(est, gt)
    aligned = np.array([sim * p for p in est])
    radius = float(np.linalg.norm(gt - gt.mean(0), axis=1).mean())
    rot = []
    for v, t in zip(posed.views, gT, strict=True):
        r = v.cam_from_world[:3, :3] @ sim.rotation.matrix().T
        rot.append(
            np.degrees(np.arccos(np.clip((np.trace(r @ t[:3, :3].T) - 1) / 2, -1, 1)))
        )
    cerr = np.linalg.norm(aligned - gt, axis=1)
    res = dict(
        photos=len(truth),
        registered=len(names),
        sfm_wall_s=round(wall, 1),
        sfm_peak_rss_mb=round(rss),
        rot_median_deg=float(np.median(rot)),
        rot_p90_deg=float(np.percentile(rot, 90)),
        centre_median=float(np.median(cerr)),
        centre_p90=float(np.percentile(cerr, 90)),
        radius=radius,
    )
    # train on the SfM poses; PSNR on its own held-out split (no truth alignment)
    wall, rss, stdout = run_ptovs(work, "reconstruct", "--data", str(photos.parent))
    art = Path(stdout.strip().splitlines()[-1].split(": ", 1)[1])
    from ptovs.artifacts import Artifact, read_json_dataset

    with Artifact(art) as a:
        m = read_json_dataset(a.root()["metrics_json"])
    res.update(
        train_wall_s=round(wall, 1),
        psnr_train=m.get("psnr_train"),
        psnr_test=m.get("psnr_test"),
        total_s=round(time.perf_counter() - t0, 1),
    )
    return res


def photo_errors(art_path: Path, scene_dir: Path, n_train: int = 40) -> dict:
    """Where the appearance error lies, photo by photo (issue 24, fifth stop).

    Each test photo and the first `n_train` train photos are rendered with their
    own embedding and compared with the generator's re-render of the same camera
    and appearance without occluders; then again after the best global colour map
    of that photo (3×3 matrix + offset, least squares over its pixels). What the
    map recovers is exposure, tint and filter; what it leaves is spatial (shading
    that moves with each photo's sun). Grouped by split and by the generator's
    `hard` flag (night, black-and-white, sepia, strong tint or exposure).
    """
    from ptovs.artifacts import Artifact
    from ptovs.field.losses import psnr
    from ptovs.field.render import WildField
    from ptovs.raster import Camera
    from ptovs.scene import load_scene
    from ptovs.synthetic.generate import load_truth

    scene = load_scene(scene_dir)
    with Artifact(art_path) as art:
        field = WildField.from_artifact(art)
    world, cams = load_truth(scene_dir)
    records = {r["name"]: r for r in cams["images"]}
    groups: dict[str, list[tuple[float, float]]] = {}
    splits = [("test", v) for v in scene.test_views()]
    splits += [("train", v) for v in scene.train_views()[:n_train]]
    for split, v in splits:
        rgb = field.render(Camera.from_view(v), field.embeddings_of([v.name]))[0]
        rgb = rgb.numpy().astype(np.float64)
        t, app = clean_view(world, records[v.name], v)
        t = t.astype(np.float64)
        x = np.concatenate((rgb.reshape(-1, 3), np.ones((rgb[..., 0].size, 1))), 1)
        coef, *_ = np.linalg.lstsq(x, t.reshape(-1, 3), rcond=None)
        mapped = np.clip(x @ coef, 0, 1).reshape(t.shape)
        key = f"{split}_{'hard' if app.hard else 'normal'}"
        groups.setdefault(key, []).append((psnr(rgb, t), psnr(mapped, t)))
    return {
        k: {
            "photos": len(v),
            "psnr": float(np.mean([a for a, _ in v])),
            "psnr_colour_map": float(np.mean([b for _, b in v])),
        }
        for k, v in sorted(groups.items())
    }


def error_budget(
    work: Path, scene: Path, max_gaussians: int
) -> Iterator[tuple[str, dict]]:
    """Issue 24's error budget at today's budget: the field as it is; the same
    cameras with every photo re-rendered without occluders (own appearance), and
    under one neutral appearance without occluders (the static ceiling of this
    capacity and schedule); and a larger Gaussian cap. Every row is scored against
    the same truth (test views: own embedding, true transient pixels excluded;
    transfer: the world re-rendered under another photo's appearance). Yields
    each row as it is measured."""
    from ptovs.synthetic.generate import clean_scene

    yield "today", run_config(work / "today", scene, [])
    for label, appearance in (("no-occluders", "own"), ("static", "neutral")):
        folder = work / "data" / label / scene.name
        if not (folder / "dense" / "images").is_dir():
            clean_scene(scene, folder, appearance=appearance)
        r = run_config(work / label, folder, [])
        r["mask_auroc"] = None  # no occluders left to find
        if appearance == "neutral":  # every photo looks alike: nothing to transfer
            r["transfer_psnr"] = None
        yield label, r
    sets = [f"max_gaussians={max_gaussians}"]
    yield f"cap {max_gaussians}", run_config(work / "cap", scene, sets)


def presets_part(work: Path, scene: Path, iterations: int) -> list[dict]:
    rows = []
    for preset in ("cpu", "authors"):
        sets = [
            f"preset={preset}",
            f"iterations={iterations}",
            f"densify_until={iterations}",
            f"checkpoint_every={iterations}",
        ]
        res = run_config(work / f"presets_{preset}", scene, sets)
        res["preset"] = preset
        rows.append(res)
    return rows


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
        "--parts", nargs="+", default=["default", "plain", "budgets", "sfm", "presets"]
    )
    ap.add_argument("--budgets", nargs="+", type=int, default=[1000, 2000, 4000])
    ap.add_argument("--preset-iterations", type=int, default=200)
    ap.add_argument("--max-gaussians", type=int, default=50000, help="errors: the cap")
    ap.add_argument(
        "--variant",
        action="append",
        default=[],
        help="variants: LABEL:KEY=V[,KEY=V...] (reconstruct --set values)",
    )
    ap.add_argument(
        "--artifact",
        action="append",
        default=[],
        metavar="SEED:PATH",
        help="rescore: a reconstruct artifact of bench seed SEED to score again",
    )
    ap.add_argument("--data", type=Path, default=ROOT / "data")
    ap.add_argument("--work", type=Path, default=ROOT / "work" / "bench")
    args = ap.parse_args()
    by_seed: dict[int, list[Path]] = {}
    for spec in args.artifact:
        seed, _, path = spec.partition(":")
        by_seed.setdefault(int(seed), []).append(Path(path))
    args.artifact = by_seed
    args.work.mkdir(parents=True, exist_ok=True)
    results = Results(args.work / "bench_reconstruct.json")
    save = results.save

    for seed in args.seeds:
        scene = bench_scene(args.data, seed)
        if "default" in args.parts:
            r = run_config(args.work / "default", scene, [])
            results[f"default_s{seed}"] = r
            save()
            print(
                f"| default | {seed} | {r['wall_s']} | {r['test_psnr']:.2f} | "
                f"{r['transfer_psnr']:.2f} | {r['mask_auroc']:.3f} | {r['gaussians']} | "
                f"{r['peak_rss_mb']} |",
                flush=True,
            )
        if "plain" in args.parts:
            r = run_config(args.work / "plain", scene, ["wild=false"])
            results[f"plain_s{seed}"] = r
            save()
            print(
                f"| plain | {seed} | {r['wall_s']} | {r['test_psnr']:.2f} | "
                f"{r['transfer_psnr']:.2f} | – | {r['gaussians']} | {r['peak_rss_mb']} |",
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
        if "rescore" in args.parts:  # score fields trained earlier (no training)
            for path in args.artifact.get(seed, []):
                r = evaluate(path, scene)
                results[f"rescore_{path.parent.parent.parent.name}_s{seed}"] = r
                save()
                print(_variant_row(str(path), seed, {"wall_s": "–", **r}), flush=True)
        if "photos" in args.parts:  # the appearance error, photo by photo
            for path in args.artifact.get(seed, []):
                for group, r in photo_errors(path, scene).items():
                    results[f"photos_{path.stem}_{group}_s{seed}"] = r
                    save()
                    print(
                        f"| {path.stem} | {seed} | {group} | {r['photos']} | "
                        f"{r['psnr']:.2f} | {r['psnr_colour_map']:.2f} |",
                        flush=True,
                    )
        if "errors" in args.parts:
            for label, r in error_budget(
                args.work / "errors", scene, args.max_gaussians
            ):
                results[f"errors_{label}_s{seed}"] = r
                save()
                auroc, transfer = (
                    "–" if r[k] is None else f"{r[k]:.3f}"
                    for k in ("mask_auroc", "transfer_psnr")
                )
                print(
                    f"| {label} | {seed} | {r['wall_s']} | {r['test_psnr']:.2f} | "
                    f"{transfer} | {auroc} | {r['gaussians']} |",
                    flush=True,
                )
    seed0 = bench_scene(args.data, args.seeds[0])
    if "budgets" in args.parts:
        for it in args.budgets:
            r = run_config(args.work / "budgets", seed0, [f"iterations={it}"])
            results[f"budget_{it}"] = r
            save()
            print(
                f"| {it} | {r['wall_s']} | {r['test_psnr']:.2f} | {r['transfer_psnr']:.2f} | "
                f"{r['mask_auroc']:.3f} | {r['gaussians']} |",
                flush=True,
            )
    if "sfm" in args.parts:
        r = sfm_part(args.work / "sfm", seed0)
        results["sfm"] = r
        save()
        print(json.dumps(r), flush=True)
    if "presets" in args.parts:
        for r in presets_part(args.work, seed0, args.preset_iterations):
            results[f"preset_{r['preset']}"] = r
            save()
            print(
                f"| {r['preset']} | {args.preset_iterations} | {r['seconds_per_iteration']} | "
                f"{r['gaussians']} | {r['peak_rss_mb']} | {r['test_psnr']:.2f} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
