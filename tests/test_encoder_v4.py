"""The stand-in for CLIP, version 4 (issue 41): version 3 read through a learnt
invariance, with keyed flips."""

from __future__ import annotations

import numpy as np
import pytest

from ptovs.crop import prepare_crop
from ptovs.encoders import synthetic_v2 as v2
from ptovs.encoders import synthetic_v4 as v4
from ptovs.synthetic.generate import PRESETS, plan_scene, rerender, scene_vocabulary

PRESET = "tiny"


@pytest.fixture(scope="module")
def monkeypatch_module():
    mp = pytest.MonkeyPatch()
    yield mp
    mp.undo()


@pytest.fixture(scope="module")
def scene(monkeypatch_module):
    """A tiny world written for version 4, its encoder (small text renders), and
    part crops of 4 cameras under 4 lights: [(camera, part, light), crop]."""
    monkeypatch_module.setattr(v2, "TEXT_PX", 96)
    plan = plan_scene(PRESET, 3, 4)
    world = plan.world
    vocab = scene_vocabulary(world, PRESETS[PRESET], [], 4)
    lights = [v4.bank_lights()[j] for j in (0, 1, 4, 6)]  # neutral, day, bw, night
    items = []
    for i, cam in enumerate(plan.cams[:4]):
        rec = {"image_id": i, **cam.to_dict()}
        for j, app in enumerate(lights):
            v, _ = rerender(world, rec, app, "none", seed=0)
            for k in np.unique(v.part_id[v.part_id >= 0]):
                m = v.part_id == k
                if m.sum() >= 40:
                    items.append(((i, int(k), j), prepare_crop(v.image, m)))
    return plan, vocab, items


def test_shapes_norms_determinism_and_degenerate_crops(scene) -> None:
    enc = v4.SyntheticEncoderV4(scene[1])
    crops = np.stack([c for _, c in scene[2][:5]])
    a = enc.encode_images(crops)
    assert a.shape == (5, v2.DIM) and a.dtype == np.float32
    assert np.allclose(np.linalg.norm(a, axis=1), 1.0, atol=1e-5)
    b = np.concatenate([enc.encode_images(crops[k : k + 1]) for k in range(5)])
    assert np.array_equal(a, b)  # a crop's vector never depends on its batch
    assert enc.encode_images(np.zeros((0, 224, 224, 3), np.float32)).shape == (0, 512)
    flat = np.full((224, 224, 3), 0.5, np.float32)
    speck = np.zeros((224, 224, 3), np.float32)
    speck[110:113, 110:113] = 1.0
    out = enc.encode_images(np.stack([flat, speck, np.ones_like(flat)]))
    assert np.isfinite(out).all()


def test_content_is_the_documented_formula(scene) -> None:
    crops = np.stack([c for _, c in scene[2][:4]])
    raw = v2.raw_features(crops)
    keys = [v2._key(c) for c in crops]
    p = v4.projection()
    z, _ = v2.standardised(raw)
    y = (z - p["mean"]) @ p["directions"]
    amp = v4.PARAMS["noise"] * (1 + v2.distortion(raw))
    amp = amp + v4.PARAMS["flip_size"] * np.array(
        [np.random.default_rng([k, 1]).random() < v4.PARAMS["flip"] for k in keys]
    )
    e = np.stack([np.random.default_rng(k).standard_normal(v4.K) for k in keys])
    x = (y + p["scale"] * amp[:, None] * e / np.sqrt(v4.K)) @ v4._to_512()
    want = x / np.linalg.norm(x, axis=1, keepdims=True)
    assert np.allclose(v4.content(crops), want, atol=1e-12)


def test_flips_are_a_keyed_share() -> None:
    raw = np.tile(v2._bank()[:1], (4000, 1))  # one crop's statistics, many keys
    amp = v4.perturbation_size(raw, range(10_000, 14_000))
    base = v4.PARAMS["noise"] * (1 + v2.distortion(raw[:1]))[0]
    hit = amp > base + 1e-9
    assert np.allclose(amp[hit], base + v4.PARAMS["flip_size"])
    share = hit.mean()  # binomial: sd 0.0056 at 4000 draws
    assert abs(share - v4.PARAMS["flip"]) < 0.025, share
    again = v4.perturbation_size(raw, range(10_000, 14_000))
    assert np.array_equal(amp, again)


def test_fisher_finds_the_separating_directions() -> None:
    """Classes apart along one statistic, with a larger nuisance along another:
    the first direction is the separating one, the nuisance is ignored."""
    rng = np.random.default_rng(0)
    bank = v2._bank()
    mean, sd = bank.mean(0), np.maximum(bank.std(0), 1e-3)
    sep, nui = v2._offset("fine"), v2._offset("fine") + 1
    rows, cls = [], []
    for c in range(4):
        r = np.tile(mean, (200, 1)) + 0.05 * sd * rng.standard_normal((200, len(mean)))
        r[:, sep] += 0.5 * c * sd[sep]
        r[:, nui] += 2.0 * sd[nui] * rng.standard_normal(200)
        rows.append(r)
        cls += [c] * 200
    raw, cls = np.concatenate(rows), np.array(cls)
    mu, V, scale, ev = v4.fisher(raw, cls, k=3)
    assert ev[0] > 10 * ev[1] and scale > 0 and np.isfinite(V).all()
    y = (v2.standardised(raw)[0] - mu) @ V[:, 0]
    means = np.array([y[cls == c].mean() for c in range(4)])
    within = np.mean([y[cls == c].std() for c in range(4)])
    assert np.all(np.abs(np.diff(np.sort(means))) > 5 * within)  # classes apart
    assert abs(np.corrcoef(y, raw[:, nui])[0, 1]) < 0.2  # the nuisance ignored
    assert abs(np.corrcoef(y, raw[:, sep])[0, 1]) > 0.95
    # where the leading principal component follows the nuisance
    z = v2.standardised(raw)[0]
    pc = (z - z.mean(0)) @ np.linalg.svd(z - z.mean(0), full_matrices=False)[2][0]
    assert abs(np.corrcoef(pc, raw[:, nui])[0, 1]) > 0.9


def test_crops_of_a_part_cluster_more_than_in_version_3(scene) -> None:
    """The point of version 4: across cameras and lights, a part's crops lie
    closer together, relative to the distance between parts, than version 3's
    (perturbations off, so the statistics alone are compared)."""
    items = scene[2]
    lab = np.array([m[1] for m, _ in items])
    crops = np.stack([c for _, c in items])
    raw = v2.raw_features(crops)
    keys = [v2._key(c) for c in crops]
    quiet4 = {"noise": 0.0, "flip": 0.0, "flip_size": 0.0}
    f4 = v4.content_from(raw, keys, quiet4)
    z, _ = v2.standardised(raw)
    f3 = z @ v2._projection()[0]
    f3 = f3 / np.linalg.norm(f3, axis=1, keepdims=True)

    def ratio(x):
        means = {k: x[lab == k].mean(0) for k in np.unique(lab)}
        within = np.mean([((x[i] - means[k]) ** 2).sum() for i, k in enumerate(lab)])
        mu = x.mean(0)
        between = np.mean([((means[k] - mu) ** 2).sum() for k in lab])
        return within / between

    assert ratio(f4) < 0.7 * ratio(f3), (ratio(f4), ratio(f3))


def test_version_4_reads_version_3_worlds(scene) -> None:
    import json

    from ptovs.encoders import standin_version, synthetic_encoder

    plan, vocab, _ = scene
    assert standin_version(vocab) == 4 and vocab["parts"]
    enc = synthetic_encoder(vocab)
    assert isinstance(enc, v4.SyntheticEncoderV4)
    # the same world, textures and cameras as version 3's: the same photos
    p3 = plan_scene(PRESET, 3, 3)
    assert json.dumps(p3.world.to_dict(), sort_keys=True) == json.dumps(
        plan.world.to_dict(), sort_keys=True
    )
    # version 3's text rules on this image side: "building" is the average word
    parts = sorted(enc._parts)
    C = np.stack([v2.SyntheticEncoderV2._text_content(enc, p) for p in parts])
    b = enc._text_content("building")
    m = C.mean(axis=0)
    assert b @ m == pytest.approx(m @ m, abs=1e-9)
    t = enc.encode_texts([*parts, "sky", "object", "no such phrase"])
    assert np.isfinite(t).all()
    # and its own part content, not version 3's
    e3 = v2.SyntheticEncoderV3({**vocab, "version": 3})
    assert not np.allclose(enc.encode_texts(parts[:1]), e3.encode_texts(parts[:1]))
