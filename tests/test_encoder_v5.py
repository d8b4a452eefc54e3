"""The stand-in for CLIP, version 5 (issue 41): version 4 reading the part inside
its crop's dark rim, with a faintness term."""

from __future__ import annotations

import numpy as np
import pytest

from ptovs.crop import prepare_crop
from ptovs.encoders import synthetic_v2 as v2
from ptovs.encoders import synthetic_v4 as v4
from ptovs.encoders import synthetic_v5 as v5
from ptovs.synthetic.generate import PRESETS, plan_scene, scene_vocabulary


def _striped_part(contrast: float, side: int = 40, seed: int = 0) -> np.ndarray:
    """A crop as the pipeline cuts it: a textured disc of `side` px in a 160-px
    photo (stripes and noise about mid grey, blended to grey at `contrast`, kept
    in floating point), black outside the mask, resized up to 224 px."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:160, 0:160]
    lum = 0.5 + 0.2 * np.sin(2 * np.pi * (xx + 0.6 * yy) / 7.0)
    lum = lum + 0.05 * rng.standard_normal(lum.shape)
    rgb = np.stack([lum * 1.1, lum, lum * 0.8], -1).clip(0, 1)
    img = (0.5 + contrast * (rgb - 0.5)).astype(np.float32)
    mask = (yy - 80) ** 2 + (xx - 80) ** 2 <= (side // 2) ** 2
    return prepare_crop(img, mask)


@pytest.mark.parametrize("mod", [v4, v5], ids=["v4", "v5"])
def test_projection_is_verified_on_read(monkeypatch, mod) -> None:
    p = mod.projection()
    assert p["directions"].shape == (v2.N_FEATURES, mod.K)
    assert np.isfinite(p["directions"]).all() and p["scale"] > 0
    mod.projection.cache_clear()
    monkeypatch.setattr(mod, "PROJECTION_SHA256", "0" * 64)
    try:
        with pytest.raises(RuntimeError, match=f"{mod.PROJECTION_FILE} is damaged"):
            mod.projection()
    finally:
        mod.projection.cache_clear()


def test_texture_statistics_ignore_contrast_unlike_version_4() -> None:
    """The point of version 5: a part blended towards grey (in floating point, so
    no grey level is lost) keeps its texture statistics, where version 2's
    statistics (versions 2 to 4) read the crop's dark ring instead."""
    f, c = v2._offset("fine"), v2._offset("coarse")
    texture = np.r_[f : c + (len(v2.WAVELENGTHS) - v2.N_FINE) * len(v2.THETAS)]
    crops = np.stack([_striped_part(1.0), _striped_part(0.05)])
    new = v2.raw_features(crops, v5.STATS)[:, texture]
    old = v2.raw_features(crops)[:, texture]
    d_new = np.abs(new[0] - new[1]).max()
    d_old = np.abs(old[0] - old[1]).max()
    assert d_new < 0.05, d_new
    assert d_old > 4 * d_new, (d_old, d_new)
    # and the perturbation's blur detector no longer takes the faint crop for a
    # blurred one
    dist = v2.distortion(v2.raw_features(crops, v5.STATS), v5.STATS)
    assert dist[1] == pytest.approx(dist[0], abs=0.1)
    assert v2.distortion(v2.raw_features(crops))[1] > dist[1] + 0.5


def test_faintness_is_the_documented_formula() -> None:
    lum = v2._offset("lum") + 1
    raw = np.zeros((4, v2.N_FEATURES + v2.N_AUX))
    t4, k4 = v5.PARAMS["t4"], v5.PARAMS["k4"]
    raw[:, lum] = [2 * t4, t4, t4 / 4, 0.0]  # the last: below one grey level
    got = v4.faintness(raw, v5.PARAMS)
    want = [0.0, 0.0, 2 * k4, k4 * np.log2(t4 * 255.0)]
    assert np.allclose(got, want)
    assert np.array_equal(v4.faintness(raw, v4.PARAMS), np.zeros(4))  # version 4: off
    # the 5-95 % range the robust statistics put in the "lum" group
    stats = v2.raw_features(_striped_part(0.05)[None], v5.STATS)
    assert 0.0 < stats[0, lum] < 0.05


def test_content_is_the_documented_formula_and_batch_free() -> None:
    crops = np.stack([_striped_part(c, s, k) for k, (c, s) in
                      enumerate([(1.0, 40), (0.05, 40), (0.03, 24), (1.0, 90)])])  # fmt: skip
    raw = v2.raw_features(crops, v5.STATS)
    keys = [v2._key(c) for c in crops]
    p = v5.projection()
    z, _ = v2.standardised(raw, v5.STATS)
    y = (z - p["mean"]) @ p["directions"]
    P = v5.PARAMS
    amp = P["noise"] * (1 + v2.distortion(raw, v5.STATS) + v4.faintness(raw, P))
    amp = amp + P["flip_size"] * np.array(
        [np.random.default_rng([k, 1]).random() < P["flip"] for k in keys]
    )
    e = np.stack([np.random.default_rng(k).standard_normal(v5.K) for k in keys])
    x = (y + p["scale"] * amp[:, None] * e / np.sqrt(v5.K)) @ v4._to_512()
    want = x / np.linalg.norm(x, axis=1, keepdims=True)
    got = v5.content(crops)
    assert np.allclose(got, want, atol=1e-12)
    one = np.concatenate([v5.content(crops[k : k + 1]) for k in range(len(crops))])
    assert np.array_equal(got, one)  # a crop's vector never depends on its batch


def test_degenerate_crops_stay_finite() -> None:
    flat = np.full((224, 224, 3), 0.5, np.float32)
    speck = np.zeros((224, 224, 3), np.float32)
    speck[110:113, 110:113] = 1.0
    line = np.zeros((224, 224, 3), np.float32)
    line[100, :] = 0.7
    huge = np.full((224, 224, 3), 1e30, np.float32)  # clipped to [0, 1]
    crops = np.stack([flat, speck, line, np.zeros_like(flat), np.ones_like(flat)])
    out = v5.content(crops)
    assert out.shape == (5, v2.DIM) and np.isfinite(out).all()
    assert np.allclose(np.linalg.norm(out, axis=1), 1.0)
    assert np.isfinite(v2.raw_features(np.clip(huge, 0, 1)[None], v5.STATS)).all()


def test_version_5_reads_version_3_worlds(monkeypatch) -> None:
    import json

    from ptovs.encoders import standin_version, synthetic_encoder

    monkeypatch.setattr(v2, "TEXT_PX", 96)
    plan = plan_scene("tiny", 3, 5)
    vocab = scene_vocabulary(plan.world, PRESETS["tiny"], [], 5)
    assert standin_version(vocab) == 5 and vocab["parts"]
    enc = synthetic_encoder(vocab)
    assert isinstance(enc, v5.SyntheticEncoderV5)
    p3 = plan_scene("tiny", 3, 3)
    assert json.dumps(p3.world.to_dict(), sort_keys=True) == json.dumps(
        plan.world.to_dict(), sort_keys=True
    )
    parts = sorted(enc._parts)
    t = enc.encode_texts([*parts, "building", "sky", "no such phrase"])
    assert t.shape == (len(parts) + 3, v2.DIM) and np.isfinite(t).all()
    e4 = v4.SyntheticEncoderV4({**vocab, "version": 4})
    assert not np.allclose(enc.encode_texts(parts[:1]), e4.encode_texts(parts[:1]))


def test_shipped_versions_are_untouched_by_the_options() -> None:
    """Versions 2 to 4 read with the options off: the same statistics as without
    the keys at all."""
    crops = np.stack([_striped_part(1.0), _striped_part(0.05, 24)])
    off = {**v2.PARAMS, "robust": 0, "core_texture": 0, "clip_ln": 0.0}
    assert np.array_equal(v2.raw_features(crops), v2.raw_features(crops, off))
    assert not np.array_equal(v2.raw_features(crops), v2.raw_features(crops, v5.STATS))
