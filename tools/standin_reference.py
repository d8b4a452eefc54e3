"""Reference output of the stand-in for CLIP, version 5: features of fixed crops
and phrases, to check that a refactoring of the stand-in leaves it unchanged.

The inputs are built deterministically from public interfaces only: a small
world (`build_world`, fixed seed) written for version 5 (`scene_vocabulary`),
its parts cut as segment crops from a few views under a few lights, and
striped discs at several contrasts and sizes. The encoder is the one a version-5
scene gets (`synthetic_encoder`).

    python tools/standin_reference.py            # rewrite tests/data/standin_v5_reference.npz
    python tools/standin_reference.py --check    # compare with it

The file holds float32 unit rows; `tests/test_standin.py` recomputes and
compares them within 1e-5 (the CPU's floating point differs between machines).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REFERENCE = Path(__file__).resolve().parents[1] / "tests/data/standin_v5_reference.npz"
SEED = 20261129
N_PARTS = 3
AZIMUTHS = (-60.0, 0.0, 45.0)
PHRASES = ("building", "object", "sky", "ground", "no such phrase")


def striped_part(contrast: float, side: int = 40, seed: int = 0) -> np.ndarray:
    """A crop as the pipeline cuts it: a textured disc of `side` px in a 160-px
    photo (stripes and noise about mid grey, blended to grey at `contrast`, kept
    in floating point), black outside the mask, resized up to 224 px."""
    from ptovs.crop import prepare_crop

    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:160, 0:160]
    lum = 0.5 + 0.2 * np.sin(2 * np.pi * (xx + 0.6 * yy) / 7.0)
    lum = lum + 0.05 * rng.standard_normal(lum.shape)
    rgb = np.stack([lum * 1.1, lum, lum * 0.8], -1).clip(0, 1)
    img = (0.5 + contrast * (rgb - 0.5)).astype(np.float32)
    mask = (yy - 80) ** 2 + (xx - 80) ** 2 <= (side // 2) ** 2
    return prepare_crop(img, mask)


def inputs() -> tuple[dict, np.ndarray, list[str]]:
    """The version-5 vocabulary, the crops [B, 224, 224, 3] and the phrases."""
    from dataclasses import replace

    from ptovs.crop import prepare_crop
    from ptovs.synthetic.generate import PRESETS, scene_vocabulary
    from ptovs.synthetic.world import build_world, neutral_appearance, render
    from ptovs.synthetic.world.swatches import landmark_camera

    world = build_world(np.random.default_rng(SEED), N_PARTS)
    vocab = scene_vocabulary(world, PRESETS["tiny"], [], 5)
    lights = [neutral_appearance(), replace(neutral_appearance(), filter="sepia")]
    crops = []
    for az in AZIMUTHS:
        cam = landmark_camera(world, az, 128)
        for app in lights:
            v = render(world, cam, app, aa=1)
            img = np.maximum(v.image.astype(np.float32) / 255.0, 1.0 / 255.0)
            for p in world.parts:
                m = v.part_id == p.id
                if m.sum() >= 64:
                    crops.append(prepare_crop(img, m))
    for k, (c, s) in enumerate(
        [(1.0, 40), (0.2, 40), (0.05, 40), (0.03, 24), (1.0, 90)]
    ):
        crops.append(striped_part(c, s, k))
    phrases = sorted(vocab["parts"]) + list(PHRASES)
    return vocab, np.stack(crops), phrases


def features() -> dict[str, np.ndarray]:
    """Version 5's image and text features of `inputs()`."""
    from ptovs.encoders import synthetic_encoder

    vocab, crops, phrases = inputs()
    enc = synthetic_encoder(vocab)
    return {
        "images": enc.encode_images(crops).astype(np.float32),
        "texts": enc.encode_texts(phrases).astype(np.float32),
        "phrases": np.array(phrases),
    }


def compare(got: dict, want: dict, tol: float = 1e-5) -> list[str]:
    """What differs between two `features()` results beyond `tol` (empty: same)."""
    out = []
    if list(got["phrases"]) != list(want["phrases"]):
        out.append(f"phrases differ: {list(got['phrases'])} vs {list(want['phrases'])}")
    for k in ("images", "texts"):
        a, b = got[k], want[k]
        if a.shape != b.shape:
            out.append(f"{k}: shape {a.shape} vs {b.shape}")
        elif not np.allclose(a, b, rtol=tol, atol=tol):
            out.append(f"{k}: max |diff| {np.abs(a - b).max():.3g}")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--check", action="store_true", help="compare, do not write")
    args = ap.parse_args(argv)
    got = features()
    if args.check:
        with np.load(REFERENCE, allow_pickle=False) as f:
            want = {k: f[k] for k in f.files}
        diff = compare(got, want)
        print("\n".join(diff) or f"{REFERENCE.name}: same")
        return 1 if diff else 0
    REFERENCE.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(REFERENCE, **got)
    print(f"wrote {REFERENCE} ({REFERENCE.stat().st_size} bytes)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
