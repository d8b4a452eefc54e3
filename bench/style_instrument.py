"""Is the synthetic style measurable? The raw stand-in encoder against a style's text side.

python bench/style_instrument.py --preset bench --seeds 12 --photos 12
python bench/style_instrument.py --preset tiny --seeds 30 --photos 12

For each seed, the landmark is photographed from the seed's own cameras under its
own random appearances (the photos `synth-scene` takes, one sample per pixel, no
transients), each photo is cropped to the landmark by the truth mask as a segment
crop is, and the stand-in encoder picks the nearest of the scene's five candidate
styles. Two definitions of a style's text side are compared:

  v1 mixture   the landmark's part swatches mixed by part extent² (the first
               definition, kept here only for this comparison)
  v2 rendered  the whole landmark under neutral daylight from the front and ±40°,
               cropped as a segment (`synthetic.generate.landmark_look`, current)

Reports per-photo accuracy (a photo picks the true style) and collection accuracy
(the mean similarity over a seed's photos picks it), chance being 0.2. No training,
no pipeline: this bounds what any field distilled from these crops can do.
Results go to --out (JSON) and stdout.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

from ptovs.encoders import prepare_crop
from ptovs.encoders.synthetic import SyntheticEncoder
from ptovs.synthetic import generate as G
from ptovs.synthetic.world import part_swatch, render, sample_appearance


def mixture_look(world, preset) -> list[dict]:
    """v1: part swatches weighted by extent² (what `landmark_look` used to return)."""
    w = np.array([p.size**2 for p in world.parts], float)
    w = w / w.sum()
    return [
        {"weight": float(wi), "swatch": part_swatch(world, p, preset.swatch_px)}
        for wi, p in zip(w, world.parts, strict=True)
    ]


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--preset", default="bench", choices=sorted(G.PRESETS))
    ap.add_argument("--seeds", type=int, default=12, help="seeds 0 .. N-1")
    ap.add_argument("--photos", type=int, default=12, help="photos per seed")
    ap.add_argument(
        "--out", type=Path, default=Path("work/bench/style_instrument.json")
    )
    args = ap.parse_args()
    cfg = G.PRESETS[args.preset]
    rows, t0 = [], time.perf_counter()
    for seed in range(args.seeds):
        plan = G.plan_scene(args.preset, seed)
        world, cams = plan.world, plan.cams
        true, styles = G.scene_styles(cfg, seed, world)
        worlds = G.style_worlds(cfg, seed, world)
        names = list(styles)  # sorted, as the vocabulary lists them
        texts = {
            "v1 mixture": SyntheticEncoder(
                {
                    "phrases": {},
                    "styles": {n: mixture_look(worlds[n], cfg) for n in names},
                }
            ).encode_texts(names),
            "v2 rendered": SyntheticEncoder(
                {"phrases": {}, "styles": styles}
            ).encode_texts(names),
        }
        crops = []
        for i, cam in enumerate(cams[: args.photos]):
            view = render(world, cam, sample_appearance(G._rng(seed, 3, i)), aa=1)
            inside = view.part_id >= 0
            if inside.sum() < 20:
                continue
            crops.append(prepare_crop(view.image.astype(np.float32) / 255.0, inside))
        emb = SyntheticEncoder().encode_images(np.stack(crops))
        row = {"seed": seed, "true": true, "photos": len(crops)}
        for k, t in texts.items():
            sim = emb @ t.T
            row[k] = {
                "per_photo": float(np.mean(sim.argmax(1) == names.index(true))),
                "collection": bool(sim.mean(0).argmax() == names.index(true)),
            }
        rows.append(row)
        print(seed, {k: row[k] for k in texts}, flush=True)
    summary = {
        k: {
            "per_photo": round(float(np.mean([r[k]["per_photo"] for r in rows])), 3),
            "collection": round(float(np.mean([r[k]["collection"] for r in rows])), 3),
        }
        for k in ("v1 mixture", "v2 rendered")
    }
    res = {
        "preset": args.preset,
        "seeds": args.seeds,
        "photos": args.photos,
        "summary": summary,
        "rows": rows,
        "seconds": round(time.perf_counter() - t0, 1),
        "machine": dict(platform=platform.platform(), date=time.strftime("%Y-%m-%d")),
    }
    print(json.dumps(summary, indent=1))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    prev = json.loads(args.out.read_text()) if args.out.exists() else {}
    prev[args.preset] = res
    args.out.write_text(json.dumps(prev, indent=1))


if __name__ == "__main__":
    main()
