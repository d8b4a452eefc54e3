"""Calibration of the stand-in encoder on `bench` scenes (docs/standin.md).

Closed set: each part crop (LangSplat recipe, truth part mask) is assigned the
part whose query phrase has the highest text similarity. Open set: the
share of crops on which the part's own phrase wins the pipeline's relevancy rule
against every negative phrase (the canonical and background phrases), and the
share that wins by the generator screen's margin (`ptovs.synthetic.screen`). Four
sets of crops per scene, from re-renders of the scene's train cameras:

  clean     neutral appearance, no occluders
  hard      a hard appearance (night, b/w, sepia, strong tint or exposure)
  occluded  neutral appearance with new billboards; parts whose mask is at
            least 30% covered by transients (the crop shows the occluder)
  as-shot   the scene's own JPEGs (their random appearance and transients)

Usage:
    python bench/encoder_calibration.py --seeds 0 1 2 --out work/synthetic
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

from ptovs.encoders import prepare_crop, scene_encoder
from ptovs.synthetic import generate_scene
from ptovs.synthetic.generate import load_truth, rerender
from ptovs.synthetic.screen import MARGIN, NEGATIVES

MIN_FRAC = 0.004  # a part needs 0.4% of the image (and 64 px) to be cropped
OCCLUDED = 0.3  # transient share of a part's mask for the occluded set


def _part_crops(
    image: np.ndarray,  # [H, W, 3] uint8
    part_id: np.ndarray,  # [H, W]
    transient: np.ndarray | None = None,  # [H, W]
    min_occ: float = 0.0,
) -> tuple[list[np.ndarray], list[int]]:
    crops, labels = [], []
    need = max(64, int(MIN_FRAC * part_id.size))
    for k in np.unique(part_id[part_id >= 0]):
        m = part_id == k
        if m.sum() < need:
            continue
        if min_occ > 0:
            if transient is None or (transient & m).sum() / m.sum() < min_occ:
                continue
        crops.append(prepare_crop(image, m))
        labels.append(int(k))
    return crops, labels


def calibrate(scene: Path, n_views: int, seed: int) -> dict[str, dict]:
    """Accuracy per crop set on one scene; also crops/s of encode_images."""
    world, cams = load_truth(scene)
    enc = scene_encoder(scene)
    text = enc.encode_texts([p.query for p in world.parts])  # [P, 512]
    negs = enc.encode_texts(list(NEGATIVES))
    ids = np.array([p.id for p in world.parts])
    sets: dict[str, tuple[list, list]] = {
        s: ([], []) for s in ("clean", "hard", "occluded", "as-shot")
    }
    recs = [r for r in cams["images"] if r["split"] == "train"][:n_views]
    for r in recs:
        v, _ = rerender(world, r, "neutral", "none", seed=seed)
        _add(sets["clean"], _part_crops(v.image, v.part_id))
        v, _ = rerender(world, r, "hard", "none", seed=seed)
        _add(sets["hard"], _part_crops(v.image, v.part_id))
        v, _ = rerender(world, r, "neutral", "force", seed=seed)
        _add(sets["occluded"], _part_crops(v.image, v.part_id, v.transient, OCCLUDED))
        img = cv2.cvtColor(
            cv2.imread(str(scene / "dense" / "images" / r["name"])), cv2.COLOR_BGR2RGB
        )
        t = np.load(scene / "synthetic" / "truth" / (Path(r["name"]).stem + ".npz"))
        _add(sets["as-shot"], _part_crops(img, t["part_id"]))
    out = {}
    for name, (crops, labels) in sets.items():
        if not crops:
            out[name] = {"n": 0, "acc": float("nan"), "open_win": float("nan"),
                         "open_margin": float("nan"), "crops_per_s": float("nan")}  # fmt: skip
            continue
        x = np.stack(crops)
        t0 = time.perf_counter()
        f = enc.encode_images(x)
        dt = time.perf_counter() - t0
        pred = ids[np.argmax(f @ text.T, axis=1)]
        own = np.searchsorted(ids, np.asarray(labels))
        margin = (f * text[own]).sum(1) - (f @ negs.T).max(1)
        out[name] = {
            "n": len(labels),
            "acc": float((pred == np.asarray(labels)).mean()),
            "open_win": float((margin > 0).mean()),
            "open_margin": float((margin >= MARGIN).mean()),
            "crops_per_s": len(labels) / dt,
        }
    out["_meta"] = {"parts": len(world.parts), "chance": 1.0 / len(world.parts)}
    return out


def _add(dst: tuple[list, list], src: tuple[list, list]) -> None:
    dst[0].extend(src[0])
    dst[1].extend(src[1])


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--out", type=Path, default=Path("work/synthetic"))
    ap.add_argument(
        "--views", type=int, default=30, help="train cameras re-rendered per scene"
    )
    ap.add_argument(
        "--json", type=Path, default=None, help="also write the results here"
    )
    args = ap.parse_args()
    rows, results = [], {}
    for seed in args.seeds:
        scene = args.out / f"bench_s{seed}"
        t0 = time.perf_counter()
        if not (scene / "synthetic" / "truth" / "cameras.json").is_file():
            generate_scene(args.out, "bench", seed, progress=False)
        gen = time.perf_counter() - t0
        res = calibrate(scene, args.views, seed)
        results[seed] = res
        meta = res.pop("_meta")
        for name, r in res.items():
            rows.append(
                f"| {seed} | {name} | {r['n']} | {r['acc']:.3f} | {meta['chance']:.3f} "
                f"| {r['open_win']:.3f} | {r['open_margin']:.3f} "
                f"| {r['crops_per_s']:.0f} |"
            )
        print(f"seed {seed}: {meta['parts']} parts, generation {gen:.1f} s", flush=True)
    print()
    print("| seed | set | crops | closed-set accuracy | chance | open set: wins | "
          "open set: by the margin | crops/s |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    for name in ("clean", "hard", "occluded", "as-shot"):
        n = sum(results[s][name]["n"] for s in results)
        acc = [
            sum(results[s][name][k] * results[s][name]["n"] for s in results)
            / max(n, 1)
            for k in ("acc", "open_win", "open_margin")
        ]
        print(
            f"| all | {name} | {n} | {acc[0]:.3f} | | {acc[1]:.3f} | {acc[2]:.3f} | |"
        )
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
