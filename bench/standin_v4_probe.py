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
  v4            version 4 as shipped (`synthetic_v4`: lda:16:0.25:0.15:2.0)
  v3-quiet      version 3 without its keyed perturbation
  v3-capped     version 3 with the perturbation held at a clean crop's size
  groups:G=W,..:NOISE  version 3 with other group weights (colour, lum,
                silhouette, layout, fine, coarse)
  shrink:M:A:NOISE  version 3 with the bank's M leading within-part directions
                (the views' and lights' main effects on a part's statistics)
                scaled by A, then the keyed perturbation of relative size NOISE
  drop:A-B[,C-D]:K:NOISE[:Q:BIG]  lda with the standardised statistics A..B
                (inclusive indices) set to 0 in the bank and the crops
  lda:K:NOISE[:Q:BIG]  the statistics projected onto the K directions that best separate
                parts from one another against their spread across views and
                lights (Fisher's discriminant), fitted once on a bank of parts of
                other worlds (--bank-seeds; never calibration or judged seeds)
                under 12 azimuths and 7 lights (neutral, 3 daylight, black-and-
                white, sepia, night); the keyed perturbation (relative size
                NOISE, grown by the crop's distortion as in version 2) added in
                that space, then a fixed random projection to 512-d; with Q
                and BIG, a keyed share Q of crops gets BIG more perturbation.

`--decompose` prints, per seed, the between-part and within-part variance of
version 3's standardised statistics by group, the perturbation's share, and how
much of the between-part variance the top principal components hold.
"""

from __future__ import annotations

import argparse
import pickle
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import standin_profile as SP  # noqa: E402  (same folder)
from common import ROOT, seed_list  # noqa: E402

from ptovs.encoders import synthetic as v1  # noqa: E402
from ptovs.encoders import synthetic_v2 as v2  # noqa: E402
from ptovs.encoders import synthetic_v4 as v4  # noqa: E402
from ptovs.field.relevancy import CANONICAL  # noqa: E402
from ptovs.synthetic.world import render_swatch  # noqa: E402

BANDS = {  # the table's rows this probe can read: relative change, (low, high)
    "bw": (-0.20, 0.0), "sepia": (-0.20, 0.0), "daylight": (-0.15, 0.02),
    "night": (-0.35, -0.05), "piece-70-100": (-0.25, 0.0),
    "piece-40-70": (-0.55, 0.0), "piece-10-40": (-0.75, -0.10),
}  # fmt: skip
FULL_BANDS = {  # the rest of the registered table (--full)
    "contrast-5": (-0.20, -0.03), "contrast-3": (-0.45, -0.15),
    "blur-3": (-0.30, -0.05), "blur-5": (-0.65, -0.30),
    "res-64": (-0.30, -0.05), "res-32": (-0.65, -0.30), "jpeg-7": (-0.65, -0.20),
    "noise-05": (-0.15, 0.0), "noise-20": (-0.65, -0.30),
    "occluded-10%-30%": (-0.25, 0.0), "occluded-30%-60%": (-0.55, -0.10),
}  # fmt: skip


def _stats(crops: np.ndarray) -> dict:
    return {
        "raw": v2.raw_features(crops),
        "key": np.array([v2._key(c) for c in crops], np.uint64),
    }


def cache_seed(seed: int, cache: Path, full: bool = False) -> dict:
    """The code row's crops of a calibration seed (version 3's world) as
    statistics and keys, with its phrases' and canonical phrases' crops; with
    `full`, every row of the table."""
    path = cache / f"s{seed}_v3{'_full' if full else ''}.pkl"
    if path.is_file():
        return pickle.loads(path.read_bytes())
    col = SP.collect(seed, 16, 3, 3, code_only=not full)
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


def cache_bank(seeds: list[int], cache: Path) -> dict:
    """Parts of other worlds as segment crops (`synthetic_v4.bank_statistics`):
    12 azimuths x 7 lights; a class per (world, part)."""
    path = cache / f"bank_{seeds[0]}-{seeds[-1]}.pkl"
    if path.is_file():
        return pickle.loads(path.read_bytes())
    raw, cls = v4.bank_statistics(
        seeds, lambda s, n: print(f"bank world {s}: {n} crops", flush=True)
    )
    out = {"raw": raw, "cls": cls}
    cache.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(out))
    return out


# ------------------------------------------------------------------ variants


def standardise(
    raw: np.ndarray, weights: dict | None = None
) -> tuple[np.ndarray, float]:
    """Version 2's standardised, clipped, group-weighted statistics, and their
    nominal norm (the perturbation's unit); `weights` overrides group weights."""
    if not weights:
        return v2.standardised(raw)
    p = {**v2.PARAMS, **{f"w_{k}": x for k, x in weights.items()}}
    bank = v2._bank()
    mean, scale = bank.mean(axis=0), np.maximum(bank.std(axis=0), 1e-3)
    gw = np.concatenate(
        [np.full(n, p[f"w_{name}"] / np.sqrt(n)) for name, n in v2._GROUPS]
    )
    z = np.clip((raw - mean) / scale, -v2.ZCLIP, v2.ZCLIP)[:, : v2.N_FEATURES] * gw
    return z, float(np.sqrt((gw * gw).sum()))


def perturbation(raw, keys, dim: int, size: float, cap: float | None = None,
                 spike: tuple[float, float] = (0.0, 0.0)):  # fmt: skip
    """The keyed perturbation; with spike (Q, BIG), a keyed share Q of crops gets
    BIG more (a flip of the crop's reading that another light does not share)."""
    amp = v4.perturbation_size(
        raw, keys, {"noise": size, "flip": spike[0], "flip_size": spike[1]}
    )
    if cap is not None:  # (no variant caps and flips at once)
        amp = np.minimum(amp, cap)
    e = np.stack([np.random.default_rng(int(k)).standard_normal(dim) for k in keys])
    return amp[:, None] * e / np.sqrt(dim)


def v3_content(size: float, cap: float | None = None, weights: dict | None = None):
    """Version 2's `content` from cached statistics (the same up to float order),
    optionally with other group weights."""
    P, _ = v2._projection()

    def f(raw, keys):
        z, norm = standardise(raw, weights)
        z = z + norm * perturbation(raw, keys, v2.N_FEATURES, size, cap)
        return v1._normalise(z @ P)

    return f


def lda_content(bank: dict, k: int, size: float, spike=(0.0, 0.0),
                drop: list[tuple[int, int]] = ()):  # fmt: skip
    """Fisher's projection of the bank, the keyed perturbation in its space, the
    fixed projection to 512-d; with `drop`, the standardised statistics in those
    index ranges (inclusive) set to 0 in the bank and in every crop (amendment 9's
    diagnosis: which statistics carry the loss at low contrast)."""
    keep = np.ones(v2.N_FEATURES)
    for lo, hi in drop:
        keep[lo : hi + 1] = 0.0
    zb = standardise(bank["raw"])[0] * keep if drop else None
    mu, V, scale, _ = v4.fisher(bank["raw"], bank["cls"], k, z=zb)
    P = np.random.default_rng(v2.SEED + 11).standard_normal((k, v2.DIM))

    def f(raw, keys):
        z = standardise(raw)[0] * keep
        y = (z - mu) @ V + scale * perturbation(raw, keys, k, size, spike=spike)
        return v1._normalise(y @ P / np.sqrt(v2.DIM))

    return f


def nuisance(bank: dict, m: int):
    """The bank's M leading within-part directions of the standardised statistics
    (how a part's crops vary across views and lights), orthonormal, and the mean."""
    z, _ = standardise(bank["raw"])
    w = np.concatenate(
        [
            z[bank["cls"] == c] - z[bank["cls"] == c].mean(0)
            for c in np.unique(bank["cls"])
        ]
    )
    _, ev, vt = np.linalg.svd(w, full_matrices=False)
    return z.mean(0), vt[:m], (ev[:m] ** 2) / (ev**2).sum()


def shrink_content(bank: dict, m: int, alpha: float, size: float):
    """Version 3 with the bank's M leading nuisance directions scaled by ALPHA
    before the keyed perturbation and the projection."""
    P, _ = v2._projection()
    mu, U, _ = nuisance(bank, m)

    def f(raw, keys):
        z, norm = standardise(raw)
        z = z - (1.0 - alpha) * ((z - mu) @ U.T) @ U
        z = z + norm * perturbation(raw, keys, v2.N_FEATURES, size)
        return v1._normalise(z @ P)

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
    bands = dict(BANDS)
    if "blur-3" in s["rows"]:
        bands.update(FULL_BANDS)
        view = s["rows"]["view-60-180"]["accuracy"] / s["rows"]["view-0-30"]["accuracy"]
        s["rows"]["view"] = {"relative": view - 1.0}
        bands["view"] = (-0.30, -0.05)
        print(f"  shape bias {s['shape_bias']:.2f} (0.40-0.70)")
    for name, (lo, hi) in bands.items():
        r = s["rows"][name]["relative"]
        inband += lo <= r <= hi
        print(f"  {name:16s} {100 * r:+4.0f} %  [{100 * lo:+.0f}, {100 * hi:+.0f}]")
    print(f"  code-3         {100 * c['relative']:+4.0f} % [{100 * c['relative_ci'][0]:+.0f},"
          f" {100 * c['relative_ci'][1]:+.0f}]  (-20 % - 0 %); through it relevancy own "
          f"{c['relevancy_own_code']:.3f}, other {c['relevancy_other_code']:.3f}")  # fmt: skip
    print(f"  {inband} of {len(bands)} rows in band", flush=True)


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
    ap.add_argument("--full", action="store_true", help="every row of the table")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    data = [cache_seed(s, args.cache, args.full) for s in seed_list(args.seeds)]
    print(f"seeds cached ({time.perf_counter() - t0:.0f} s)", flush=True)
    if args.decompose:
        for d in data:
            decompose(d)
    bank = None
    for v in args.variants:
        if v == "v3":
            f = v3_content(v2.PARAMS["noise"])
        elif v == "v4":
            f = v4.content_from
        elif v == "v3-quiet":
            f = v3_content(0.0)
        elif v == "v3-capped":
            f = v3_content(v2.PARAMS["noise"], cap=v2.PARAMS["noise"])
        elif v.startswith(("lda:", "drop:")):  # [drop:66-75,80-81:]K:NOISE[:Q:BIG]
            head, *rest = v.split(":")
            spec = rest.pop(0) if head == "drop" else ""
            k, size, *sp = rest
            if bank is None:
                bank = cache_bank(seed_list(args.bank_seeds), args.cache)
            spike = (float(sp[0]), float(sp[1])) if sp else (0.0, 0.0)
            drop = [tuple(int(x) for x in r.split("-")) for r in spec.split(",") if r]
            f = lda_content(bank, int(k), float(size), spike, drop)
        elif v.startswith("groups:"):  # groups:fine=1.0,silhouette=0.4:NOISE
            _, spec, size = v.split(":")
            w = {k: float(x) for k, x in (kv.split("=") for kv in spec.split(","))}
            f = v3_content(float(size), weights=w)
        elif v.startswith("shrink:"):
            _, m, alpha, size = v.split(":")
            if bank is None:
                bank = cache_bank(seed_list(args.bank_seeds), args.cache)
            f = shrink_content(bank, int(m), float(alpha), float(size))
        else:
            ap.error(f"unknown variant {v!r}")
        report([score(d, f) for d in data], v)
    print(f"done in {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
