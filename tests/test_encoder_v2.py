"""The stand-in for CLIP, version 2 (issue 41): how it fails, not only that it works."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ptovs.crop import prepare_crop
from ptovs.encoders import synthetic_v2 as v2
from ptovs.synthetic.generate import PRESETS, plan_scene, rerender, scene_vocabulary
from ptovs.synthetic.world import neutral_appearance

PRESET = "tiny"


@pytest.fixture(scope="module")
def world_crops():
    """A tiny world, its encoder (small text renders) and clean part crops."""
    plan = plan_scene(PRESET, 3)
    world = plan.world
    parts: dict[str, list[int]] = {}
    for p in world.parts:
        parts.setdefault(p.query, []).append(p.id)
    vocab = scene_vocabulary(world, PRESETS[PRESET], [])
    crops, labels = [], []
    for i, cam in enumerate(plan.cams[:6]):
        rec = {"image_id": i, **cam.to_dict()}
        v, _ = rerender(world, rec, "neutral", "none", seed=0)
        for k in np.unique(v.part_id[v.part_id >= 0]):
            m = v.part_id == k
            if m.sum() >= 40:
                crops.append(prepare_crop(v.image, m))
                labels.append(int(k))
    return world, {**vocab, "world": world.to_dict(), "parts": parts}, crops, labels


@pytest.fixture(scope="module")
def enc(world_crops, monkeypatch_module):
    monkeypatch_module.setattr(v2, "TEXT_PX", 96)  # small text renders: seconds
    return v2.SyntheticEncoderV2(world_crops[1])


@pytest.fixture(scope="module")
def monkeypatch_module():
    mp = pytest.MonkeyPatch()
    yield mp
    mp.undo()


def test_shapes_norms_and_determinism(world_crops, enc) -> None:
    crops = np.stack(world_crops[2][:5])
    a = enc.encode_images(crops)
    assert a.shape == (5, v2.DIM) and a.dtype == np.float32
    assert np.allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-5)
    # batch independent and repeatable, bit for bit
    b = np.concatenate([enc.encode_images(crops[k : k + 1]) for k in range(5)])
    assert np.array_equal(a, b)
    assert np.array_equal(a, enc.encode_images(crops))
    assert enc.encode_images(np.zeros((0, 224, 224, 3), np.float32)).shape == (0, 512)
    with pytest.raises(ValueError):
        enc.encode_images(crops[0])


def test_degenerate_crops_stay_finite(enc) -> None:
    flat = np.full((224, 224, 3), 0.5, np.float32)  # constant: no texture at all
    speck = np.zeros((224, 224, 3), np.float32)
    speck[110:113, 110:113] = 1.0  # nine pixels inside the mask
    bright = np.ones((224, 224, 3), np.float32)
    out = enc.encode_images(np.stack([flat, speck, bright]))
    assert np.isfinite(out).all()
    assert np.allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-5)


def test_text_side_is_a_category(world_crops, enc) -> None:
    world, _, crops, labels = world_crops
    phrases = sorted({p.query for p in world.parts})
    text = enc.encode_texts(phrases)
    assert text.shape == (len(phrases), v2.DIM)
    # the text side renders the part itself (instances x views x daylight)
    pid = world.parts[0].id
    n = len(v2.part_crops(world, pid))
    assert n % (len(v2.daylight_appearances()) * (v2.N_INSTANCES + 1)) == 0
    variants = v2.instances(world.parts[0].texture, pid)
    assert len({t.to_dict().__repr__() for t in variants}) == v2.N_INSTANCES + 1
    # the part's own phrase wins on most clean crops (closed set)
    idx = {p.id: phrases.index(p.query) for p in world.parts}
    pred = np.argmax(enc.encode_images(np.stack(crops)) @ text.T, axis=1)
    acc = float(np.mean([idx[k] == q for k, q in zip(labels, pred, strict=True)]))
    assert acc >= 1.0 / len(phrases) + 0.3, acc
    # generic phrases and unknown phrases still embed
    other = enc.encode_texts(["object", "sky", "no such phrase"])
    assert np.isfinite(other).all()


def test_blur_deficit_grows_with_blur(world_crops) -> None:
    crops = [c for c in world_crops[2] if (c.max(axis=2) > 0).mean() > 0.2][:6]
    assert crops

    def deficit(sigma: float) -> np.ndarray:
        out = []
        for c in crops:
            inside = c.max(axis=2) > 0
            b = cv2.GaussianBlur(c, (0, 0), sigma) if sigma else c
            b = np.clip(b, 1 / 255, 1).astype(np.float32)
            b[~inside] = 0
            out.append(b)
        return v2.blur_deficit(v2.raw_features(np.stack(out)))

    d0, d3, d6 = deficit(0.0), deficit(3.0), deficit(6.0)
    assert (d0 >= 0).all()
    assert d3.mean() > d0.mean() + 0.5
    assert d6.mean() >= d3.mean() - 0.5


def test_chroma_decoupling_sees_jpeg_and_noise(world_crops) -> None:
    """Chroma edges that leave the luminance edges (JPEG blocks, sensor noise)
    raise a crop's distortion; a colourless crop has none to decouple."""
    crops = [c for c in world_crops[2] if (c.max(axis=2) > 0).mean() > 0.2][:6]
    rng = np.random.default_rng(0)

    def measure(fn) -> np.ndarray:
        out = []
        for c in crops:
            inside = c.max(axis=2) > 0
            b = np.clip(fn(c), 1 / 255, 1).astype(np.float32)
            b[~inside] = 0
            out.append(b)
        return v2.chroma_decoupling(v2.raw_features(np.stack(out)))

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


def test_colour_is_a_weak_cue(world_crops, enc) -> None:
    """Greyscale moves a crop's embedding less than a strong blur does (CLIP's
    order), and the keyed perturbation differs between two lights of one crop."""
    crops = np.stack(world_crops[2][:8])
    grey = crops.mean(axis=3, keepdims=True).repeat(3, axis=3)
    grey[crops.max(axis=3) == 0] = 0
    blur = np.stack(
        [
            cv2.GaussianBlur(c, (0, 0), 6.0) * (c.max(axis=2, keepdims=True) > 0)
            for c in crops
        ]
    ).astype(np.float32)
    a = enc.encode_images(crops)
    d_grey = 1 - (a * enc.encode_images(grey)).sum(1)
    d_blur = 1 - (a * enc.encode_images(np.clip(blur, 0, 1))).sum(1)
    assert d_grey.mean() < d_blur.mean(), (d_grey.mean(), d_blur.mean())
    assert v2._key(crops[0]) == v2._key(crops[0].copy())
    assert v2._key(crops[0]) != v2._key(np.clip(crops[0] * 0.7, 0, 1))


def test_daylight_appearances_are_fixed() -> None:
    a, b = v2.daylight_appearances(), v2.daylight_appearances()
    assert a == b and a[0] == neutral_appearance() and len(a) == v2.N_DAYLIGHT
    assert all(x.sky != "night" and not x.hard for x in a)


def test_a_scene_written_for_version_2(tmp_path, monkeypatch) -> None:
    """`synth-scene --standin 2`: the vocabulary says so, every stage's encoder
    follows it, and extract-features keys its features by it."""
    import json
    from types import SimpleNamespace

    from ptovs.encoders import get_encoder, standin_version
    from ptovs.encoders.synthetic import SyntheticEncoder
    from ptovs.stages.extract_features import Config, build_encoder, standin_key
    from ptovs.synthetic import generate_scene

    monkeypatch.setattr(v2, "TEXT_PX", 96)
    scene = generate_scene(tmp_path, "tiny", 5, progress=False, standin=2)
    vocab = json.loads((scene / "synthetic" / "vocabulary.json").read_text())
    assert standin_version(vocab) == 2 and vocab["parts"] and "world" in vocab
    assert isinstance(SyntheticEncoder.from_scene(scene), v2.SyntheticEncoderV2)
    assert isinstance(build_encoder(Config(), True, scene), v2.SyntheticEncoderV2)
    ref = SimpleNamespace(load=lambda: SimpleNamespace(root=scene))
    assert standin_key(Config(), ref) == {"standin": "2"}
    assert standin_key(Config(encoder="openclip"), ref) == {}
    # a version 1 vocabulary (every scene made before issue 41) keys as before
    old = tmp_path / "old"
    (old / "synthetic").mkdir(parents=True)
    (old / "synthetic" / "vocabulary.json").write_text(json.dumps({"version": 1}))
    ref1 = SimpleNamespace(load=lambda: SimpleNamespace(root=old))
    assert standin_key(Config(), ref1) == {}
    assert not isinstance(get_encoder("synthetic"), v2.SyntheticEncoderV2)
    with pytest.raises(ValueError, match="stand-in version"):
        standin_version({"version": 7})


def test_version_3_building_is_the_average_word(world_crops, enc) -> None:
    """Version 3 (amendment 4): "building" embeds so that its cosine with any
    content is the mean of the part phrases' cosines (plus a fixed orthogonal
    part's chance cosine); everything else is version 2's, bit for bit."""
    world, vocab, crops, _ = world_crops
    e3 = v2.SyntheticEncoderV3({**vocab, "version": 3})
    parts = sorted(e3._parts)
    C = np.stack([v2.SyntheticEncoderV2._text_content(e3, p) for p in parts])
    m = C.mean(axis=0)
    b = e3._text_content("Building")
    assert np.linalg.norm(b) == pytest.approx(1.0, abs=1e-9)
    assert b @ m == pytest.approx(m @ m, abs=1e-9)  # the orthogonal part adds nothing
    cc = v2.content(np.stack(crops[:12]))
    gap = cc @ b - (cc @ C.T).mean(axis=1)  # n's chance cosine, sd about 0.04
    assert np.abs(gap).max() < 0.2, gap
    assert np.array_equal(e3._text_content("building"), b)  # fixed, not redrawn
    # the image side and every other phrase are version 2's
    x = np.stack(crops[:3])
    assert np.array_equal(e3.encode_images(x), enc.encode_images(x))
    same = ["object", "things", "scene", "sky", "background", parts[0]]
    assert np.array_equal(e3.encode_texts(same), enc.encode_texts(same))
    assert not np.allclose(
        e3.encode_texts(["building"]), enc.encode_texts(["building"])
    )
    # without the scene's parts there is nothing to average: version 2's phrase
    bare = v2.SyntheticEncoderV3({"version": 3})
    assert np.array_equal(bare.encode_texts(["building"]),
                          v2.SyntheticEncoderV2({"version": 2}).encode_texts(["building"]))  # fmt: skip


def test_version_3_is_dispatched_and_keyed(world_crops, tmp_path) -> None:
    import json
    from types import SimpleNamespace

    from ptovs.encoders import standin_version, synthetic_encoder
    from ptovs.stages.extract_features import Config, standin_key

    world = world_crops[0]
    vocab = scene_vocabulary(world, PRESETS[PRESET], [], 3)
    assert standin_version(vocab) == 3 and vocab["parts"] and "world" in vocab
    assert isinstance(synthetic_encoder(vocab), v2.SyntheticEncoderV3)
    (tmp_path / "synthetic").mkdir()
    (tmp_path / "synthetic" / "vocabulary.json").write_text(json.dumps(vocab))
    ref = SimpleNamespace(load=lambda: SimpleNamespace(root=tmp_path))
    assert standin_key(Config(), ref) == {"standin": "3"}
    with pytest.raises(ValueError, match="1, 2, 3, 4 or 5"):
        scene_vocabulary(world, PRESETS[PRESET], [], 6)


def test_screen_asks_only_to_beat_an_average_word() -> None:
    from ptovs.synthetic.screen import MARGIN, NEGATIVES, margins, passes

    own = np.array([0.30, 0.30, 0.30])
    neg = np.zeros((3, len(NEGATIVES)))
    neg[:, NEGATIVES.index("building")] = [0.28, 0.25, 0.32]
    neg[:, NEGATIVES.index("sky")] = 0.05
    plain = margins(own, neg)  # every negative by MARGIN (versions 1 and 2)
    assert np.allclose(plain, [0.02, 0.05, -0.02]) and not passes(plain)
    avg = margins(own, neg, ("building",))  # version 3: beat the average word
    building = np.array([0.28, 0.25, 0.32])
    assert np.allclose(avg, own - np.maximum(0.05, building - MARGIN))
    assert passes(avg)
    # a crop that loses to the average word by more than MARGIN still fails there
    neg[:, NEGATIVES.index("building")] = 0.30 + 1.5 * MARGIN
    assert (margins(own, neg, ("building",)) < 0).all()
    # any other negative keeps the full margin
    neg[:, NEGATIVES.index("building")] = 0.0
    neg[:, NEGATIVES.index("sky")] = 0.25
    assert np.allclose(margins(own, neg, ("building",)), 0.05)
