"""The encoder seam, the LangSplat crop recipe and the stand-in for CLIP."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from ptovs.encoders import Encoder, get_encoder, prepare_crop, scene_encoder
from ptovs.encoders.synthetic import GENERIC_PHRASES, SyntheticEncoder
from ptovs.synthetic.generate import load_truth, rerender
from ptovs.synthetic.world import render_swatch


@pytest.fixture(scope="module")
def tiny(tiny_scene_dir: Path) -> Path:
    return tiny_scene_dir  # the session's tiny scene, seed 0 (conftest.py)


@pytest.fixture(scope="module")
def enc(tiny: Path) -> SyntheticEncoder:
    return scene_encoder(tiny)


def _crops(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x = rng.random((n, 224, 224, 3), dtype=np.float32)
    yy, xx = np.mgrid[0:224, 0:224]
    for k in range(n):
        r = rng.uniform(30, 110)
        x[k][(yy - 112) ** 2 + (xx - 112) ** 2 > r * r] = 0
    return x


# ---------------------------------------------------------------- crops --


def test_prepare_crop_recipe() -> None:
    img = np.full((40, 60, 3), 200, np.uint8)
    img[..., 1] = 100
    mask = np.zeros((40, 60), bool)
    mask[10:20, 5:45] = True  # 10 x 40: wide, padded top and bottom
    mask[12, 5] = False
    c = prepare_crop(img, mask, size=80)
    assert c.shape == (80, 80, 3) and c.dtype == np.float32
    assert 0.0 <= c.min() and c.max() <= 1.0
    # the 40-wide box fills the width; rows outside the centred band are black
    assert np.all(c[:25] == 0) and np.all(c[-25:] == 0)
    np.testing.assert_allclose(c[40, 40], [200 / 255, 100 / 255, 200 / 255], atol=1e-6)
    # float input gives (nearly) the same crop
    cf = prepare_crop(img.astype(np.float32) / 255, mask, size=80)
    assert np.abs(cf - c).max() < 2 / 255


def test_prepare_crop_zeroes_outside_mask() -> None:
    rng = np.random.default_rng(1)
    img = rng.integers(1, 256, (50, 50, 3), dtype=np.uint8)
    mask = np.zeros((50, 50), bool)
    mask[10:40, 10:40] = True
    mask[20:30, 20:30] = False  # a hole inside the box
    c = prepare_crop(img, mask, size=30)  # the box is 30 x 30: resize is identity
    assert np.all(c[10:20, 10:20] == 0)
    assert np.all(c[:10].max(axis=-1) > 0)
    with pytest.raises(ValueError, match="empty mask"):
        prepare_crop(img, np.zeros((50, 50), bool))
    with pytest.raises(ValueError):
        prepare_crop(img, np.ones((10, 10), bool))


# -------------------------------------------------------------- factory --


def test_get_encoder(tiny: Path) -> None:
    e = get_encoder("synthetic", vocabulary=tiny / "synthetic" / "vocabulary.json")
    assert isinstance(e, Encoder) and e.name == "synthetic" and e.dim == 512
    with pytest.raises((ValueError, ImportError), match=r"clip_checkpoint|\[clip\]"):
        # no checkpoint given (or the extra is missing)
        get_encoder("openclip", pretrained="laion2b_s34b_b88k")
    with pytest.raises((ValueError, ImportError), match=r"clip_pretrained|\[clip\]"):
        get_encoder("openclip")  # ViT-B-16's tags disagree on the activation
    with pytest.raises(ValueError, match="synthetic"):
        get_encoder("dino")
    with pytest.raises(FileNotFoundError):
        get_encoder("synthetic", vocabulary=tiny / "nope.json")


# --------------------------------------------------------------- images --


def test_image_side_shapes_norms_batches(enc: SyntheticEncoder) -> None:
    x = _crops(9)
    f = enc.encode_images(x)
    assert f.shape == (9, 512) and f.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(f, axis=1), 1.0, atol=1e-6)
    # batch independent, bitwise
    assert np.array_equal(enc.encode_images(x[3:5]), f[3:5])
    assert np.array_equal(enc.encode_images(x[7:8]), f[7:8])
    # another crop size works
    assert enc.encode_images(x[:2, ::2, ::2]).shape == (2, 512)
    assert enc.encode_images(np.zeros((0, 224, 224, 3), np.float32)).shape == (0, 512)
    with pytest.raises(ValueError):
        enc.encode_images(x[0])


def test_deterministic_across_processes(tiny: Path, tmp_path: Path) -> None:
    vocab = tiny / "synthetic" / "vocabulary.json"
    phrases = list(json.loads(vocab.read_text())["phrases"])[:3] + [
        "object",
        "sky",
        "zebra",
    ]
    np.save(tmp_path / "x.npy", _crops(5, seed=7))
    script = textwrap.dedent(
        f"""
        import hashlib, numpy as np
        from ptovs.encoders import get_encoder
        e = get_encoder("synthetic", vocabulary={str(vocab)!r})
        f = e.encode_images(np.load({str(tmp_path / "x.npy")!r}))
        t = e.encode_texts({phrases!r})
        print(hashlib.sha256(f.tobytes() + t.tobytes()).hexdigest())
        """
    )
    outs = [
        subprocess.run(
            [sys.executable, "-c", script],
            capture_output=True,
            text=True,
            check=True,
            env=env,
        ).stdout.strip()
        for env in (None, {**__import__("os").environ, "OMP_NUM_THREADS": "1"})
    ]
    assert len(outs[0]) == 64 and outs[0] == outs[1]


# ---------------------------------------------------------------- texts --


def test_text_side(enc: SyntheticEncoder, tiny: Path) -> None:
    vocab = json.loads((tiny / "synthetic" / "vocabulary.json").read_text())
    parts = json.loads((tiny / "synthetic" / "truth" / "parts.json").read_text())
    phrases = [p["query"] for p in parts["parts"]] + parts["distractors"] + ["sky"]
    t = enc.encode_texts(phrases)
    assert t.shape == (len(phrases), 512) and t.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(t, axis=1), 1.0, atol=1e-6)
    # a phrase's embedding is its swatch's embedding: the best text for the swatch
    sw = np.stack([render_swatch(vocab["phrases"][p]) for p in phrases])
    sims = enc.encode_images(sw) @ t.T
    assert (np.argmax(sims, axis=1) == np.arange(len(phrases))).all()
    # case and surrounding spaces do not matter for vocabulary phrases
    assert np.array_equal(enc.encode_texts([f"  {phrases[0].upper()} "]), t[:1])
    # generic phrases: fixed mixtures, distinct, same with or without a vocabulary
    g = enc.encode_texts(list(GENERIC_PHRASES))
    assert len({row.tobytes() for row in g}) == len(GENERIC_PHRASES)
    bare = SyntheticEncoder()
    assert np.array_equal(bare.encode_texts(["object"]), enc.encode_texts(["object"]))
    # sky works without a vocabulary and matches a sky crop better than a part
    sky = bare.encode_texts(["sky"])
    assert np.allclose(np.linalg.norm(sky), 1.0)
    # unknown phrases: seeded by the phrase, stable across instances, unrelated
    u = enc.encode_texts(["Obelisk of Somewhere", "Zebra crossing"])
    assert np.array_equal(
        u, bare.encode_texts(["Obelisk of Somewhere", "Zebra crossing"])
    )
    assert abs(float(u[0] @ u[1])) < 0.9
    img = enc.encode_images(_crops(4))
    assert np.abs(img @ u.T).max() < 0.2
    with pytest.raises(ValueError):
        enc.encode_texts("Column")


def test_clip_like_calibration_on_tiny(tiny: Path, enc: SyntheticEncoder) -> None:
    world, cams = load_truth(tiny)
    text = enc.encode_texts([p.query for p in world.parts])
    ids = np.array([p.id for p in world.parts])
    crops, labels, hard_crops, hard_labels = [], [], [], []
    for r in [r for r in cams["images"] if r["split"] == "train"][:8]:
        for kind, dst, lab in (
            ("neutral", crops, labels),
            ("hard", hard_crops, hard_labels),
        ):
            v, _ = rerender(world, r, kind, "none", seed=1)
            for k in np.unique(v.part_id[v.part_id >= 0]):
                m = v.part_id == k
                if m.sum() >= 40:
                    dst.append(prepare_crop(v.image, m))
                    lab.append(k)
    pred = ids[np.argmax(enc.encode_images(np.stack(crops)) @ text.T, axis=1)]
    acc = float((pred == np.array(labels)).mean())
    pred_h = ids[np.argmax(enc.encode_images(np.stack(hard_crops)) @ text.T, axis=1)]
    acc_h = float((pred_h == np.array(hard_labels)).mean())
    chance = 1.0 / len(world.parts)
    assert len(labels) >= 15
    assert acc >= chance + 0.4, acc
    assert acc_h < acc, (acc_h, acc)
