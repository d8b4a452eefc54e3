"""The stand-in for CLIP, version 5: how it fails, not only that it works
(docs/standin.md), and how scenes of retired versions are refused."""

from __future__ import annotations

import importlib.util
import json
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from ptovs.crop import prepare_crop
from ptovs.encoders import standin_stats as st
from ptovs.encoders import standin_text as tx
from ptovs.encoders import synthetic_v5 as v5
from ptovs.synthetic.generate import PRESETS, plan_scene, rerender, scene_vocabulary
from ptovs.synthetic.world import neutral_appearance

PRESET = "tiny"


@pytest.fixture(scope="module")
def monkeypatch_module():
    mp = pytest.MonkeyPatch()
    yield mp
    mp.undo()


@pytest.fixture(scope="module")
def scene(monkeypatch_module):
    """A tiny world, its version-5 vocabulary and part crops of 4 cameras under 3
    lights: [((camera, part, light), crop)] (small text renders: seconds)."""
    monkeypatch_module.setattr(tx, "TEXT_PX", 96)
    plan = plan_scene(PRESET, 3)
    world = plan.world
    vocab = scene_vocabulary(world, PRESETS[PRESET], [], 5)
    n = neutral_appearance()
    lights = [n, replace(n, filter="bw"), replace(n, filter="sepia")]
    items = []
    for i, cam in enumerate(plan.cams[:4]):
        rec = {"image_id": i, **cam.to_dict()}
        for j, app in enumerate(lights):
            v, _ = rerender(world, rec, app, "none", seed=0)
            for k in np.unique(v.part_id[v.part_id >= 0]):
                m = v.part_id == k
                if m.sum() >= 40:
                    items.append(((i, int(k), j), prepare_crop(v.image, m)))
    return world, vocab, items


def _clean(scene) -> list[np.ndarray]:
    crops = [c for (_, _, j), c in scene[2] if j == 0]
    return [c for c in crops if (c.max(axis=2) > 0).mean() > 0.2][:6]


def _tool():
    path = Path(__file__).resolve().parents[1] / "tools" / "standin_reference.py"
    spec = importlib.util.spec_from_file_location("standin_reference", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


_striped_part = _tool().striped_part  # a striped disc cut as a segment crop


def test_projection_is_verified_on_read(monkeypatch) -> None:
    p = v5.projection()
    assert p["directions"].shape == (st.N_FEATURES, v5.K)
    assert np.isfinite(p["directions"]).all() and p["scale"] > 0
    v5.projection.cache_clear()
    monkeypatch.setattr(v5, "PROJECTION_SHA256", "0" * 64)
    try:
        with pytest.raises(RuntimeError, match=f"{v5.PROJECTION_FILE} is damaged"):
            v5.projection()
    finally:
        v5.projection.cache_clear()


def test_texture_statistics_ignore_contrast_unlike_the_plain_reading() -> None:
    """A part blended towards grey (in floating point, so no grey level is lost)
    keeps version 5's texture statistics, where the plain reading (options off)
    reads the crop's dark ring instead."""
    f, c = st._offset("fine"), st._offset("coarse")
    texture = np.r_[f : c + (len(st.WAVELENGTHS) - st.N_FINE) * len(st.THETAS)]
    crops = np.stack([_striped_part(1.0), _striped_part(0.05)])
    new = st.raw_features(crops, v5.STATS)[:, texture]
    old = st.raw_features(crops)[:, texture]
    d_new = np.abs(new[0] - new[1]).max()
    d_old = np.abs(old[0] - old[1]).max()
    assert d_new < 0.05, d_new
    assert d_old > 4 * d_new, (d_old, d_new)
    # and the blur detector does not take the faint crop for a blurred one
    dist = st.distortion(st.raw_features(crops, v5.STATS), v5.STATS)
    assert dist[1] == pytest.approx(dist[0], abs=0.1)
    assert st.distortion(st.raw_features(crops))[1] > dist[1] + 0.5


def test_the_plain_reading_is_untouched_by_options_set_off() -> None:
    crops = np.stack([_striped_part(1.0), _striped_part(0.05, 24)])
    off = {**st.PARAMS, "robust": 0, "core_texture": 0, "clip_ln": 0.0}
    assert np.array_equal(st.raw_features(crops), st.raw_features(crops, off))
    assert not np.array_equal(st.raw_features(crops), v5.raw_features(crops))


def test_faintness_is_the_documented_formula() -> None:
    lum = st._offset("lum") + 1
    raw = np.zeros((4, st.N_FEATURES + st.N_AUX))
    t4, k4 = v5.PARAMS["t4"], v5.PARAMS["k4"]
    raw[:, lum] = [2 * t4, t4, t4 / 4, 0.0]  # the last: below one grey level
    want = [0.0, 0.0, 2 * k4, k4 * np.log2(t4 * 255.0)]
    assert np.allclose(v5.faintness(raw), want)
    # the 5-95 % range the robust statistics put in the "lum" group
    stats = v5.raw_features(_striped_part(0.05)[None])
    assert 0.0 < stats[0, lum] < 0.05


def test_content_is_the_documented_formula_and_batch_free() -> None:
    crops = np.stack([_striped_part(c, s, k) for k, (c, s) in
                      enumerate([(1.0, 40), (0.05, 40), (0.03, 24), (1.0, 90)])])  # fmt: skip
    raw = st.raw_features(crops, v5.STATS)
    keys = [st._key(c) for c in crops]
    p = v5.projection()
    z, _ = st.standardised(raw, v5.STATS)
    y = (z - p["mean"]) @ p["directions"]
    P = v5.PARAMS
    amp = P["noise"] * (1 + st.distortion(raw, v5.STATS) + v5.faintness(raw, P))
    amp = amp + P["flip_size"] * np.array(
        [np.random.default_rng([k, 1]).random() < P["flip"] for k in keys]
    )
    e = np.stack([np.random.default_rng(k).standard_normal(v5.K) for k in keys])
    x = (y + p["scale"] * amp[:, None] * e / np.sqrt(v5.K)) @ v5._to_512()
    want = x / np.linalg.norm(x, axis=1, keepdims=True)
    got = v5.content(crops)
    assert np.allclose(got, want, atol=1e-12)
    one = np.concatenate([v5.content(crops[k : k + 1]) for k in range(len(crops))])
    assert np.array_equal(got, one)  # a crop's vector never depends on its batch


def test_flips_are_a_keyed_share() -> None:
    raw = np.tile(st._bank_for(tuple(sorted(v5.STATS.items())))[:1], (4000, 1))
    amp = v5.perturbation_size(raw, range(10_000, 14_000))
    base = v5.PARAMS["noise"] * (1 + st.distortion(raw[:1], v5.STATS)
                                 + v5.faintness(raw[:1]))[0]  # fmt: skip
    hit = amp > base + 1e-9
    assert np.allclose(amp[hit], base + v5.PARAMS["flip_size"])
    share = hit.mean()  # binomial: sd 0.0056 at 4000 draws
    assert abs(share - v5.PARAMS["flip"]) < 0.025, share
    assert np.array_equal(amp, v5.perturbation_size(raw, range(10_000, 14_000)))


def test_degenerate_crops_stay_finite() -> None:
    flat = np.full((224, 224, 3), 0.5, np.float32)
    speck = np.zeros((224, 224, 3), np.float32)
    speck[110:113, 110:113] = 1.0
    line = np.zeros((224, 224, 3), np.float32)
    line[100, :] = 0.7
    huge = np.full((224, 224, 3), 1e30, np.float32)  # clipped to [0, 1]
    crops = np.stack([flat, speck, line, np.zeros_like(flat), np.ones_like(flat)])
    out = v5.content(crops)
    assert out.shape == (5, st.DIM) and np.isfinite(out).all()
    assert np.allclose(np.linalg.norm(out, axis=1), 1.0)
    assert np.isfinite(v5.raw_features(np.clip(huge, 0, 1)[None])).all()
    enc = v5.SyntheticEncoderV5()
    assert enc.encode_images(np.zeros((0, 224, 224, 3), np.float32)).shape == (0, 512)


def test_blur_deficit_grows_with_blur(scene) -> None:
    crops = _clean(scene)
    assert crops

    def deficit(sigma: float, stats: dict | None) -> np.ndarray:
        out = []
        for c in crops:
            inside = c.max(axis=2) > 0
            b = cv2.GaussianBlur(c, (0, 0), sigma) if sigma else c
            b = np.clip(b, 1 / 255, 1).astype(np.float32)
            b[~inside] = 0
            out.append(b)
        return st.blur_deficit(st.raw_features(np.stack(out), stats), stats)

    for stats in (None, v5.STATS):
        d0, d3, d6 = deficit(0.0, stats), deficit(3.0, stats), deficit(6.0, stats)
        assert (d0 >= 0).all()
        assert d3.mean() > d0.mean() + 0.5
        assert d6.mean() >= d3.mean() - 0.5


def test_chroma_decoupling_sees_jpeg_and_noise(scene) -> None:
    """Chroma edges that leave the luminance edges (JPEG blocks, sensor noise)
    raise a crop's distortion; a colourless crop has none to decouple."""
    crops = _clean(scene)
    rng = np.random.default_rng(0)

    def measure(fn) -> np.ndarray:
        out = []
        for c in crops:
            inside = c.max(axis=2) > 0
            b = np.clip(fn(c), 1 / 255, 1).astype(np.float32)
            b[~inside] = 0
            out.append(b)
        return st.chroma_decoupling(v5.raw_features(np.stack(out)), v5.STATS)

    def jpeg(c: np.ndarray) -> np.ndarray:
        u8 = np.round(c * 255).astype(np.uint8)[..., ::-1]
        ok, buf = cv2.imencode(".jpg", u8, [cv2.IMWRITE_JPEG_QUALITY, 7])
        assert ok
        return cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1] / 255.0

    clean = measure(lambda c: c)
    noisy = measure(lambda c: c + rng.uniform(-0.2, 0.2, c.shape))
    blocky = measure(jpeg)
    grey = measure(lambda c: np.repeat(c.mean(axis=2, keepdims=True), 3, axis=2))
    assert (clean >= 0).all() and np.isfinite(clean).all()
    assert noisy.mean() > clean.mean() + 1.0
    assert blocky.mean() > clean.mean() + 1.0
    assert np.allclose(grey, 0.0)
    c0 = crops[0]
    assert st._key(c0) == st._key(c0.copy())
    assert st._key(c0) != st._key(np.clip(c0 * 0.7, 0, 1))


def test_colour_is_a_weak_cue(scene) -> None:
    """Greyscale moves a crop's embedding less than a strong blur does (CLIP's
    order)."""
    crops = np.stack([c for (_, _, j), c in scene[2] if j == 0][:8])
    grey = crops.mean(axis=3, keepdims=True).repeat(3, axis=3)
    grey[crops.max(axis=3) == 0] = 0
    blur = np.stack(
        [
            cv2.GaussianBlur(c, (0, 0), 6.0) * (c.max(axis=2, keepdims=True) > 0)
            for c in crops
        ]
    ).astype(np.float32)
    enc = v5.SyntheticEncoderV5()
    a = enc.encode_images(crops)
    d_grey = 1 - (a * enc.encode_images(grey)).sum(1)
    d_blur = 1 - (a * enc.encode_images(np.clip(blur, 0, 1))).sum(1)
    assert d_grey.mean() < d_blur.mean(), (d_grey.mean(), d_blur.mean())


def test_crops_of_a_part_cluster_more_than_in_the_plain_reading(scene) -> None:
    """The point of the learnt projection: across cameras and lights, a part's
    crops lie closer together, relative to the distance between parts, than in
    the plain reading (perturbations off: the statistics alone are compared)."""
    items = scene[2]
    lab = np.array([m[1] for m, _ in items])
    crops = np.stack([c for _, c in items])
    raw = v5.raw_features(crops)
    keys = [st._key(c) for c in crops]
    quiet = {**v5.PARAMS, "noise": 0.0, "flip": 0.0, "flip_size": 0.0}
    f5 = v5.content_from(raw, keys, quiet)
    z, _ = st.standardised(st.raw_features(crops))
    f0 = z @ st._projection()[0]
    f0 = f0 / np.linalg.norm(f0, axis=1, keepdims=True)

    def ratio(x):
        means = {k: x[lab == k].mean(0) for k in np.unique(lab)}
        within = np.mean([((x[i] - means[k]) ** 2).sum() for i, k in enumerate(lab)])
        mu = x.mean(0)
        between = np.mean([((means[k] - mu) ** 2).sum() for k in lab])
        return within / between

    assert ratio(f5) < 0.7 * ratio(f0), (ratio(f5), ratio(f0))


def test_daylight_appearances_are_fixed() -> None:
    a, b = tx.daylight_appearances(), tx.daylight_appearances()
    assert a == b and a[0] == neutral_appearance() and len(a) == tx.N_DAYLIGHT
    assert all(x.sky != "night" and not x.hard for x in a)


def test_text_side_is_a_category_and_building_the_average_word(scene) -> None:
    from ptovs.encoders import standin_version, synthetic_encoder

    world, vocab, items = scene
    assert standin_version(vocab) == 5 and vocab["parts"] and "world" in vocab
    enc = synthetic_encoder(vocab)
    assert isinstance(enc, v5.SyntheticEncoderV5) and enc.name == "synthetic-v5"
    # the text side renders the part itself (instances x views x daylight)
    pid = world.parts[0].id
    n = len(tx.part_crops(world, pid))
    assert n % (len(tx.daylight_appearances()) * (tx.N_INSTANCES + 1)) == 0
    variants = tx.instances(world.parts[0].texture, pid)
    assert len({t.to_dict().__repr__() for t in variants}) == tx.N_INSTANCES + 1
    # "building": its cosine with any content is the mean of the part phrases'
    parts = sorted(enc._parts)
    C = np.stack([enc._phrase_content(p) for p in parts])
    m = C.mean(axis=0)
    b = enc._text_content("Building")
    assert np.linalg.norm(b) == pytest.approx(1.0, abs=1e-9)
    assert b @ m == pytest.approx(m @ m, abs=1e-9)  # the orthogonal part adds nothing
    cc = v5.content(np.stack([c for _, c in items[:12]]))
    gap = cc @ b - (cc @ C.T).mean(axis=1)  # n's chance cosine, sd about 0.04
    assert np.abs(gap).max() < 0.2, gap
    assert np.array_equal(enc._text_content("building"), b)  # fixed, not redrawn
    t = enc.encode_texts([*parts, "sky", "object", "no such phrase"])
    assert t.shape == (len(parts) + 3, st.DIM) and np.isfinite(t).all()
    # without the scene's parts there is nothing to average
    bare = v5.SyntheticEncoderV5({"version": 5})
    assert np.isfinite(bare.encode_texts(["building"])).all()
    # the screen's reading: the same text rules over the plain statistics
    screen = tx.CategoryEncoder(vocab)
    assert not np.allclose(enc.encode_texts(parts[:1]), screen.encode_texts(parts[:1]))


def test_screen_asks_only_to_beat_an_average_word() -> None:
    from ptovs.synthetic.screen import MARGIN, NEGATIVES, margins, passes

    own = np.array([0.30, 0.30, 0.30])
    neg = np.zeros((3, len(NEGATIVES)))
    neg[:, NEGATIVES.index("building")] = [0.28, 0.25, 0.32]
    neg[:, NEGATIVES.index("sky")] = 0.05
    plain = margins(own, neg)  # every negative by MARGIN (version 1)
    assert np.allclose(plain, [0.02, 0.05, -0.02]) and not passes(plain)
    avg = margins(own, neg, ("building",))  # version 5: beat the average word
    building = np.array([0.28, 0.25, 0.32])
    assert np.allclose(avg, own - np.maximum(0.05, building - MARGIN))
    assert passes(avg)
    # a crop that loses to the average word by more than MARGIN still fails there
    neg[:, NEGATIVES.index("building")] = 0.30 + 1.5 * MARGIN
    assert (margins(own, neg, ("building",)) < 0).all()


def _scene_with(tmp_path, vocab: dict):
    (tmp_path / "synthetic").mkdir(parents=True, exist_ok=True)
    path = tmp_path / "synthetic" / "vocabulary.json"
    path.write_text(json.dumps(vocab))
    return path, SimpleNamespace(load=lambda: SimpleNamespace(root=tmp_path))


def test_version_5_is_dispatched_and_keyed(scene, tmp_path) -> None:
    from ptovs.encoders import get_encoder, scene_encoder
    from ptovs.encoders.synthetic import SyntheticEncoder
    from ptovs.stages.extract_features import Config, build_encoder, extra_key

    _, ref = _scene_with(tmp_path, scene[1])
    assert isinstance(scene_encoder(tmp_path), v5.SyntheticEncoderV5)
    assert isinstance(build_encoder(Config(), True, tmp_path), v5.SyntheticEncoderV5)
    assert extra_key(Config(), ref) == {"standin": "5"}
    assert extra_key(Config(encoder="openclip"), ref) == {}
    # a version 1 vocabulary keys as it always did
    _, ref1 = _scene_with(tmp_path / "old", {"version": 1})
    assert extra_key(Config(), ref1) == {}
    # SAM's generator version keys SAM's and SAM 2.1's features, and only theirs
    assert extra_key(Config(segmenter="sam2"), ref1) == {"sam_generator": "2"}
    assert extra_key(Config(segmenter="sam", encoder="openclip"), ref) == {
        "sam_generator": "2"
    }
    assert type(get_encoder("synthetic")) is SyntheticEncoder


@pytest.mark.parametrize("version", [2, 3, 4])
def test_retired_versions_fail_naming_the_file_and_the_fix(
    scene, tmp_path, version
) -> None:
    from ptovs.encoders import scene_encoder, standin_version
    from ptovs.stages.extract_features import Config, extra_key

    path, ref = _scene_with(tmp_path, {"version": version, "phrases": {}})
    for call in (lambda: scene_encoder(tmp_path), lambda: extra_key(Config(), ref)):
        with pytest.raises(ValueError) as err:
            call()
        msg = str(err.value)
        assert "\n" not in msg and str(path) in msg
        assert f"stand-in version {version}" in msg and "--standin 1" in msg
        assert "--standin 5" in msg
    with pytest.raises(ValueError, match="unknown stand-in version 7"):
        standin_version({"version": 7})
    with pytest.raises(ValueError, match=f"stand-in version {version} is not"):
        plan_scene(PRESET, 0, version)
    with pytest.raises(ValueError, match="1 or 5"):
        scene_vocabulary(scene[0], PRESETS[PRESET], [], version)


@pytest.mark.parametrize("version", ["2", "3", "4"])
def test_synth_scene_refuses_retired_versions(tmp_path, version) -> None:
    from click.testing import CliRunner

    from ptovs.cli import main

    res = CliRunner().invoke(main, ["synth-scene", str(tmp_path), "--standin", version])
    assert res.exit_code != 0
    assert f"stand-in version {version} is not available" in res.output
    assert "--standin 1 or --standin 5" in res.output
    assert not any(tmp_path.iterdir())
