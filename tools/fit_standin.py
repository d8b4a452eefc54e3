"""Refit the invariance projection of the stand-in for CLIP, version 5.

    python tools/fit_standin.py [--out PATH]

Renders the parts of the bank worlds (seeds 900-911, preset small; never a
calibration or judged seed) under 12 azimuths x 7 lights, reduces each crop to
version 5's statistics, fits Fisher's discriminant over (world, part) classes
and writes its mean, directions and scale (default: the package's own
`standin_v5.npz`). About ten minutes on 2 cores. The package verifies the file
by its SHA-256 (`synthetic_v5.PROJECTION_SHA256`): after a refit, put the
printed digest there. Floats differ between CPU models, so a refit elsewhere may
differ in the last bits.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from ptovs.encoders import standin_stats as st
from ptovs.encoders import synthetic_v5 as v5

ROOT = Path(__file__).resolve().parent.parent


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


def bank_statistics(seeds, progress=None) -> tuple[np.ndarray, np.ndarray]:
    """Version 5's statistics [n, N] of the parts of the worlds of `seeds`
    (preset small, as the generator plans them for version 5) as segment crops,
    12 azimuths x 7 lights, and their class [n] (one per world and part)."""
    from ptovs.crop import prepare_crop
    from ptovs.synthetic.generate import plan_scene
    from ptovs.synthetic.world import render
    from ptovs.synthetic.world.swatches import landmark_camera

    raws, cls, c0 = [], [], 0
    for seed in seeds:
        world = plan_scene("small", seed, 5).world
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
        raws.append(v5.raw_features(np.stack(crops)))
        cls += lab
        c0 += len(ids)
        if progress is not None:
            progress(seed, len(crops))
    return np.concatenate(raws), np.array(cls)


def fisher(raw: np.ndarray, cls: np.ndarray, k: int = v5.K, ridge: float = 1e-3,
           stats: dict | None = None):  # fmt: skip
    """The k directions of the standardised statistics that best separate the
    classes against their within-class spread (within-class covariance whitened
    to I, ridge-regularised). Returns mean [N], directions [N, k], the mean norm
    of the projected, centred rows, and the k eigenvalues."""
    z, _ = st.standardised(raw, stats)
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


def write(raw: np.ndarray, cls: np.ndarray, out: Path) -> str:
    mu, V, scale, ev = fisher(raw, cls, v5.K, stats=v5.STATS)
    buf = io.BytesIO()
    np.savez(buf, mean=mu, directions=V, scale=np.array(scale), eigenvalues=ev,
             bank_seeds=np.array(v5.BANK_SEEDS), n_crops=np.array(len(raw)))  # fmt: skip
    blob = buf.getvalue()
    tmp = out.with_suffix(".tmp")
    tmp.write_bytes(blob)
    tmp.replace(out)
    return hashlib.sha256(blob).hexdigest()


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", type=Path, default=None,
                    help="where to write (default: the package's file)")  # fmt: skip
    args = ap.parse_args(argv)
    out = args.out or ROOT / "src" / "ptovs" / "encoders" / v5.PROJECTION_FILE
    raw, cls = bank_statistics(
        v5.BANK_SEEDS, lambda s, n: print(f"bank world {s}: {n} crops", flush=True)
    )
    digest = write(raw, cls, out)
    print(f"wrote {out} ({len(raw)} crops); sha256 {digest}")


if __name__ == "__main__":
    sys.exit(main())
