"""How the stand-in encoder fails, crop by crop, against CLIP's published profile.

    python bench/standin_profile.py --seeds 300-303 --out work/standin/profile.json
    make bench-standin                     # version 5; STANDIN_VERSION=1 for version 1

Calibration only: crops of the labelled parts (truth masks, cut as the pipeline cuts
a segment: `ptovs.crop.prepare_crop`), classified closed-set among the scene's part
phrases (top-1 text cosine). No method, no field, no mIoU is computed here. The
calibration seeds (300 and up) are never used to judge a method.

Per seed, the world and cameras are the generator's plan (`plan_scene`, preset
`small`); every train camera is rendered again (`rerender`) under

  clean        the neutral daylight, no occluders: the reference of every row
  daylight     a random ordinary appearance (day, dusk or overcast, no filter)
  night        a random night appearance
  bw, sepia    the neutral daylight through the camera's film filter
  occluded     the neutral daylight with new billboards (rows by covered share)
  piece        the crops the pipeline makes: segments of the clean photo (the
               default segmenter, every level) that lie within one part, in rows
               by the share of the part's pixels they show (`native-piece`: the
               same at the preset's own photo size, against its `native` row)
  conflict     the neutral daylight with every part's texture moved to another
               part (a derangement): shape of one part, texture of another

and the clean render is degraded as the published studies degrade images:

  contrast-5, contrast-3   the photo blended to mid grey at 5 % / 3 % contrast
                           (model-vs-human), 8-bit
  contrast-5-levels, contrast-3-levels   per part, the photo blended
                           so that the part keeps the grey levels a whole real
                           photograph keeps at 5 % / 3 %: contrast c * REAL_SPREAD /
                           the part's own 5-95 % luminance range, at most 1
  jpeg-7                   the photo as JPEG quality 7 (ImageNet-C severity 5)
  blur-3, blur-5           Gaussian blur of the 224-px crop, sigma 3 / 5 px
  res-64, res-32           the 224-px crop through 64 / 32 px (LR0.FM)
  noise-05, noise-20       uniform noise of width 0.05 / 0.20 on the crop

Each row is top-1 accuracy and its change relative to clean on the same crops,
with a 95 % bootstrap interval over (seed, view) clusters (an appearance row draws
one light per view; `--summarise FILE` reprints a saved run with them). Also:
shape bias on the conflict crops (decisions for the part's own phrase over
decisions for the phrase of the texture it wears), the view change (clean crops by
the camera's azimuth from the landmark's front), and how independent the errors of
two daylight renders of the same crop are (error lift: P(wrong in B | wrong in A)
/ P(wrong in B); 1 is independent). On the clean crops, the relevancy rows:
the pipeline's relevancy (min over its canonical phrases of
sigmoid(tau (cos q - cos c)), tau = 10) of the crop's own phrase and, per crop, the
median over the scene's other part phrases; each row is the median over crops.

The scene code: the chain's 512 -> 3 -> 512 autoencoder
(`ptovs.stages.train_ae`, its defaults, no uncertainty weights), trained per seed
on the crops the scene's ordinary photos give (`CODE_FIT` in bench/standin_code.py:
whole parts under neutral, daylight, night and film light, and the pipeline's
pieces), and the clean and daylight crops (`CODE_EVAL`) read through it:
closed-set accuracy relative to the same crops read raw, and the two relevancy rows
through the code.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import multiprocessing
import sys
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, seed_list  # noqa: E402  (same folder)
from standin_code import code_rows, relevancies, summarise_code  # noqa: E402

from ptovs.atomic import atomic_file  # noqa: E402
from ptovs.crop import prepare_crop  # noqa: E402
from ptovs.encoders import synthetic_encoder  # noqa: E402
from ptovs.synthetic.generate import (  # noqa: E402
    PRESETS,
    plan_scene,
    rerender,
    scene_vocabulary,
)
from ptovs.synthetic.world import Camera, neutral_appearance  # noqa: E402
from ptovs.synthetic.world.appearance import sample_appearance  # noqa: E402

MIN_FRAC = 0.004  # a part needs 0.4 % of the image (and 64 px) to be cut
CROP_ROWS = {  # crop-level degradations: name -> function of a [224, 224, 3] crop
    "blur-3": lambda c, r: _remask(c, cv2.GaussianBlur(c, (0, 0), 3.0)),
    "blur-5": lambda c, r: _remask(c, cv2.GaussianBlur(c, (0, 0), 5.0)),
    "res-64": lambda c, r: _remask(c, _through(c, 64)),
    "res-32": lambda c, r: _remask(c, _through(c, 32)),
    "noise-05": lambda c, r: _remask(c, c + r.uniform(-0.05, 0.05, c.shape)),
    "noise-20": lambda c, r: _remask(c, c + r.uniform(-0.2, 0.2, c.shape)),
}
PHOTO_ROWS = {  # photo-level degradations of the clean render (uint8 RGB)
    "contrast-5": lambda im: _contrast(im, 0.05),
    "contrast-3": lambda im: _contrast(im, 0.03),
    "jpeg-7": lambda im: _jpeg(im, 7),
}
# the median 5-95 % luminance range of whole real photographs at 224 px
# (`tools/real_spread.py` on the two real photo sets: 19 photos), and the rows that
# blend each part to the grey levels such a photograph keeps at 5 % / 3 % contrast
REAL_SPREAD = 0.54
LEVEL_ROWS = {"contrast-5-levels": 0.05, "contrast-3-levels": 0.03}
APPEARANCE_ROWS = ("daylight", "night", "bw", "sepia")
# a piece's share of its part's pixels in the view
PIECE_BINS = ((0.0, 0.1), (0.1, 0.4), (0.4, 0.7), (0.7, 1.01))
OCCLUSION_BINS = ((0.1, 0.3), (0.3, 0.6))
VIEW_BINS = ((0.0, 30.0), (30.0, 60.0), (60.0, 180.0))


def _remask(clean: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Degraded crop kept inside the clean crop's mask (black outside, never
    black inside: black means outside to the encoder)."""
    inside = clean.max(axis=2) > 0
    out = np.clip(out, 1.0 / 255.0, 1.0).astype(np.float32)
    out[~inside] = 0.0
    return out


def _through(crop: np.ndarray, px: int) -> np.ndarray:
    small = cv2.resize(crop, (px, px), interpolation=cv2.INTER_AREA)
    return cv2.resize(small, crop.shape[:2][::-1], interpolation=cv2.INTER_CUBIC)


def _contrast(im: np.ndarray, c: float) -> np.ndarray:
    x = im.astype(np.float64) / 255.0
    return np.clip(np.round((c * x + (1 - c) * 0.5) * 255.0), 0, 255).astype(np.uint8)


def luminance_spread(image: np.ndarray, mask: np.ndarray) -> float:
    """The 5-95 % range of a uint8 RGB photo's luminance over `mask`, in [0, 1]."""
    y = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)[mask]
    if y.size == 0:
        return 0.0
    lo, hi = np.percentile(y.astype(np.float64) / 255.0, [5, 95])
    return float(hi - lo)


def level_contrast(c0: float, spread: float) -> float:
    """The contrast that leaves a part of luminance range `spread` the grey levels a
    whole photograph of range REAL_SPREAD keeps at contrast `c0` (at most 1: a flat
    part keeps its photo as it is)."""
    if spread <= 0.0:
        return 1.0
    return float(min(1.0, c0 * REAL_SPREAD / spread))


def _jpeg(im: np.ndarray, quality: int) -> np.ndarray:
    ok, buf = cv2.imencode(".jpg", im[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    return cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1].copy()


def _appearance(kind: str, rng: np.random.Generator):
    if kind in ("bw", "sepia"):
        return replace(neutral_appearance(), filter=kind)
    for _ in range(200):
        app = sample_appearance(rng)
        if kind == "night" and app.sky == "night":
            return app
        if kind == "daylight" and app.sky != "night" and not app.hard:
            return app
    raise RuntimeError(f"no {kind} appearance drawn")


def _parts(view, need: int) -> list[tuple[int, np.ndarray]]:
    return [
        (int(k), view.part_id == k)
        for k in np.unique(view.part_id[view.part_id >= 0])
        if (view.part_id == k).sum() >= need
    ]


def _azimuth(world, cam: Camera) -> float:
    """Degrees between the camera and the landmark's front (-y), about the up axis."""
    d = cam.centre - world.center
    return abs(math.degrees(math.atan2(d[0], -d[1])))


@functools.lru_cache(maxsize=1)
def _segmenter():
    from ptovs.segment import get_segmenter

    return get_segmenter("hier", levels=("s", "m", "l"))


def pieces(image: np.ndarray, part_id: np.ndarray, need: int):
    """The default segmenter's segments of a photo that lie within one part (at
    least 80 % of their pixels on it, 70 % on some part): (part, share of the part's
    pixels in the view that the segment shows, mask), every level."""
    out = []
    for level in _segmenter().segment(np.ascontiguousarray(image)):
        for k in range(int(level.labels.max()) + 1):
            m = level.mask(k)
            under = part_id[m]
            under = under[under >= 0]
            if m.sum() < need or len(under) < 0.7 * m.sum():
                continue
            major = int(np.bincount(under).argmax())
            if (under == major).mean() >= 0.8:
                share = float((under == major).sum() / (part_id == major).sum())
                out.append((major, share, m))
    return out


def _piece_row(prefix: str, share: float) -> str | None:
    for lo, hi in PIECE_BINS:
        if lo <= share < hi:
            return f"{prefix}-{lo * 100:.0f}-{min(hi, 1.0) * 100:.0f}"
    return None


def part_labels(world) -> tuple[list[str], dict[int, int]]:
    """The scene's part phrases (sorted) and each part's index among them."""
    phrases = sorted({p.query for p in world.parts})
    return phrases, {p.id: phrases.index(p.query) for p in world.parts}


def clean_views(plan, seed: int, n_cams: int, scale: int):
    """The calibration's views of a seed: `n_cams` train cameras drawn by the seed,
    at `scale` x the preset's side, each rendered under the neutral daylight without
    occluders. Yields (camera index, camera, its record, the render, its parts big
    enough to cut) for the cameras that show any part."""
    train = [i for i in range(len(plan.cams)) if i not in plan.test_ids]
    rng = np.random.default_rng([seed, 41])
    cams = sorted(rng.choice(train, min(n_cams, len(train)), replace=False).tolist())
    for ci in cams:
        cam = plan.cams[ci].scaled(scale)
        rec = {"image_id": ci, **cam.to_dict()}
        need = max(64 * scale * scale, int(MIN_FRAC * cam.width * cam.height))
        clean, _ = rerender(plan.world, rec, "neutral", "none", seed=seed)
        parts = _parts(clean, need)
        if parts:
            yield ci, cam, rec, clean, parts


def encoder(version: int, world, preset: str = "small"):
    """The stand-in of `version` for a world, from its vocabulary as the generator
    writes it."""
    return synthetic_encoder(scene_vocabulary(world, PRESETS[preset], [], version))


def collect(
    seed: int, n_cams: int, scale: int = 3, version: int = 5, preset: str = "small"
) -> dict:
    """Every row's crops (uint8) and truth labels for one calibration seed, in
    the world the generator makes for stand-in `version` (its screen's textures)."""
    plan = plan_scene(preset, seed, version)
    world = plan.world
    phrases, label = part_labels(world)
    rows: dict[str, list] = {}  # row -> [(cam, part, truth[, texture's label]), crop]

    def add(row: str, ci: int, pid: int, crop: np.ndarray, *extra: int) -> None:
        c8 = np.round(np.clip(crop, 0.0, 1.0) * 255.0).astype(np.uint8)
        rows.setdefault(row, []).append(((ci, pid, label[pid], *extra), c8))

    for ci, cam, rec, clean, parts in clean_views(plan, seed, n_cams, scale):
        crops = {k: prepare_crop(clean.image, m) for k, m in parts}
        for row, c0 in LEVEL_ROWS.items():
            for k, m in parts:  # the part's spread kept in thousandths
                r = luminance_spread(clean.image, m)
                low = _contrast(clean.image, level_contrast(c0, r))
                add(row, ci, k, prepare_crop(low, m), round(1e3 * r))
        known = {k for k, _ in parts}
        for k, share, m in pieces(clean.image, clean.part_id, 30 * scale * scale):
            row = _piece_row("piece", share)
            if row and k in known:
                add(row, ci, k, prepare_crop(clean.image, m))
        if scale != 1:  # the parts at the instrument's photo size
            rec1 = {"image_id": ci, **plan.cams[ci].to_dict()}
            small, _ = rerender(world, rec1, "neutral", "none", seed=seed)
            for k, _m in parts:
                if (small.part_id == k).sum() >= 16:
                    add("native", ci, k, prepare_crop(small.image, small.part_id == k))
            for k, share, m in pieces(small.image, small.part_id, 30):
                row = _piece_row("native-piece", share)
                if row and k in known:
                    add(row, ci, k, prepare_crop(small.image, m))
        for k, c in crops.items():
            add("clean", ci, k, c)
        arng = np.random.default_rng([seed, 43, ci])
        for row in APPEARANCE_ROWS + ("daylight-b",):
            app = _appearance(row.removesuffix("-b"), arng)
            v, _ = rerender(world, rec, app, "none", seed=seed)
            for k, m in parts:  # same masks: the geometry does not change
                add(row, ci, k, prepare_crop(v.image, m))
        az = _azimuth(world, cam)
        crng = np.random.default_rng([seed, 42, ci])
        for k, c in crops.items():
            for lo, hi in VIEW_BINS:
                if lo <= az < hi:
                    add(f"view-{lo:.0f}-{hi:.0f}", ci, k, c)
            for row, fn in CROP_ROWS.items():
                add(row, ci, k, fn(c, crng))
        for row, fn in PHOTO_ROWS.items():
            img = fn(clean.image)
            for k, m in parts:
                add(row, ci, k, prepare_crop(img, m))
        occ, _ = rerender(world, rec, "neutral", "force", seed=seed)
        for k, m in parts:
            share = float((occ.transient & m).sum() / m.sum())
            for lo, hi in OCCLUSION_BINS:
                if lo <= share < hi:
                    add(
                        f"occluded-{lo:.0%}-{hi:.0%}", ci, k, prepare_crop(occ.image, m)
                    )
        # cue conflict: every part wears the texture of the next one (in id order)
        ids = [p.id for p in world.parts]
        wearer = {ids[i]: ids[(i + 1) % len(ids)] for i in range(len(ids))}
        tex = {p.id: p.texture for p in world.parts}
        swapped = replace(
            world, parts=[replace(p, texture=tex[wearer[p.id]]) for p in world.parts]
        )
        v, _ = rerender(swapped, rec, "neutral", "none", seed=seed)
        for k, m in parts:
            if label[wearer[k]] != label[k]:  # the same phrase is no conflict
                add("conflict", ci, k, prepare_crop(v.image, m), label[wearer[k]])
    return {"seed": seed, "world": world, "phrases": phrases, "rows": rows}


def score(col: dict, version: int) -> dict:
    """Each crop's predicted phrase under the stand-in of `version`, the
    relevancy rows on the clean crops, and the scene code's rows."""
    from ptovs.field.relevancy import CANONICAL

    enc = encoder(version, col["world"])
    text = enc.encode_texts(col["phrases"])
    canon = enc.encode_texts(list(CANONICAL))
    out, rel, embs, truths = {}, [], {}, {}
    for row, items in col["rows"].items():
        crops = np.stack([c for _, c in items]).astype(np.float32) / np.float32(255.0)
        emb = enc.encode_images(crops).astype(np.float64)
        pred = np.argmax(emb @ text.T, axis=1)
        out[row] = [
            [*meta[:3], int(p), *meta[3:]]
            for (meta, _), p in zip(items, pred, strict=True)
        ]
        embs[row] = emb
        truths[row] = np.array([meta[2] for meta, _ in items])
        if row == "clean":
            rel = relevancies(emb @ text.T, emb @ canon.T, truths[row]).tolist()
    res = {"seed": col["seed"], "phrases": col["phrases"], "rows": out,
           "relevancy": rel}  # fmt: skip
    res["code"] = code_rows(embs, truths, text, canon)
    return res


def view_interval(
    results: list[dict], rows: tuple[str, ...], n_boot: int = 2000, seed: int = 0
) -> list[float]:
    """95 % bootstrap interval of the accuracy of `rows` (pooled) over clean's,
    minus 1, resampling (seed, view) clusters: each view of a seed is one draw of
    the appearance rows' light, so such a row is as precise as its number of
    views, not of crops. Rows are [view, part, truth, prediction, ...]."""
    recs = [
        (res["seed"], r[0], name == "clean", r[2] == r[3])
        for res in results
        for name in ("clean", *rows)
        for r in res["rows"].get(name, [])
    ]
    if not recs:
        return [float("nan"), float("nan")]
    t = np.array(recs, dtype=np.float64)
    _, inv = np.unique(t[:, :2], axis=0, return_inverse=True)
    inv = inv.ravel()
    k = int(inv.max()) + 1
    sums = [
        np.bincount(inv[m], t[m, 3] if ok else None, k)
        for m in (t[:, 2] == 1, t[:, 2] == 0)
        for ok in (True, False)
    ]  # clean right, clean crops, row right, row crops: per cluster
    pick = np.random.default_rng(seed).integers(0, k, (n_boot, k))
    c_ok, c_n, r_ok, r_n = (x[pick].sum(1) for x in sums)
    acc_c = c_ok / np.maximum(c_n, 1)
    ratio = r_ok / np.maximum(r_n, 1) / np.maximum(acc_c, 1e-12) - 1.0
    return [float(np.percentile(ratio, 2.5)), float(np.percentile(ratio, 97.5))]


def summarise(results: list[dict]) -> dict:
    """Accuracy per row, relative change against clean, shape bias, error lift."""
    acc: dict[str, dict] = {}
    clean = [r for res in results for r in res["rows"].get("clean", [])]
    base = float(np.mean([t == p for _, _, t, p in clean])) if clean else float("nan")
    names = sorted({k for res in results for k in res["rows"]} - {"conflict"})
    for name in names:
        rs = [r for res in results for r in res["rows"].get(name, [])]
        a = float(np.mean([r[2] == r[3] for r in rs])) if rs else float("nan")
        acc[name] = {"n": len(rs), "accuracy": a, "relative": a / base - 1.0}
        if rs and name != "clean":
            acc[name]["relative_ci_views"] = view_interval(results, (name,))
        if name in LEVEL_ROWS and rs:  # the parts' own spread, and the contrast given
            r = np.array([x[4] for x in rs]) / 1e3
            c = [level_contrast(LEVEL_ROWS[name], v) for v in r]
            acc[name] |= {"median_spread": float(np.median(r)),
                          "median_contrast": float(np.median(c))}  # fmt: skip
    if "native" in acc:  # the instrument's size: pieces against its whole parts
        for name, row in acc.items():
            if name.startswith("native-piece"):
                row["relative_native"] = row["accuracy"] / acc["native"]["accuracy"] - 1
    conf = [r for res in results for r in res["rows"].get("conflict", [])]
    shape = sum(r[3] == r[2] for r in conf)
    texture = sum(r[3] == r[4] for r in conf)
    out = {
        "clean_accuracy": base,
        "rows": acc,
        "shape_bias": shape / (shape + texture) if shape + texture else float("nan"),
        "conflict": {"n": len(conf), "shape": shape, "texture": texture},
    }
    # error lift between two independent daylight renders of the same crops
    wa, wb = [], []
    for res in results:
        a = {(r[0], r[1]): r[2] != r[3] for r in res["rows"].get("daylight", [])}
        b = {(r[0], r[1]): r[2] != r[3] for r in res["rows"].get("daylight-b", [])}
        for key in a.keys() & b.keys():
            wa.append(a[key])
            wb.append(b[key])
    wa_, wb_ = np.array(wa), np.array(wb)
    p_b = wb_.mean() if len(wb_) else float("nan")
    p_b_given_a = wb_[wa_].mean() if wa_.any() else float("nan")
    out["error_lift"] = float(p_b_given_a / p_b) if p_b > 0 else float("nan")
    rel = np.array([r for res in results for r in res.get("relevancy", [])])
    if len(rel):
        out["relevancy_own"] = float(np.median(rel[:, 0]))
        out["relevancy_other"] = float(np.nanmedian(rel[:, 1]))
    if "daylight" in acc and "daylight-b" in acc:  # both draws of ordinary light
        both = acc["daylight"]["accuracy"] + acc["daylight-b"]["accuracy"]
        out["daylight_both"] = {
            "relative": both / 2 / base - 1.0,
            "relative_ci_views": view_interval(results, ("daylight", "daylight-b")),
        }
    code = summarise_code(results)
    if code:
        out["code"] = code
    return out


def _one_seed(n_cams: int, scale: int, version: int, t0: float, seed: int) -> dict:
    out = score(collect(seed, n_cams, scale, version), version)
    print(f"seed {seed}: {time.perf_counter() - t0:.0f} s", flush=True)
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", nargs="+", default=["300-303"])
    ap.add_argument("--cams", type=int, default=16, help="train cameras a seed")
    ap.add_argument("--version", type=int, default=5, choices=(1, 5))
    ap.add_argument("--scale", type=int, default=3, help="photo side x the preset's")
    ap.add_argument(
        "--out", type=Path, default=ROOT / "work" / "standin" / "profile.json"
    )
    ap.add_argument("--jobs", type=int, default=1, help="seeds measured at once")
    ap.add_argument("--summarise", type=Path, metavar="JSON",
                    help="re-read a saved profile (its crops' decisions) and print "
                    "its summary again, with the intervals; nothing is measured")  # fmt: skip
    args = ap.parse_args(argv)
    if args.summarise is not None:
        try:
            saved = json.loads(args.summarise.read_text())
            seeds, version = saved["seeds"], saved["summary"]["version"]
        except (OSError, ValueError, KeyError, TypeError) as e:
            ap.error(f"--summarise {args.summarise}: not a saved profile ({e}); "
                     "give the --out file of an earlier run")  # fmt: skip
        report({**summarise(seeds), "version": version})
        return
    t0 = time.perf_counter()
    seeds = seed_list(args.seeds)
    job = functools.partial(_one_seed, args.cams, args.scale, args.version, t0)
    if args.jobs > 1:
        ctx = multiprocessing.get_context("spawn")
        with ctx.Pool(args.jobs) as pool:
            results = pool.map(job, seeds, chunksize=1)
    else:
        results = [job(s) for s in seeds]
    summary = summarise(results)
    summary["version"] = args.version
    summary["seconds"] = round(time.perf_counter() - t0, 1)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_file(args.out) as tmp:
        Path(tmp).write_text(json.dumps({"summary": summary, "seeds": results}))
    report(summary)


def report(summary: dict) -> None:
    """Print a profile's summary: each row with its (seed, view)-cluster interval."""
    print(f"version {summary['version']}  clean accuracy "
          f"{summary['clean_accuracy']:.3f}  shape bias "
          f"{summary['shape_bias']:.2f}  error lift {summary['error_lift']:.2f}  "
          f"relevancy own {summary.get('relevancy_own', float('nan')):.3f} "
          f"other {summary.get('relevancy_other', float('nan')):.3f}")  # fmt: skip
    for name, r in summary["rows"].items():
        lo, hi = r.get("relative_ci_views", (float("nan"),) * 2)
        print(f"  {name:22s} n={r['n']:4d}  acc {r['accuracy']:.3f}  "
              f"{100 * r['relative']:+.1f} %  [{100 * lo:+.1f}, {100 * hi:+.1f}]")  # fmt: skip
    if "daylight_both" in summary:
        d = summary["daylight_both"]
        lo, hi = d["relative_ci_views"]
        print(f"  {'daylight, both draws':22s} {100 * d['relative']:+.1f} %  "
              f"[{100 * lo:+.1f}, {100 * hi:+.1f}]")  # fmt: skip
    if "code" in summary:
        c = summary["code"]
        print(f"  scene code (3-d)       n={c['n']:4d}  acc {c['accuracy_raw']:.3f} -> "
              f"{c['accuracy_code']:.3f}  {100 * c['relative']:+.0f} % "
              f"[{100 * c['relative_ci'][0]:+.0f}, {100 * c['relative_ci'][1]:+.0f}]  relevancy own "
              f"{c['relevancy_own_raw']:.3f} -> {c['relevancy_own_code']:.3f}, other "
              f"{c['relevancy_other_raw']:.3f} -> {c['relevancy_other_code']:.3f}")  # fmt: skip


if __name__ == "__main__":
    main()
