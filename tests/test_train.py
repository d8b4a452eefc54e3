"""train-ae and train-male (issue: train): the autoencoder, MALE-GS, the baselines."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from conftest import RECON, copy_work, run_cli
from ptovs.artifacts import Artifact, read_json_dataset
from ptovs.cli import main
from ptovs.field import language as lang
from ptovs.field.language import load_codes
from ptovs.field.lift import feature_lift_sums
from ptovs.memory import release
from ptovs.nets.autoencoder import LanguageAE, load_autoencoder
from ptovs.raster import blend_weights, render
from ptovs.stages import train_ae as tae
from test_raster import make_camera, random_scene, stack_at

F64 = torch.float64


@pytest.fixture(scope="module")
def trained(tmp_path_factory, tiny_scene_dir, trained_work):
    """tiny: the extracted chain, then `ptovs train` (default variant)."""
    work = copy_work(trained_work[0], tmp_path_factory.mktemp("train") / "work")
    return work, tiny_scene_dir, trained_work[1]


def _art(work: Path, stage: str) -> Artifact:
    (path,) = sorted((work / "tiny_s0" / stage).glob("*.h5"))
    return Artifact(path)


def _path_of(out: str, stage: str) -> Path:
    line = next(x for x in out.splitlines() if x.startswith(stage + " "))
    return Path(line.split()[-1])


# ------------------------------------------------------------------ train-ae --


def test_train_runs_both_stages_then_caches(trained):
    work, data, out = trained
    assert "train-ae             done" in out and "train-male           done" in out
    again = run_cli(work, "train", "--data", str(data))
    assert again.count("cached") == 6, again  # the whole chain, nothing rerun


def test_ae_codes_decode_close_to_heldout_features(trained):
    work, _, _ = trained
    with _art(work, "train-ae") as ae_art, _art(work, "extract-features") as feats:
        metrics = read_json_dataset(ae_art.root()["metrics_json"])
        assert metrics["heldout"] > 0 and metrics["heldout_cos"] >= 0.85
        model = load_autoencoder(ae_art)
        cos = []
        for name in feats.names():
            x = torch.from_numpy(feats[name]["feat_orig"].astype(np.float32))
            with torch.no_grad():
                h = model.encode(x)
                cos.append(torch.nn.functional.cosine_similarity(model.decode(h), x))
            stored = ae_art[name]
            # every table is encoded (renders too), to unit codes equal to encode(x)
            assert {"code_orig", "code_nov1", "code_self"} <= set(stored)
            np.testing.assert_allclose(stored["code_orig"], h.numpy(), atol=1e-5)
            np.testing.assert_allclose(
                np.linalg.norm(stored["code_nov1"], axis=1), 1.0, atol=1e-5
            )
        assert float(torch.cat(cos).mean()) >= 0.85


def test_segment_uncertainty_and_tau_exclusion_exactly():
    # two levels over a 2x3 image; rows 0-1 on level 0, rows 2-3 on level 1
    seg = np.array(
        [[[0, 0, 1], [1, 1, -1]], [[2, 3, 3], [3, 3, 3]]], np.int16
    )  # row 0: px (0,0),(0,1); row 1: (0,2),(1,0),(1,1); row 2: (0,0); row 3: rest
    u = np.array([[0.0, 0.2, 1.0], [0.95, 0.9, 0.5]], np.float32)
    ubar = tae.segment_uncertainty(seg, 5, u)
    want = [0.1, (1.0 + 0.95 + 0.9) / 3, 0.0, (0.2 + 1.0 + 0.95 + 0.9 + 0.5) / 5, 0.0]
    np.testing.assert_allclose(ubar, want, rtol=1e-6)  # row 4 covers nothing: 0
    keep, p = tae.sample_weights(seg, 5, u, tae.Config(tau_u=0.9))
    assert keep.tolist() == [True, False, True, True, True]  # 0.95 > 0.9 only
    np.testing.assert_allclose(p, 1.0 - np.asarray(want), rtol=1e-6)
    keep, _ = tae.sample_weights(seg, 5, u, tae.Config(tau_u=1.0))
    assert keep.all()  # the code's behaviour: nothing excluded
    _, p = tae.sample_weights(seg, 5, u, tae.Config(weighting="none"))
    assert (p == 1).all()


def test_collected_training_set_matches_a_direct_count(trained, tmp_path):
    work, _, _ = trained
    with _art(work, "extract-features") as feats, _art(work, "uncertainty") as unc:
        cfg = tae.Config(tau_u=0.5)  # low enough to exclude some segments on tiny
        s = tae.collect_samples(feats, unc, cfg, tmp_path)
        rows, weights = [], []
        for name in feats.names():
            seg, table = feats[name]["seg_orig"], feats[name]["feat_orig"]
            u = unc[name]["u_t"].astype(np.float64)
            for r in range(len(table)):
                px = (seg == r).any(0)
                ub = u[px].mean()  # each row lives on one level only
                if ub <= 0.5:
                    rows.append(table[r])
                    weights.append(1.0 - ub)
        assert 0 < s.stats["excluded_tau_u"] < s.stats["segments"]
        assert len(s.train) + len(s.heldout) == len(rows)
        np.testing.assert_array_equal(np.asarray(s.rows), np.asarray(rows))
        np.testing.assert_allclose(s.weights, weights, rtol=1e-5)
        assert not set(s.train) & set(s.heldout)


def test_ae_objective_variants():
    torch.manual_seed(0)
    model = LanguageAE(16, (8, 4, 3), (6, 16))
    x = torch.nn.functional.normalize(torch.randn(10, 16), dim=1)
    one = torch.ones(10)
    base = tae.objective(model, x, one, tae.Config(weighting="none"))
    for w in ("input_and_target", "loss_only"):  # p = 1: all forms agree
        assert torch.allclose(
            tae.objective(model, x, one, tae.Config(weighting=w)), base
        )
    p = torch.linspace(0.1, 1.0, 10)
    a = tae.objective(model, x, p, tae.Config(weighting="input_and_target"))
    b = tae.objective(model, x, p, tae.Config(weighting="loss_only"))
    assert torch.isfinite(a) and torch.isfinite(b) and not torch.allclose(a, b)
    c = tae.objective(model, x, p, tae.Config(cos_axis="batch"))
    assert torch.isfinite(c) and not torch.allclose(a, c)
    back = LanguageAE.from_state(model.state_dict())
    model.eval()
    assert torch.allclose(back(x), model(x))


# --------------------------------------------------------------- train-male --


def _toy_view(n=40, w=24, h=18, seed=0, levels=2, apps=3, u_t=None, u_a=None):
    """Random Gaussians, a camera, and segment maps / codes for every slot."""
    g, cam, _ = random_scene(n, w, h, seed=seed)
    rng = np.random.default_rng(seed)
    segs, codes = [], []
    for _ in range(apps):
        k = 5
        seg = np.stack([rng.integers(0, k, (h, w)) + lv * k for lv in range(levels)])
        seg[:, :2, :3] = -1  # a corner without segments
        c = rng.normal(size=(k * levels, 3)).astype(np.float32)
        segs.append(seg.astype(np.int16))
        codes.append(c / np.linalg.norm(c, axis=1, keepdims=True))
    bw = blend_weights(g, cam)
    return g, cam, bw, segs, codes, u_t, u_a


def _dense_reference_loss(f64, bw, segs, codes, u_t, u_a, variant):
    """The loss of docs/method.md §7 on dense float64 images (no compaction)."""
    n_lv, h, w = segs[0].shape
    hw = h * w
    wmat = bw.W.to_dense().double()  # [HW, P]
    fn = lang.normalize_chunks(f64)
    r = (wmat @ fn).reshape(hw, n_lv, len(segs), 3)
    ut = (
        torch.zeros(hw, dtype=torch.float64)
        if u_t is None
        else torch.from_numpy(u_t.ravel()).double()
    )
    ua = (
        torch.zeros(hw, dtype=torch.float64)
        if u_a is None
        else torch.from_numpy(u_a.ravel()).double()
    )
    total = 0.0
    for a, (seg, code) in enumerate(zip(segs, codes, strict=True)):
        for lv in range(n_lv):
            s = torch.from_numpy(seg[lv].ravel().astype(np.int64))
            valid = (s >= 0).double()
            gt = torch.from_numpy(code).double()[s.clamp_min(0)] * valid[:, None]
            if variant == "paper" or a == 0:
                m, denom = valid * (1 - ua) * (1 - ut), hw * 3
            else:
                m, denom = valid * (1 - ut), hw * 3 * (len(segs) - 1)
            total = total + ((r[:, lv, a] - gt).abs() * m[:, None]).sum() / denom
    return total


@pytest.mark.parametrize("variant", ["paper", "code"])
def test_male_loss_and_gradient_match_float64_reference(variant):
    rng = np.random.default_rng(3)
    u_t = rng.random((18, 24)).astype(np.float32)
    u_a = rng.random((18, 24)).astype(np.float32)
    g, cam, bw, segs, codes, _, _ = _toy_view(u_t=u_t, u_a=u_a)
    view = lang.prepare_view(bw, segs, codes, u_t, u_a, variant)
    n_ch = 2 * 3 * 3
    f = torch.randn(len(g), n_ch, generator=torch.Generator().manual_seed(1))
    f32 = f.clone().requires_grad_(True)
    scale = lang.slot_scale(18 * 24, 2, 3, variant)
    per = lang.train_step(f32, view, scale)
    f64 = f.double().requires_grad_(True)
    ref = _dense_reference_loss(f64, bw, segs, codes, u_t, u_a, variant)
    ref.backward()
    assert float(per.sum().detach()) == pytest.approx(float(ref), rel=1e-5)
    torch.testing.assert_close(f32.grad.double(), f64.grad, rtol=1e-4, atol=1e-6)


def test_sparse_fast_path_trains_like_render():
    g, cam, bw, segs, codes, _, _ = _toy_view(n=60, seed=5)
    store = lang.ViewStore(1 << 30, None)
    store.add(lang.prepare_view(bw, segs, codes, None, None))
    cfg = dict(iterations=6, stop="fixed", init="data")
    n_ch = 2 * 3 * 3
    fast, _, _ = lang.train_male(store, n_ch, lang.MaleConfig(**cfg))
    slow, _, _ = lang.train_male(
        store, n_ch, lang.MaleConfig(renderer="raster", **cfg), g, [cam]
    )
    torch.testing.assert_close(fast, slow, rtol=0, atol=1e-4)
    # and one step's gradients agree exactly enough to be the same computation
    f = torch.randn(len(g), n_ch)
    a, b = f.clone().requires_grad_(True), f.clone().requires_grad_(True)
    scale = lang.slot_scale(18 * 24, 2, 3, "paper")
    lang.train_step(a, store[0], scale)
    lang.train_step(b, store[0], scale, "raster", g, cam)
    torch.testing.assert_close(a.grad, b.grad, rtol=1e-4, atol=1e-6)


def test_masked_pixels_get_no_gradient():
    u_t = np.zeros((18, 24), np.float32)
    u_t[:, :12] = 1.0  # the left half is transient: weight 0
    g, cam, bw, segs, codes, _, _ = _toy_view(n=60, seed=7, u_t=u_t)
    n_ch = 2 * 3 * 3
    f = torch.randn(len(g), n_ch, generator=torch.Generator().manual_seed(2))
    scale = lang.slot_scale(18 * 24, 2, 3, "paper")

    def grad(segs_):
        x = f.clone().requires_grad_(True)
        lang.train_step(x, lang.prepare_view(bw, segs_, codes, u_t, None), scale)
        return x.grad

    base = grad(segs)
    other = [s.copy() for s in segs]
    for s in other:  # new targets only where the mask is zero
        s[:, :, :12] = (s[:, :, :12] + 1) % 5
    torch.testing.assert_close(grad(other), base, rtol=0, atol=0)
    # Gaussians drawn only on masked pixels get exactly zero gradient
    w = bw.W.to_dense()
    cols_right = w.reshape(18, 24, -1)[:, 12:].abs().sum((0, 1))
    only_left = (cols_right == 0) & (w.abs().sum(0) > 0)
    assert only_left.any()
    assert (base[only_left] == 0).all()


def test_hard_cases_give_no_nan():
    n_ch = 2 * 3 * 3
    # all-invalid view (no segment anywhere) and constant uncertainty maps
    g, cam, bw, segs, codes, _, _ = _toy_view(seed=9)
    empty = [np.full_like(s, -1) for s in segs]
    for u in (np.zeros((18, 24), np.float32), np.ones((18, 24), np.float32)):
        store = lang.ViewStore(1 << 30, None)
        store.add(lang.prepare_view(bw, empty, codes, u, u))
        store.add(lang.prepare_view(bw, segs, codes, u, u))
        for init in ("zero", "data"):
            f, m, hist = lang.train_male(
                store, n_ch, lang.MaleConfig(iterations=8, stop="fixed", init=init)
            )
            assert torch.isfinite(f).all() and np.isfinite(hist["epoch_loss"]).all()
            total, per = lang.evaluate_loss(f, store, "paper")
            assert np.isfinite(total) and np.isfinite(per).all()
    # zero codes: the first gradient through x/(|x|+1e-9) is huge but finite
    f = torch.zeros(len(g), n_ch, requires_grad=True)
    view = lang.prepare_view(bw, segs, codes, None, None)
    lang.train_step(f, view, lang.slot_scale(18 * 24, 2, 3, "paper"))
    assert torch.isfinite(f.grad).all() and f.grad.abs().max() > 1e6
    # no Gaussian in view: nothing covered, constant loss, zero gradient
    far = g.__class__(
        g.means + torch.tensor([0.0, 0.0, -100.0]), g.quats, g.scales, g.opacities
    )
    bw_far = blend_weights(far, cam)
    v = lang.prepare_view(bw_far, segs, codes, None, None)
    assert len(v.rows) == 0 and float(v.const.sum()) > 0
    x = torch.randn(len(g), n_ch, requires_grad=True)
    per = lang.train_step(x, v, lang.slot_scale(18 * 24, 2, 3, "paper"))
    assert torch.equal(per, v.const) and (x.grad == 0).all()


def test_view_store_sample_keeps_what_fits_and_never_spills(tmp_path):
    """The lift's store: views past the budget are dropped (counted), not written."""
    _, _, bw, segs, codes, _, _ = _toy_view(seed=4)
    v = lang.prepare_view(bw, segs, codes, None, None)
    store = lang.ViewStore(2 * v.nbytes + 10, tmp_path / "spill", sample=True)
    for _ in range(5):
        store.add(v)
    assert len(store) == 2 and store.dropped == 3 and store.full
    assert store.ram_bytes == 2 * v.nbytes and store.disk_bytes == 0
    assert not (tmp_path / "spill").exists()
    assert not lang.ViewStore(1 << 30, None).full  # a store that spills is never full
    empty = lang.ViewStore(0, None, sample=True)
    empty.add(v)
    assert len(empty) == 0 and empty.dropped == 1


def test_view_store_spills_to_disk_and_reads_back(tmp_path):
    g, cam, bw, segs, codes, _, _ = _toy_view(seed=4)
    v = lang.prepare_view(bw, segs, codes, None, None)
    store = lang.ViewStore(v.nbytes + 10, tmp_path / "spill")
    store.add(v)
    store.add(v)  # over budget: memory-mapped
    assert store.ram_bytes == v.nbytes and store.disk_bytes == v.nbytes
    assert len(list((tmp_path / "spill").glob("*.npy"))) == len(lang.ViewData.ARRAYS)
    back = store[1]
    for k, t in v.arrays().items():
        assert torch.equal(back.arrays()[k], t), k
    f = torch.randn(len(g), 18)
    s = lang.slot_scale(18 * 24, 2, 3, "paper")
    assert torch.equal(
        lang.masked_l1(lang.csr_matmul(back.w, len(g), f), back, s)[0],
        lang.masked_l1(lang.csr_matmul(v.w, len(g), f), v, s)[0],
    )


@pytest.fixture(scope="module")
def optimised(trained):
    """The trained tiny chain's work dir with train-male's optimiser run as well
    (`--variant optimise`), and the path of that train-male artifact."""
    work, data, _ = trained
    out = run_cli(work, "train", "--variant", "optimise", "--data", str(data))
    assert "train-ae             cached" in out, out
    return work, _path_of(out, "train-male")


def test_male_artifact_on_tiny(optimised):
    work, path = optimised
    with Artifact(path) as art, _art(work, "reconstruct") as rec:
        assert art.config["mode"] == "optimise"
        root = art.root()
        metrics = read_json_dataset(root["metrics_json"])
        loss = root["log_epoch_loss"]
        assert len(loss) >= 2 and loss[-1] < loss[0]
        assert metrics["final_loss"] < loss[0]
        codes, meta = load_codes(art)
        assert meta["apps"] == ["orig", "nov1", "nov2", "nov3"]
        assert meta["levels"] == ["s", "m", "l"]
        n = len(rec.root()["means"])
        assert codes.shape == (n, 3, 4, 3)
        # 4 appearances x 3 levels x 3 channels in float16: 72 B per stored Gaussian
        assert root["codes"].dtype == np.float16
        assert metrics["bytes_per_gaussian"] == 72.0
        seen = np.unpackbits(root["seen_bits"], count=n).astype(bool)
        assert root["codes"].shape[0] == seen.sum() == metrics["gaussians_seen"]
        norms = codes[torch.from_numpy(seen)].norm(dim=-1)
        assert ((norms - 1).abs() < 2e-3).float().mean() > 0.99  # unit, as rendered
        assert (codes[torch.from_numpy(~seen)] == 0).all()
        assert np.isfinite(root["codes"]).all()


@pytest.mark.parametrize("mode", ["lift", "optimise"])
def test_male_rendered_codes_match_targets_better_than_chance(trained, optimised, mode):
    """The field (the default lift, and the optimiser's), rendered in a train view,
    is closer to its targets than the same codes shuffled across Gaussians."""
    from ptovs.field.render import WildField
    from ptovs.raster import Camera
    from ptovs.scene import load_scene

    work, data, _ = trained
    scene = load_scene(data)
    path = optimised[1] if mode == "optimise" else _path_of(trained[2], "train-male")
    path = work / "tiny_s0" / "train-male" / path.name
    with (
        Artifact(path) as art,
        _art(work, "reconstruct") as rec,
        _art(work, "train-ae") as ae,
        _art(work, "extract-features") as feats,
    ):
        codes, meta = load_codes(art)
        g = WildField.from_artifact(rec).gaussians
        errs, shuffled = [], []
        perm = torch.randperm(len(g), generator=torch.Generator().manual_seed(0))
        for view in scene.train_views()[:4]:
            cam = Camera.from_view(view)
            for ai, app in enumerate(meta["apps"]):
                seg = feats[view.name][f"seg_{app}"]
                table = ae[view.name][f"code_{app}"]
                for lv in range(len(meta["levels"])):
                    ok = seg[lv] >= 0
                    gt = table[seg[lv][ok].astype(np.int64)]
                    for c, out in ((codes, errs), (codes[perm], shuffled)):
                        img = render(g, cam, c[:, lv, ai].contiguous(), depth=False)
                        out.append(np.abs(img.image.numpy()[ok] - gt).mean())
        # every level and slot: on tiny (715 Gaussians, a few large segments) the
        # shuffled codes are a strong baseline; trained measured 0.875 of it
        assert np.mean(errs) < 0.95 * np.mean(shuffled)


# ----------------------------------------------------------- kill and resume --


def _ckpt_step(work: Path, stage: str) -> int:
    (path,) = (work / "tiny_s0" / stage).glob("*.ckpt/last.pt")
    return int(torch.load(path, weights_only=True)["state"]["step"])


def _kill_after(monkeypatch, module, name, n):
    real = getattr(module, name)
    calls = {"n": 0}

    def dying(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] > n:
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(module, name, dying)
    return calls


def test_killed_train_male_resumes_to_the_same_codes(
    extracted_work, tiny_scene_dir, tmp_path, monkeypatch
):
    work = copy_work(extracted_work[0], tmp_path / "work")
    data = str(tiny_scene_dir)
    run_cli(work, "train-ae", "--data", data)
    sets = [
        "--set",
        "mode=optimise",
        "--set",
        "iterations=40",
        "--set",
        "stop=fixed",
        "--set",
        "checkpoint_every=10",
    ]
    calls = _kill_after(monkeypatch, lang, "train_step", 25)
    res = CliRunner().invoke(
        main, ["--work-dir", str(work), *RECON, "train-male", "--data", data, *sets]
    )
    assert res.exit_code != 0
    assert _ckpt_step(work, "train-male") == 20
    monkeypatch.undo()
    calls = _kill_after(monkeypatch, lang, "train_step", 10**9)
    run_cli(work, "train-male", "--data", data, *sets)
    assert calls["n"] == 20  # iterations 21..40 only
    with _art(work, "train-male") as art:
        resumed = art.root()["codes"]
        assert read_json_dataset(art.root()["metrics_json"])["iterations"] == 40
    run_cli(work, "train-male", "--data", data, *sets, "--force")
    with _art(work, "train-male") as art:
        np.testing.assert_array_equal(art.root()["codes"], resumed)


def test_killed_train_ae_resumes_to_the_same_codes(
    extracted_work, tiny_scene_dir, tmp_path, monkeypatch
):
    work = copy_work(extracted_work[0], tmp_path / "work")
    data = str(tiny_scene_dir)
    sets = [
        "--set",
        "epochs=6",
        "--set",
        "checkpoint_every=1",
        "--set",
        "early_stop=false",
    ]
    _kill_after(monkeypatch, tae, "score", 4)  # dies scoring the 5th epoch
    res = CliRunner().invoke(
        main, ["--work-dir", str(work), *RECON, "train-ae", "--data", data, *sets]
    )
    assert res.exit_code != 0
    assert _ckpt_step(work, "train-ae") == 4
    monkeypatch.undo()
    run_cli(work, "train-ae", "--data", data, *sets)
    with _art(work, "train-ae") as art:
        m = read_json_dataset(art.root()["metrics_json"])
        assert m["epochs_run"] == 6 and len(art.root()["log_train_loss"]) == 6
        resumed = {n: art[n]["code_orig"] for n in art.names()}
    run_cli(work, "train-ae", "--data", data, *sets, "--force")
    with _art(work, "train-ae") as art:
        for n in art.names():
            np.testing.assert_allclose(art[n]["code_orig"], resumed[n], atol=1e-6)


# ---------------------------------------------------------------------- lift --


def _two_view_lift_case():
    """Three Gaussians, two views, one level and two slots (hand-built): A is seen
    by both views, B only by view 0 (inside its one segment), C by neither."""
    pts = [[0.5, 0.0, 3.0], [-1.0, 0.1, 3.0], [0.0, 0.0, -2.0]]
    g64 = stack_at(pts, scale=0.15, opacity=0.8)
    w, h = 24, 18
    cams = [make_camera(w, h, F64), make_camera(w, h, F64)]
    cams[1].cam_from_world[0, 3] = -1.5  # camera 1 sits at x = +1.5
    rng = np.random.default_rng(11)
    views = []
    for v in range(2):
        segs, codes = [], []
        for _ in range(2):  # slots
            seg = (
                np.zeros((1, h, w), np.int16)  # view 0: one segment everywhere
                if v == 0
                else rng.integers(-1, 3, (1, h, w)).astype(np.int16)
            )
            c = rng.normal(size=(3, 3)).astype(np.float32)
            segs.append(seg)
            codes.append(c / np.linalg.norm(c, axis=1, keepdims=True))
        u_t = rng.random((h, w)).astype(np.float32) * 0.9
        u_a = rng.random((h, w)).astype(np.float32) * 0.9
        views.append((segs, codes, u_t, u_a))
    return g64, cams, views


def test_lift_matches_float64_reference():
    g64, cams, views = _two_view_lift_case()
    g32 = type(g64)(*(t.float() for t in (g64.means, g64.quats, g64.scales)),
                    g64.opacities.float())  # fmt: skip
    store = lang.ViewStore(1 << 30, None)
    num = torch.zeros(3, 2, 3, dtype=F64)  # [P, slot, xyz]
    for cam, (segs, codes, u_t, u_a) in zip(cams, views, strict=True):
        cam32 = type(cam)(cam.cam_from_world.float(), cam.K.float(), cam.width,
                          cam.height)  # fmt: skip
        store.add(lang.prepare_view(blend_weights(g32, cam32), segs, codes, u_t, u_a))
        # W from the float64 torch oracle: splat the identity, one channel a Gaussian
        wmat = render(g64, cam, torch.eye(3, dtype=F64), background=None,
                      backend="torch", depth=False).image.reshape(-1, 3)  # fmt: skip
        m = ((1 - u_t) * (1 - u_a)).ravel()
        for a, (seg, code) in enumerate(zip(segs, codes, strict=True)):
            s = seg[0].ravel().astype(np.int64)
            # the stage keeps targets and weights in float16 (ViewData): round alike
            wgt = ((s >= 0) * m).astype(np.float16).astype(np.float64)
            gt = code.astype(np.float16).astype(np.float64)[np.maximum(s, 0)]
            num[:, a] += wmat.T @ torch.from_numpy(gt * wgt[:, None])
    ref = num / num.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    ref[num.norm(dim=-1) == 0] = 0
    f, metrics, hist = lang.train_male(store, 6, lang.MaleConfig(mode="lift-codes"))
    got = f.reshape(3, 2, 3).double()
    torch.testing.assert_close(got, ref, rtol=0, atol=1e-6)
    assert metrics["iterations"] == 0 and hist["epoch_loss"] == []
    # B is seen by view 0 alone, inside its single segment: it gets that code
    for a in range(2):
        np.testing.assert_allclose(got[1, a].numpy(), views[0][1][a][0], atol=1e-3)
    assert (got[2] == 0).all()  # C is behind both cameras: no view, zero code
    assert torch.isfinite(got).all()


@pytest.mark.parametrize("variant", ["paper", "code"])  # one weight a pixel, or two
def test_feature_lift_sums_match_a_dense_reference(variant, monkeypatch):
    """Σ_x W[x, k] m[x, ℓ, a] F_a[seg_a[ℓ, x]] per Gaussian, against dense float64:
    by pixel tuples where a pixel's segments share one weight (the paper's loss),
    by the direct product where they do not (the code's)."""
    import ptovs.field.lift as lift

    g, cam, bw, segs, _, _, _ = _toy_view(n=50, seed=6)
    rng = np.random.default_rng(6)
    feats = [rng.normal(size=(10, 8)).astype(np.float32) for _ in segs]
    u_t = rng.random((18, 24)).astype(np.float32)
    u_a = rng.random((18, 24)).astype(np.float32)
    valid = np.stack([s.reshape(len(s), -1).T >= 0 for s in segs], axis=-1)
    m = lang.mask_weights(valid, u_t, u_a, variant)
    paths = []
    for name in ("_by_tuples", "_by_product"):
        orig = getattr(lift, name)

        def spy(*a, _orig=orig, _name=name):
            got = _orig(*a)
            if got is not None:
                paths.append(_name)
            return got

        monkeypatch.setattr(lift, name, spy)
    got = feature_lift_sums(bw.csr()[1], segs, feats, m)
    assert paths == (["_by_tuples"] if variant == "paper" else ["_by_product"])
    wmat = bw.W.to_dense().double()  # [HW, P]
    for a, (seg, f) in enumerate(zip(segs, feats, strict=True)):
        for lv in range(seg.shape[0]):
            s = seg[lv].ravel().astype(np.int64)
            per_px = np.where((s >= 0)[:, None], f.astype(np.float64)[s], 0.0)
            ref = wmat.T @ torch.from_numpy(per_px * m[:, lv, a, None])
            torch.testing.assert_close(
                got[:, lv, a].double(), ref, rtol=1e-5, atol=1e-5
            )


def _resident_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


@pytest.mark.skipif(not Path("/proc/self/statm").exists(), reason="needs /proc")
def test_feature_lift_sums_keeps_no_memory_between_calls():
    """Repeated calls leave the resident memory where it was. torch's CPU product of
    two sparse CSR tensors kept memory on every call (a 2,934-photo lift was killed
    at 23.7 GB); here that is ~1 GB over the 20 measured calls."""
    rng = np.random.default_rng(0)
    n, h, w, per = 150_000, 120, 160, 8
    base = rng.integers(0, h * w, n)[:, None]  # per distinct, sorted pixels a row
    pix = np.sort((base + 97 * np.arange(per)) % (h * w), axis=1).astype(np.int32)
    indptr = torch.arange(0, n * per + 1, per, dtype=torch.int32)
    wt_csr = (indptr, torch.from_numpy(pix.ravel()), torch.rand(n * per))
    level = 40 * np.arange(3)[:, None, None]  # a slot's rows distinct across levels
    segs = [np.where(s >= 0, s + level, -1).astype(np.int16)
            for s in rng.integers(-1, 40, (2, 3, h, w))]  # fmt: skip
    feats = [rng.normal(size=(120, 8)).astype(np.float32) for _ in segs]
    valid = np.stack([s.reshape(3, -1).T >= 0 for s in segs], axis=-1)
    m = lang.mask_weights(valid, None, None)
    out = feature_lift_sums(wt_csr, segs, feats, m)

    def calls(k: int) -> float:  # resident MB after k more calls, freed pages returned
        for _ in range(k):
            feature_lift_sums(wt_csr, segs, feats, m, out=out)
        release()  # as train-male does after every view
        return _resident_mb()

    calls(3)  # warm: the allocator's pools reach their working size
    settled = calls(10)
    # a leak grows with every call (the CSR product: ~985 MB over these 20); the
    # allocator's noise does not (up to ~120 MB seen inside the whole suite)
    assert calls(20) - settled < 250
    assert torch.isfinite(out).all()


def test_lift_hard_cases_are_finite():
    """No segment anywhere, saturated uncertainty (weight 0 everywhere) and large
    codes: the lift stays finite and leaves unreached Gaussians at zero; codes past
    float16 (the targets' storage) are refused, not turned into inf."""
    g, cam, bw, segs, codes, _, _ = _toy_view(seed=4)
    empty = [np.full_like(s, -1) for s in segs]
    ones = np.ones((18, 24), np.float32)
    for args in ((empty, codes, None, None), (segs, codes, ones, None),
                 (segs, [c * 1e4 for c in codes], None, None)):  # fmt: skip
        store = lang.ViewStore(1 << 30, None)
        store.add(lang.prepare_view(bw, *args))
        f, _, _ = lang.train_male(store, 18, lang.MaleConfig(mode="lift-codes"))
        assert torch.isfinite(f).all()
        norms = f.reshape(len(g), -1, 3).norm(dim=-1)
        assert (((norms - 1).abs() < 1e-5) | (norms == 0)).all()
    assert (f.reshape(len(g), -1, 3).norm(dim=-1) > 0).any()  # the huge codes lift
    with pytest.raises(FloatingPointError, match="float16"):  # would overflow: refused
        lang.prepare_view(bw, segs, [c * 1e30 for c in codes], None, None)
    with pytest.raises(ValueError, match="mode"):
        lang.train_male(store, 18, lang.MaleConfig(mode="nope"))


def test_lift_variant_on_tiny(trained, optimised):
    """`--variant lift` (the default) and `lift-codes`: the full method's train-ae
    reused, train-male without an optimiser; finite codes, unit 3-chunks where
    seen, the optimiser's layout."""
    work, data, _ = trained
    out = run_cli(work, "train", "--variant", "optimise", "--data", str(data))
    lifted = run_cli(work, "train", "--variant", "lift-codes", "--data", str(data))
    assert "train-ae             cached" in lifted, lifted
    # same key (file name) as the default chain's AE; `out` ran in another work dir
    assert _path_of(lifted, "train-ae").name == _path_of(out, "train-ae").name
    path = _path_of(lifted, "train-male")
    male_path = path.parent / _path_of(out, "train-male").name
    assert path != male_path and male_path.is_file()
    with Artifact(path) as art, Artifact(male_path) as male:
        assert art.config["mode"] == "lift-codes"
        metrics = read_json_dataset(art.root()["metrics_json"])
        assert metrics["iterations"] == 0 and metrics["stop"].startswith("lift")
        codes, meta = load_codes(art)
        ref, ref_meta = load_codes(male)
        assert meta == ref_meta and codes.shape == ref.shape
        assert np.isfinite(art.root()["codes"]).all()
        seen = np.unpackbits(art.root()["seen_bits"], count=len(codes)).astype(bool)
        norms = codes[torch.from_numpy(seen)].norm(dim=-1)
        assert ((norms - 1).abs() < 2e-3).float().mean() > 0.99
        # the lift is the optimiser's starting point: trained codes stay close to it
        cos = (codes * ref).sum(-1)[torch.from_numpy(seen)]
        assert float(cos.mean()) > 0.5
    feat = run_cli(work, "train", "--variant", "lift", "--data", str(data))
    default = run_cli(work, "train", "--data", str(data))
    assert _path_of(feat, "train-male") == _path_of(default, "train-male")
    with Artifact(_path_of(feat, "train-male")) as art:
        assert art.config["mode"] == "lift"
        codes, meta = load_codes(art)
        assert meta == ref_meta and np.isfinite(art.root()["codes"]).all()
        seen = np.unpackbits(art.root()["seen_bits"], count=len(codes)).astype(bool)
        norms = codes[torch.from_numpy(seen)].norm(dim=-1)  # AE codes lie on S²
        assert ((norms - 1).abs() < 2e-3).float().mean() > 0.99


def test_lift_in_gaussian_ranges_matches_one_pass(trained):
    """The lift's [P, L, A, 512] sums held within cache_mb: with 4 MB the tiny scene
    (715 Gaussians, 24 KB each) takes several passes over the views, one range of
    Gaussians each, and gives the codes of one pass. The reported loss is over the
    views whose data fit those 4 MB: the others are dropped, never spilled."""
    work, data, out = trained
    multi = run_cli(
        work, "train", "--data", str(data), "--set", "train-male.cache_mb=4"
    )
    one = work / "tiny_s0" / "train-male" / _path_of(out, "train-male").name
    with Artifact(_path_of(multi, "train-male")) as a, Artifact(one) as b:
        ma = read_json_dataset(a.root()["metrics_json"])
        mb = read_json_dataset(b.root()["metrics_json"])
        assert ma["lift_passes"] >= 4
        assert mb["loss_views"] == mb["views"] and mb["loss_views_dropped"] == 0
        assert ma["loss_views"] + ma["loss_views_dropped"] == ma["views"]
        assert ma["loss_views_dropped"] > 0
        assert ma["final_loss"] is None or np.isfinite(ma["final_loss"])
        assert a.config["mode"] == b.config["mode"] == "lift"
        np.testing.assert_array_equal(a.root()["seen_bits"], b.root()["seen_bits"])
        np.testing.assert_allclose(
            a.root()["codes"].astype(np.float32),
            b.root()["codes"].astype(np.float32),
            atol=1e-3,
        )


# ------------------------------------------------------------------ variants --


def test_langsplat_variants_through_the_cli(trained):
    work, data, _ = trained
    out = run_cli(work, "train", "--variant", "langsplat", "--data", str(data))
    for stage in ("reconstruct", "extract-features", "train-ae", "train-male"):
        assert f"{stage:<20} done" in out, out
    assert "render-appearances" not in out and "uncertainty" not in out
    out2 = run_cli(work, "train", "--variant", "langsplat-wild", "--data", str(data))
    # the originals' features and the LangSplat AE do not depend on the geometry
    for stage in ("extract-features", "train-ae"):
        assert _path_of(out2, stage) == _path_of(out, stage)
        assert f"{stage:<20} cached" in out2
    assert _path_of(out2, "reconstruct") != _path_of(out, "reconstruct")
    for text, wild in ((out, False), (out2, True)):
        with Artifact(_path_of(text, "train-male")) as art:
            meta = read_json_dataset(art.root()["meta_json"])
            assert meta["apps"] == ["orig"]
            assert (
                read_json_dataset(art.root()["metrics_json"])["bytes_per_gaussian"]
                == 18.0
            )
            assert art.config["use_ut"] is False and art.config["use_ua"] is False
        with Artifact(_path_of(text, "reconstruct")) as rec:
            assert rec.config["wild"] is wild
    with Artifact(_path_of(out, "train-ae")) as ae:
        assert ae.config["weighting"] == "none" and ae.config["tau_u"] == 1.0
        assert ae.inputs.keys() == {"features"}  # no uncertainty input


def test_paper_variant_is_the_default_but_the_papers_ae_weighting(trained):
    """`--variant paper` keeps the paper's text: the chain before the lift and loss-only defaults, whose
    one changed default is the AE weighting. Everything upstream is reused; its
    train-ae config differs from the default's in `weighting` alone."""
    work, data, _ = trained
    default = run_cli(work, "train", "--data", str(data))
    paper = run_cli(work, "train", "--variant", "paper", "--data", str(data))
    for stage in (
        "reconstruct",
        "render-appearances",
        "extract-features",
        "uncertainty",
    ):
        assert f"{stage:<20} cached" in paper, paper
        assert _path_of(paper, stage) == _path_of(default, stage)
    assert f"{'train-ae':<20} done" in paper
    with Artifact(_path_of(default, "train-ae")) as a, \
            Artifact(_path_of(paper, "train-ae")) as b:  # fmt: skip
        assert a.config["weighting"] == "loss_only"
        assert b.config["weighting"] == "input_and_target"
        assert {k: v for k, v in a.config.items() if k != "weighting"} == {
            k: v for k, v in b.config.items() if k != "weighting"
        }
        code_a, code_b = (np.asarray(x[x.names()[0]]["code_orig"]) for x in (a, b))
        assert np.isfinite(code_b).all() and not np.array_equal(code_a, code_b)


def test_train_rejects_unknown_stage_in_set(trained):
    work, data, _ = trained
    res = CliRunner().invoke(
        main,
        ["--work-dir", str(work), "train", "--data", str(data), "--set", "nope.x=1"],
    )
    assert res.exit_code != 0 and "STAGE.KEY=VALUE" in res.output


def test_release_returns_heap_pages_and_never_fails():
    """ptovs.memory.release: glibc's malloc_trim here (a bool back), a no-op elsewhere."""
    from ptovs import memory

    buf = [bytearray(1 << 16) for _ in range(64)]  # 4 MB in small chunks, then freed
    del buf
    assert isinstance(memory.release(), bool)
    assert isinstance(memory.release(), bool)  # twice: nothing left to give is fine


def test_autoencoder_follows_the_features_width():
    """Encoders wider than 512 (SigLIP B: 768) get an AE of their width at both
    ends, and it rebuilds from its own weights."""
    import torch

    from ptovs.nets.autoencoder import LanguageAE

    for dim in (64, 512, 768):
        ae = LanguageAE(dim).eval()
        x = torch.nn.functional.normalize(torch.randn(5, dim), dim=-1)
        with torch.no_grad():
            y = ae(x)
        assert y.shape == (5, dim)
        assert torch.allclose(y.norm(dim=-1), torch.ones(5), atol=1e-5)
        again = LanguageAE.from_state(ae.state_dict())
        with torch.no_grad():
            assert torch.equal(again(x), y)
