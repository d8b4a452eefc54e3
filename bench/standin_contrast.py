"""Why the stand-in loses low-contrast crops (issue 41, amendment 9's diagnosis).

    python bench/standin_contrast.py --seeds 300-302 --version 4
    python bench/standin_contrast.py --seeds 300-302 --version 3 --rim 3

Calibration seeds only, crops only, no method. For each part of each clean photo
(as `standin_profile.py` cuts them, 3x, 16 train cameras a seed) the photo is
blended to mid grey at 50 %, 20 %, 5 % and 3 % contrast, once rounded to 8 bits
(as every photo is) and once kept in floating point; the crops are read by the
stand-in and classified closed-set. Each row is top-1 accuracy relative to the clean
crops. If a row loses as much in floating point as in 8 bits, the loss is the
encoder's reading of contrast, not the photo's grey levels.

Also, per crop, how much of the crop's luminance spread is the mask's rim: the
standard deviation of the luminance over the whole mask at the encoder's working
size, over that 3 px inside the edge. The crop's resize mixes the part with the
black outside, a dark ring of fixed depth however faint the part is; version 2's
statistics normalise the luminance by the spread over the whole mask.

`--rim N` reads with version 2's statistics measured N px inside the mask's edge
(`synthetic_v2.PARAMS["rim"]`; versions 2 to 4 use 0), `--set` with version 5's
other options (`robust=1 core_texture=1 clip_ln=3`), `--floor F` with another
contrast normalisation floor ((L - mean) / (sd + F); the shipped 0.001). Only for
versions 2 and 3: versions 4 and 5 read through projections fitted on their own
statistics (version 5 reads inside the rim already).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import standin_profile as SP  # noqa: E402  (same folder)
from common import ROOT, seed_list  # noqa: E402

from ptovs.atomic import atomic_file  # noqa: E402
from ptovs.crop import prepare_crop  # noqa: E402
from ptovs.encoders import synthetic_v2 as v2  # noqa: E402
from ptovs.synthetic.generate import plan_scene  # noqa: E402

CONTRASTS = (0.5, 0.2, 0.05, 0.03)
RIM_PX = 3  # the rim measure's depth, at the encoder's working size


def rim_share(crop: np.ndarray, depth: int = RIM_PX) -> float:
    """Luminance SD over the crop's mask at the encoder's working size, over the SD
    `depth` px inside the mask's edge (nan when the inside is too small or flat)."""
    r = v2._R
    valid = (cv2.cvtColor(crop, cv2.COLOR_RGB2GRAY) > 0).astype(np.float32)
    w = v2._area(valid, r)
    col = np.clip(v2._area(crop, r) / np.maximum(w, 1e-6)[..., None], 0.0, 1.0)
    lum = col @ np.array([0.299, 0.587, 0.114])
    m = w >= 0.5
    k = np.ones((2 * depth + 1, 2 * depth + 1), np.uint8)
    inner = cv2.erode(m.astype(np.uint8), k).astype(bool)
    if inner.sum() < 20 or lum[inner].std() <= 1e-9:
        return float("nan")
    return float(lum[m].std() / lum[inner].std())


def measure(seed: int, version: int, n_cams: int = 16, scale: int = 3) -> dict:
    """Per row, [truth, prediction] of every crop of one seed; the rim shares."""
    plan = plan_scene("small", seed, version)
    phrases, label = SP.part_labels(plan.world)
    enc = SP.encoder(version, plan.world)
    text = enc.encode_texts(phrases)
    rows: dict[str, list] = {}
    rims: dict[str, list] = {}
    for _ci, _cam, _rec, clean, parts in SP.clean_views(plan, seed, n_cams, scale):
        x = clean.image.astype(np.float32) / np.float32(255.0)
        crops = {"clean": [prepare_crop(clean.image, m) for _, m in parts]}
        for c in CONTRASTS:
            name = f"contrast-{round(100 * c)}"
            low = SP._contrast(clean.image, c)  # 8-bit, as the profile's rows
            crops[name] = [prepare_crop(low, m) for _, m in parts]
            flt = (c * x + (1.0 - c) * 0.5).astype(np.float32)
            crops[name + "-float"] = [prepare_crop(flt, m) for _, m in parts]
        for name, cs in crops.items():
            batch = np.stack(cs).astype(np.float32)
            if not name.endswith("-float"):  # the profile stores crops in 8 bits
                batch = np.round(batch * 255.0) / np.float32(255.0)
            pred = np.argmax(enc.encode_images(batch) @ text.T, axis=1)
            rows.setdefault(name, []).extend(
                [[label[k], int(p)] for (k, _), p in zip(parts, pred, strict=True)]
            )
            if name == "clean" or name.endswith("-float"):
                rims.setdefault(name, []).extend(rim_share(c) for c in batch)
    return {"seed": seed, "rows": rows, "rims": rims}


def summarise(results: list[dict]) -> dict:
    acc = {}
    for name in results[0]["rows"]:
        t = np.array([r for res in results for r in res["rows"][name]])
        acc[name] = float(np.mean(t[:, 0] == t[:, 1]))
    base = acc["clean"]
    out = {name: {"accuracy": a, "relative": a / base - 1.0} for name, a in acc.items()}
    for name in results[0]["rims"]:
        v = np.array([x for res in results for x in res["rims"][name]], np.float64)
        out[name]["rim_share_median"] = float(np.nanmedian(v))
        out[name]["rim_share_p90"] = float(np.nanpercentile(v, 90))
    out["clean"]["n"] = sum(len(res["rows"]["clean"]) for res in results)
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", nargs="+", default=["300-302"])
    ap.add_argument("--version", type=int, default=4, choices=(2, 3, 4, 5))
    ap.add_argument("--rim", type=int, default=0,
                    help="version 2's statistics this many px inside the mask's edge")  # fmt: skip
    ap.add_argument("--floor", type=float, default=None,
                    help="version 2's contrast normalisation floor (shipped: 0.001)")  # fmt: skip
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=V",
                    help="more of version 5's options for versions 2 and 3: "
                    "robust=1, core_texture=1, clip_ln=3")  # fmt: skip
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args(argv)
    options = {}
    for item in args.set:
        key, _, value = item.partition("=")
        if key not in ("robust", "core_texture", "clip_ln") or not value:
            ap.error(f"--set {item!r}: one of robust=, core_texture=, clip_ln=")
        options[key] = float(value)
    if args.rim < 0:
        ap.error("--rim must be >= 0")
    if args.floor is not None and not 0.0 < args.floor < 1.0:
        ap.error("--floor must be in (0, 1): a flat part divides by it")
    if (args.rim or args.floor is not None or options) and args.version >= 4:
        ap.error("--rim, --floor and --set need --version 2 or 3 (versions 4 and 5 read "
                 "through a projection fitted on their own statistics)")  # fmt: skip
    v2.PARAMS["rim"] = args.rim  # this process only; the shipped versions use 0
    if args.floor is not None:
        v2.PARAMS["floor"] = args.floor
    v2.PARAMS.update(options)
    t0 = time.perf_counter()
    results = []
    for seed in seed_list(args.seeds):
        results.append(measure(seed, args.version))
        print(f"seed {seed}: {time.perf_counter() - t0:.0f} s", flush=True)
    summary = summarise(results)
    tag = f"rim{args.rim}" + ("" if args.floor is None else f"_floor{args.floor:g}")
    tag += "".join(f"_{k}{v:g}" for k, v in options.items())
    out = args.out or ROOT / "work" / "standin" / f"contrast_v{args.version}_{tag}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(out) as tmp:
        Path(tmp).write_text(json.dumps({"summary": summary, "seeds": results}))
    print(f"version {args.version}, {tag}: clean "
          f"{summary['clean']['accuracy']:.3f} (n {summary['clean']['n']})")  # fmt: skip
    for name, r in summary.items():
        extra = (
            f"  rim share {r['rim_share_median']:.2f} (p90 {r['rim_share_p90']:.2f})"
            if "rim_share_median" in r
            else ""
        )
        print(f"  {name:20s} {r['accuracy']:.3f} {100 * r['relative']:+4.0f} %{extra}")


if __name__ == "__main__":
    main()
