"""Why SfM registers only part of the synthetic bench photos (issue 24, item 5).

python bench/sfm.py --seeds 0 --variants default camera_mode=single peak_threshold=0.002

The `bench` photos of each seed (model withheld) are posed by `ptovs.sfm.run_sfm`
under each variant (SfmConfig overrides, `+` joins several: `a=1+b=2`). Reported:
registered / photos, the number of models COLMAP split them into and the largest
three, mean SIFT features a photo, verified pairs, time, and the rotation error of
the largest model against the true cameras after a Sim3 alignment of the centres.

Results go to <work>/bench_sfm.json and print as markdown rows.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import (  # noqa: E402  (same folder)
    ROOT,
    Results,
    bench_scene,
    camera_pose,
    pose_error,
    print_header,
)


def parse_variant(text: str) -> dict:
    """ "a=1+b=x" -> {"a": 1, "b": "x"} (numbers parsed); "default" -> {}."""
    if text == "default":
        return {}
    out = {}
    for item in text.split("+"):
        k, v = item.split("=", 1)
        try:
            out[k] = json.loads(v)
        except ValueError:
            out[k] = v
    return out


def run_variant(scene: Path, work: Path, overrides: dict) -> dict:
    import pycolmap

    from ptovs.sfm import SfmConfig, run_sfm

    config = dataclasses.replace(SfmConfig(), **overrides)
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    t0 = time.perf_counter()
    try:
        report = run_sfm(scene / "dense" / "images", work, config)["report"]
    except Exception as exc:  # noqa: BLE001 - a variant that fails is a row too
        return dict(error=str(exc)[:300], seconds=round(time.perf_counter() - t0, 1))
    seconds = time.perf_counter() - t0
    db = pycolmap.Database.open(str(work / "database.db"))
    try:
        n_img = db.num_images()
        feats = db.num_keypoints() / max(1, n_img)
        pairs = db.num_verified_image_pairs()
    finally:
        db.close()
    models = sorted(
        (
            pycolmap.Reconstruction(str(p)).num_reg_images()
            for p in (work / "sparse_raw").iterdir()
            if p.is_dir() and p.name != "best"
        ),
        reverse=True,
    )
    truth = {
        r["name"]: np.array(r["cam_from_world"])
        for r in json.loads(
            (scene / "synthetic" / "truth" / "cameras.json").read_text()
        )["images"]
    }
    best = pycolmap.Reconstruction(str(work / "sparse_raw" / "best"))
    est, gt = {}, {}
    for i in best.reg_image_ids():
        im = best.images[i]
        name = Path(im.name).stem + ".jpg" if im.name not in truth else im.name
        est[name] = camera_pose(im.cam_from_world().matrix())
        gt[name] = camera_pose(truth[name])
    err = pose_error(est, gt)
    return dict(
        registered=report["registered"],
        photos=report["photos"],
        models=models[:3],
        n_models=len(models),
        features=round(feats),
        verified_pairs=int(pairs),
        seconds=round(seconds, 1),
        **err,
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seeds", nargs="+", type=int, default=[0])
    p.add_argument("--variants", nargs="+", default=["default"])
    p.add_argument("--data", type=Path, default=ROOT / "data")
    p.add_argument("--work", type=Path, default=ROOT / "work" / "sfm")
    args = p.parse_args()
    res = Results(args.work / "bench_sfm.json")
    print_header(
        "seed", "variant", "registered", "models (largest)", "features",
        "verified pairs", "s", "rotation median / p90 (°), Sim3 of centres",
        "rotation median / p90 (°) / photos over 5°, rotations aligned",
    )  # fmt: skip
    for seed in args.seeds:
        scene = bench_scene(args.data, seed)
        for variant in args.variants:
            r = run_variant(
                scene, args.work / "runs" / f"s{seed}", parse_variant(variant)
            )
            res[f"s{seed}/{variant}"] = r
            res.save()
            if "error" in r:
                print(f"| {seed} | {variant} | failed: {r['error'][:80]} |", flush=True)
                continue
            print(
                f"| {seed} | {variant} | {r['registered']}/{r['photos']} | "
                f"{r['n_models']} ({', '.join(map(str, r['models']))}) | "
                f"{r['features']} | {r['verified_pairs']} | {r['seconds']} | "
                f"{r['rot_median_deg']:.2f} / {r['rot_p90_deg']:.2f} | {r['rot_aligned_median_deg']:.2f} / {r['rot_aligned_p90_deg']:.2f} / {r['rot_aligned_over5']} |",
                flush=True,
            )


if __name__ == "__main__":
    main()
