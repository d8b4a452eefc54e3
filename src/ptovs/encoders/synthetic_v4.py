"""The stand-in for CLIP, version 4 (issue 41): version 3 read through a learnt
invariance, so that a scene's crops cluster by part as CLIP's do.

Version 3's image statistics vary more within one part (across views and
lights) than they differ between parts; a scene's 3-d code then keeps the
variation and loses the parts (docs/benchmarks.md, "Amendment 6 measured").
CLIP learnt its invariances from other data. Version 4 does the same in small:

1. version 2's statistics of the crop, standardised as in version 2;
2. projected onto `K` directions that best separate parts from one another
   against their spread across views and lights (Fisher's discriminant),
   fitted once on a bank of parts of *other* worlds (seeds 900-911, 12
   azimuths x 7 lights; never a calibration or judged seed) and shipped with
   the package (`standin_v4.npz`, verified by its SHA-256 on load;
   `python tools/fit_standin_v4.py` refits it);
3. a keyed perturbation in that space: version 2's (its size grows with the
   crop's blur deficit and chroma decoupling), plus a *flip*: a keyed share
   `flip` of crops gets `flip_size` more. A flip depends on the crop's pixels,
   so another light or view of the same part is flipped independently: errors
   differ between appearances, the paper's premise;
4. a fixed random projection to 512-d.

The text side is version 3's (part phrases as category descriptions, "building"
as the average word) computed with this image side. Version 4 reads version 3's
worlds: the generator screens its queries with version 3, so a seed's photos are
the same for both stand-ins and only the reading differs.
"""

from __future__ import annotations

import functools
import hashlib
from dataclasses import replace
from importlib import resources

import numpy as np

from ptovs.encoders import synthetic as v1
from ptovs.encoders import synthetic_v2 as v2

VERSION = 4
K = 16
PARAMS: dict[str, float] = {  # calibrated on crops of calibration seeds 300-305
    "noise": 0.25,  # version 2's keyed perturbation, relative to the feature norm
    "flip": 0.15,  # the keyed share of crops that are read wrong-footed
    "flip_size": 2.0,  # how much more perturbation a flipped crop gets
}
BANK_SEEDS = tuple(range(900, 912))
PROJECTION_FILE = "standin_v4.npz"
PROJECTION_SHA256 = "3c86f5fd2ffcf659eea60d58633814836fa94c5343c4241e71f6a3be28fa3996"


@functools.lru_cache(maxsize=1)
def projection() -> dict[str, np.ndarray]:
    """The shipped invariance projection: mean [N], directions [N, K], scale."""
    return load_projection(PROJECTION_FILE, PROJECTION_SHA256)


def load_projection(name: str, sha256: str) -> dict[str, np.ndarray]:
    """A shipped projection file of this package, verified by its SHA-256."""
    blob = resources.files("ptovs.encoders").joinpath(name).read_bytes()
    digest = hashlib.sha256(blob).hexdigest()
    if digest != sha256:
        raise RuntimeError(
            f"ptovs/encoders/{name} is damaged or not the shipped one "
            f"(sha256 {digest[:12]}..., expected {sha256[:12]}...); "
            "reinstall ptovs or rerun tools/fit_standin_v4.py"
        )
    import io

    with np.load(io.BytesIO(blob), allow_pickle=False) as f:
        out = {k: np.asarray(f[k], np.float64) for k in ("mean", "directions", "scale")}
    if out["directions"].shape != (v2.N_FEATURES, K) or out["mean"].shape != (
        v2.N_FEATURES,
    ):
        raise RuntimeError(f"{name}: unexpected shapes")
    return out


@functools.lru_cache(maxsize=1)
def _to_512() -> np.ndarray:
    return np.random.default_rng(v2.SEED + 11).standard_normal((K, v2.DIM))


def faintness(raw: np.ndarray, params: dict) -> np.ndarray:
    """How much contrast a crop lacks, >= 0 per crop (version 5; 0 without `k4`):
    `k4` x log2(`t4` / R), R the 5-95 % luminance range of the part's core (the
    "lum" group's second statistic under version 5's robust statistics, at least
    one 8-bit grey level). CLIP's accuracy falls off below about 5 % contrast;
    here the crop's keyed perturbation grows as its range falls below `t4`."""
    if not params.get("k4"):
        return np.zeros(len(raw))
    r = np.maximum(raw[:, v2._offset("lum") + 1], 1.0 / 255.0)
    return params["k4"] * np.maximum(np.log2(params["t4"] / r), 0.0)


def perturbation_size(
    raw: np.ndarray, keys, params: dict | None = None, stats: dict | None = None
) -> np.ndarray:
    """Each crop's perturbation size, relative to the projected features' scale:
    version 2's (plus `faintness`), plus `flip_size` for the keyed share `flip`
    of crops. `stats`: the options of version 2's statistics (None: shipped)."""
    p = PARAMS if params is None else params
    amp = p["noise"] * (1.0 + v2.distortion(raw, stats) + faintness(raw, p))
    hit = np.array(
        [np.random.default_rng([int(k), 1]).random() < p["flip"] for k in keys], bool
    )
    return amp + p["flip_size"] * hit


def content(crops: np.ndarray, params: dict | None = None) -> np.ndarray:
    """Unit content vectors [B, 512] float64 of crops [B, S, S, 3]."""
    raw = v2.raw_features(crops)
    keys = [v2._key(c) for c in crops]
    return content_from(raw, keys, params)


def content_from(
    raw: np.ndarray, keys, params: dict | None = None,
    proj: dict | None = None, stats: dict | None = None,
) -> np.ndarray:  # fmt: skip
    """`content` from version 2's statistics and the crops' keys (`proj`, `stats`:
    another version's projection and statistics' options; None: version 4's)."""
    proj = projection() if proj is None else proj
    z, _ = v2.standardised(raw, stats)
    amp = perturbation_size(raw, keys, params, stats)
    P = _to_512()
    out = np.zeros((len(z), v2.DIM))
    for b in range(len(z)):  # row by row: a crop's vector never depends on its batch
        y = (z[b] - proj["mean"]) @ proj["directions"]
        e = np.random.default_rng(int(keys[b])).standard_normal(K)
        y = y + proj["scale"] * amp[b] * e / np.sqrt(K)
        out[b] = y @ P
    return v1._normalise(out)


class SyntheticEncoderV4(v2.SyntheticEncoderV3):
    """Stand-in for CLIP, version 4 (module docstring): version 3's text rules on
    an image side read through a learnt invariance, with keyed flips."""

    name = "synthetic-v4"
    image_side = staticmethod(content)


# ------------------------------------------------------------------ fitting --


def bank_lights() -> list:
    """The bank's 7 lights: neutral, 3 daylight draws, black-and-white, sepia,
    a night draw."""
    from ptovs.synthetic.world import neutral_appearance
    from ptovs.synthetic.world.appearance import sample_appearance

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


def bank_statistics(
    seeds, progress=None, stats: dict | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Version 2's statistics [n, N] (with the options `stats`; None: shipped)
    of the parts of the worlds of `seeds` (preset small, version 3's worlds) as
    segment crops, 12 azimuths x 7 lights, and their class [n] (one per world and
    part)."""
    from ptovs.crop import prepare_crop
    from ptovs.synthetic.generate import plan_scene
    from ptovs.synthetic.world import render
    from ptovs.synthetic.world.swatches import landmark_camera

    raws, cls, c0 = [], [], 0
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
        raws.append(v2.raw_features(np.stack(crops), stats))
        cls += lab
        c0 += len(ids)
        if progress is not None:
            progress(seed, len(crops))
    return np.concatenate(raws), np.array(cls)


def fisher(
    raw: np.ndarray, cls: np.ndarray, k: int = K, ridge: float = 1e-3,
    z: np.ndarray | None = None, stats: dict | None = None,
):  # fmt: skip
    """The k directions of the standardised statistics that best separate the
    classes against their within-class spread (within-class covariance whitened
    to I, ridge-regularised). Returns mean [N], directions [N, k], the mean norm
    of the projected, centred rows, and the k eigenvalues. `z`, if given, stands
    for the standardised statistics of `raw` (a probe's variant of them)."""
    if z is None:
        z, _ = v2.standardised(raw, stats)
    mu = z.mean(0)
    n = z.shape[1]
    sw, sb = np.zeros((n, n)), np.zeros((n, n))
    for c in np.unique(cls):
        zc = z[cls == c]
        m = zc.mean(0)
        sw += (zc - m).T @ (zc - m)
        sb += len(zc) * np.outer(m - mu, m - mu)
    sw = sw / len(z)
    sw = sw + ridge * np.trace(sw) / n * np.eye(n)
    li = np.linalg.inv(np.linalg.cholesky(sw))
    ev, u = np.linalg.eigh(li @ (sb / len(z)) @ li.T)
    order = np.argsort(ev)[::-1][:k]
    V = li.T @ u[:, order]
    scale = float(np.sqrt((((z - mu) @ V) ** 2).sum(1)).mean())
    return mu, V, scale, ev[order]
