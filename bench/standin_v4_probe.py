"""A dev probe toward stand-in version 4: the scene-code row (issue 41, amendment 6).

    python bench/standin_v4_probe.py --seeds 300 301 --decompose \\
        --variants v3 v3-quiet lda:16:0.25 lda:16:0.6

Calibration seeds only, crops only, no method and no mIoU. Version 3's features
lose a quarter of their closed-set accuracy through a scene's 3-d code, CLIP's
0-17 % (docs/benchmarks.md, "Amendment 6 measured"). This asks why, and tries one
design on the crops the code row uses (`standin_profile.py --code-only`'s rows:
whole parts under neutral, daylight, night and film light, and the pipeline's
pieces), which cover 7 of the table's rows and the code row; the rest (blur, low
resolution, noise, JPEG, contrast, occluders, the cue conflict, the view change)
need the full table.

Each seed's crops are reduced once to version 2's statistics and perturbation keys
(cached under --cache); a variant is a function of those, so each is scored in
seconds plus the code's training. Variants:

  v3            version 3 as frozen (the check that the cache reproduces it)
  v3-quiet      version 3 without its keyed perturbation
  v3-capped     version 3 with the perturbation held at a clean crop's size
  lda:K:NOISE   the statistics projected onto the K directions that best separate
                parts from one another against their spread across views and
                lights (Fisher's discriminant), fitted once on a bank of parts of
                other worlds (--bank-seeds; never calibration or judged seeds)
                under 12 azimuths and 7 lights (neutral, 3 daylight, black-and-
                white, sepia, night); the keyed perturbation (relative size
                NOISE, grown by the crop's distortion as in version 2) added in
                that space, then a fixed random projection to 512-d.

`--decompose` prints, per seed, the between-part and within-part variance of
version 3's standardised statistics by group, the perturbation's share, and how
much of the between-part variance the top principal components hold.
"""

from __future__ import annotations

import argparse
import pickle
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import standin_profile as SP  # noqa: E402  (same folder)
from common import ROOT, seed_list  # noqa: E402

from ptovs.crop import prepare_crop  # noqa: E402
from ptovs.encoders import synthetic as v1  # noqa: E402
from ptovs.encoders import synthetic_v2 as v2  # noqa: E402
from ptovs.field.relevancy import CANONICAL  # noqa: E402
from ptovs.synthetic.generate import plan_scene  # noqa: E402
from ptovs.synthetic.world import neutral_appearance, render, render_swatch  # noqa: E402
from ptovs.synthetic.world.appearance import sample_appearance  # noqa: E402
from ptovs.synthetic.world.swatches import landmark_camera  # noqa: E402

BANDS = {  # the table's rows this probe can read: relative change, (low, high)
    "bw": (-0.20, 0.0), "sepia": (-0.20, 0.0), "daylight": (-0.15, 0.02),
    "night": (-0.35, -0.05), "piece-70-100": (-0.25, 0.0),
    "piece-40-70": (-0.55, 0.0), "piece-10-40": (-0.75, -0.10),
}  # fmt: skip


def _stats(crops: np.ndarray) -> dict:
    return {
        "raw": v2.raw_features(crops),
        "key": np.array([v2._key(c) for c in crops], np.uint64),
    }


def cache_seed(seed: int, cache: Path) -> dict:
    """The code row's crops of a calibration seed (version 3's world) as
    statistics and keys, with its phrases' and canonical phrases' crops."""
    path = cache / f"s{seed}_v3.pkl"
    if path.is_file():
        return pickle.loads(path.read_bytes())
    col = SP.collect(seed, 16, 3, 3, code_only=True)
    enc = SP.encoder(3, col["world"])
    rows = {}
    for row, items in col["rows"].items():
        crops = np.stack([c for _, c in items]).astype(np.float32) / np.float32(255)
        rows[row] = {"meta": [m for m, _ in items], **_stats(crops)}
    text = {
        ph: [
            _stats(np.stack(v2.part_crops(enc._world, pid)))
            for pid in enc._parts[ph.strip().lower()]
        ]
        for ph in col["phrases"]
    }
    canon = {}
    for c in CANONICAL:
        if c in v2.AVERAGE_WORDS:
            continue
        key = c.strip().lower()
        desc = enc._phrases.get(c, enc._lower.get(key))
        items = (
            [{"weight": 1.0, "swatch": desc}]
            if desc is not None
            else enc._generic.get(key, [{"weight": 1.0, "swatch": v2.sky_swatch()}])
        )
        canon[c] = [
            {"weight": float(it["weight"]), **_stats(render_swatch(it["swatch"])[None])}
            for it in items
        ]
    out = {"seed": seed, "phrases": col["phrases"], "rows": rows, "text": text,
           "canon": canon}  # fmt: skip
    cache.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(out))
    return out


def bank_lights() -> list:
    rng = np.random.default_rng(20261128)
    out = [neutral_appearance()]
    while len(out) < 4:
        a = sample_appearance(rng)
        if a.sky in ("day", "overcast", "dusk") and not a.hard:
            out.append(a)
    out += [replace(neutral_appearance(), filter=f) for f in ("bw", "sepia")]
    while len(out) < 7:
        a = sample_appearance(rng)
        if a.sky == "night":
            out.append(a)
    return out


def cache_bank(seeds: list[int], cache: Path) -> dict:
    """Parts of other worlds as segment crops: 12 azimuths x 7 lights; a class per
    (world, part)."""
    path = cache / f"bank_{seeds[0]}-{seeds[-1]}.pkl"
    if path.is_file():
        return pickle.loads(path.read_bytes())
    raws, keys, cls, c0 = [], [], [], 0
    for seed in seeds:
        world = plan_scene("small", seed, 3).world
        ids = [p.id for p in world.parts]
        crops, lab = [], []
        for az in range(-150, 181, 30):
            cam = landmark_camera(world, float(az), 160)
            for app in bank_lights():
                v = render(world, cam, app, aa=1)
                img = np.maximum(v.image.astype(np.float32) / 255.0, 1.0 / 255.0)
                for j, pid in enumerate(ids):
                    m = v.part_id == pid
                    if m.sum() >= 64:
                        crops.append(prepare_crop(img, m))
                        lab.append(c0 + j)
        s = _stats(np.stack(crops))
        raws.append(s["raw"])
        keys.append(s["key"])
        cls += lab
        c0 += len(ids)
        print(f"bank world {seed}: {len(crops)} crops", flush=True)
    out = {"raw": np.concatenate(raws), "key": np.concatenate(keys),
           "cls": np.array(cls)}  # fmt: skip
    cache.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(out))
    return out


# ------------------------------------------------------------------ variants


def standardise(raw: np.ndarray) -> tuple[np.ndarray, float]:
    """Version 2's standardised, clipped, group-weighted statistics, and their
    nominal norm (the perturbation's unit)."""
    p = v2.PARAMS
    bank = v2._bank()
    mean, scale = bank.mean(axis=0), np.maximum(bank.std(axis=0), 1e-3)
    gw = np.concatenate(
        [np.full(n, p[f"w_{name}"] / np.sqrt(n)) for name, n in v2._GROUPS]
    )
    z = np.clip((raw - mean) / scale, -v2.ZCLIP, v2.ZCLIP)[:, : v2.N_FEATURES] * gw
    return z, float(np.sqrt((gw * gw).sum()))


def perturbation(raw, keys, dim: int, size: float, cap: float | None = None):
    amp = size * (1.0 + v2.distortion(raw, v2.PARAMS))
    if cap is not None:
        amp = np.minimum(amp, cap)
    e = np.stack([np.random.default_rng(int(k)).standard_normal(dim) for k in keys])
    return amp[:, None] * e / np.sqrt(dim)


def v3_content(size: float, cap: float | None = None):
    """Version 2's `content` from cached statistics (the same up to float order)."""
    P, _ = v2._projection()

    def f(raw, keys):
        z, norm = standardise(raw)
        z = z + norm * perturbation(raw, keys, v2.N_FEATURES, size, cap)
        return v1._normalise(z @ P)

    return f


def fisher(bank: dict, k: int, ridge: float = 1e-3):
    """The K directions of the statistics that best separate the bank's classes
    against their within-class spread (within-class covariance whitened to I)."""
    z, _ = standardise(bank["raw"])
    mu = z.mean(0)
    sw, sb = np.zeros((z.shape[1],) * 2), np.zeros((z.shape[1],) * 2)
    for c in np.unique(bank["cls"]):
        zc = z[bank["cls"] == c]
        m = zc.mean(0)
        sw += (zc - m).T @ (zc - m)
        sb += len(zc) * np.outer(m - mu, m - mu)
    sw = sw / len(z) + ridge * np.trace(sw / len(z)) / len(sw) * np.eye(len(sw))
    li = np.linalg.inv(np.linalg.cholesky(sw))
    ev, u = np.linalg.eigh(li @ (sb / len(z)) @ li.T)
    order = np.argsort(ev)[::-1][:k]
    V = li.T @ u[:, order]
    scale = float(np.sqrt((((z - mu) @ V) ** 2).sum(1)).mean())
    return mu, V, scale, ev[order]


def lda_content(bank: dict, k: int, size: float):
    mu, V, scale, _ = fisher(bank, k)
    P = np.random.default_rng(v2.SEED + 11).standard_normal((k, v2.DIM))

    def f(raw, keys):
        z, _ = standardise(raw)
        y = (z - mu) @ V + scale * perturbation(raw, keys, k, size)
        return v1._normalise(y @ P / np.sqrt(v2.DIM))

    return f


def tables(d: dict, content) -> tuple[np.ndarray, np.ndarray]:
    """Phrase and canonical embeddings under `content`, by version 3's rules."""
    parts = {
        ph: v1._normalise(sum(content(x["raw"], x["key"]).mean(0) for x in lst))
        for ph, lst in d["text"].items()
    }
    canon = []
    for c in CANONICAL:
        if c in v2.AVERAGE_WORDS:  # version 3's average word
            m = np.mean([parts[p] for p in sorted(parts, key=str.lower)], axis=0)
            n = np.random.default_rng([v2.SEED + 7, *c.lower().encode()])
            n = n.standard_normal(v2.DIM)
            n = n - (n @ m) / (m @ m) * m
            canon.append(m + np.sqrt(max(0.0, 1 - m @ m)) * n / np.linalg.norm(n))
        else:
            acc = sum(
                x["weight"] * content(x["raw"], x["key"])[0] for x in d["canon"][c]
            )
            canon.append(v1._normalise(acc))
    text = np.stack([parts[ph] for ph in d["phrases"]])
    return (v1._embed(text, 1).astype(np.float64),
            v1._embed(np.stack(canon), 1).astype(np.float64))  # fmt: skip


def score(d: dict, content) -> dict:
    """`standin_profile.score`'s result for one cached seed under `content`."""
    text, canon = tables(d, content)
    out, rel, embs, truths = {}, [], {}, {}
    for row, r in d["rows"].items():
        emb = v1._embed(content(r["raw"], r["key"]), 0).astype(np.float64)
        pred = np.argmax(emb @ text.T, axis=1)
        out[row] = [
            [*m[:3], int(q), *m[3:]] for m, q in zip(r["meta"], pred, strict=True)
        ]
        embs[row], truths[row] = emb, np.array([m[2] for m in r["meta"]])
        if row == "clean":
            rel = SP.relevancies(emb @ text.T, emb @ canon.T, truths[row]).tolist()
    return {"seed": d["seed"], "phrases": d["phrases"], "rows": out, "relevancy": rel,
            "code": SP.code_rows(embs, truths, text, canon)}  # fmt: skip


def report(results: list[dict], label: str) -> None:
    s = SP.summarise(results)
    c = s["code"]
    inband = 0
    print(f"{label}: clean {s['clean_accuracy']:.3f} (0.80-0.90), error lift "
          f"{s['error_lift']:.2f} (<= 3), relevancy own {s['relevancy_own']:.3f} "
          f"other {s['relevancy_other']:.3f}")  # fmt: skip
    for name, (lo, hi) in BANDS.items():
        r = s["rows"][name]["relative"]
        inband += lo <= r <= hi
        print(f"  {name:14s} {100 * r:+4.0f} %  [{100 * lo:+.0f}, {100 * hi:+.0f}]")
    print(f"  code-3         {100 * c['relative']:+4.0f} % [{100 * c['relative_ci'][0]:+.0f},"
          f" {100 * c['relative_ci'][1]:+.0f}]  (-20 % - 0 %); through it relevancy own "
          f"{c['relevancy_own_code']:.3f}, other {c['relevancy_other_code']:.3f}")  # fmt: skip
    print(f"  {inband} of {len(BANDS)} rows in band", flush=True)


def decompose(d: dict) -> None:
    z, n, lab = [], [], []
    for row, r in d["rows"].items():
        if row in SP.CODE_FIT or row.startswith("piece-"):
            zz, norm = standardise(r["raw"])
            z.append(zz)
            n.append(
                norm
                * perturbation(r["raw"], r["key"], v2.N_FEATURES, v2.PARAMS["noise"])
            )
            lab += [m[2] for m in r["meta"]]
    z, n, lab = np.concatenate(z), np.concatenate(n), np.array(lab)

    def split(x):
        means = np.stack([x[lab == k].mean(0) for k in np.unique(lab)])
        idx = np.searchsorted(np.unique(lab), lab)
        return ((means[idx] - x.mean(0)) ** 2).mean(0), ((x - means[idx]) ** 2).mean(0)

    (bt, wt), (bs, ws), (_, wn) = split(z + n), split(z), split(n)
    print(f"seed {d['seed']}: {len(lab)} crops, {len(np.unique(lab))} parts; variance "
          f"between parts / within a part (statistics alone in brackets)")  # fmt: skip
    o = 0
    for g, k in v2._GROUPS:
        sl = slice(o, o + k)
        print(f"  {g:10s} {bt[sl].sum():6.3f} / {wt[sl].sum():6.3f}"
              f"   ({bs[sl].sum():.3f} / {ws[sl].sum():.3f})")  # fmt: skip
        o += k
    print(
        f"  all        {bt.sum():6.3f} / {wt.sum():6.3f}   (perturbation within: {wn.sum():.3f})"
    )
    x = z + n - (z + n).mean(0)
    _, s, vt = np.linalg.svd(x, full_matrices=False)
    means = np.stack([x[lab == k].mean(0) for k in np.unique(lab)])
    w = np.array([(lab == k).sum() for k in np.unique(lab)])[:, None]
    for k in (3, 8):
        held = ((means @ vt[:k].T) ** 2 * w).sum() / (means**2 * w).sum()
        print(f"  top {k} components: {(s[:k] ** 2).sum() / (s**2).sum():.2f} of the "
              f"variance, {held:.2f} of the between-part variance")  # fmt: skip


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", nargs="+", default=["300", "301"])
    ap.add_argument("--bank-seeds", nargs="+", default=["900-911"])
    ap.add_argument("--cache", type=Path, default=ROOT / "work" / "standin" / "v4probe")
    ap.add_argument("--variants", nargs="*", default=["v3"])
    ap.add_argument("--decompose", action="store_true")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    data = [cache_seed(s, args.cache) for s in seed_list(args.seeds)]
    print(f"seeds cached ({time.perf_counter() - t0:.0f} s)", flush=True)
    if args.decompose:
        for d in data:
            decompose(d)
    bank = None
    for v in args.variants:
        if v == "v3":
            f = v3_content(v2.PARAMS["noise"])
        elif v == "v3-quiet":
            f = v3_content(0.0)
        elif v == "v3-capped":
            f = v3_content(v2.PARAMS["noise"], cap=v2.PARAMS["noise"])
        elif v.startswith("lda:"):
            _, k, size = v.split(":")
            if bank is None:
                bank = cache_bank(seed_list(args.bank_seeds), args.cache)
            f = lda_content(bank, int(k), float(size))
        else:
            ap.error(f"unknown variant {v!r}")
        report([score(d, f) for d in data], v)
    print(f"done in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
