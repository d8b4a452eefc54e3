"""render-appearances, extract-features and uncertainty (issue: extract) on `tiny`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from conftest import RECON, copy_work
from ptovs.artifacts import Artifact, read_json_dataset
from ptovs.cli import main
from ptovs.features import (
    SegmentFeatures,
    read_langsplat,
    tuple_ids,
    view_apps,
    write_langsplat,
)
from ptovs.field.appearance import (
    QUALITY_METRICS,
    pairwise_l1,
    paper_targets,
    render_error,
    select_targets,
)
from ptovs.field.losses import auroc
from ptovs.scene import load_scene
from ptovs.segment import NO_SEGMENT, Level
from ptovs.stages import uncertainty as unc


def _cli(work: Path, *args: str) -> str:
    # every call shares the short reconstruct config, so the chain keys agree
    res = CliRunner().invoke(main, ["--work-dir", str(work), *RECON, *args])
    assert res.exit_code == 0, res.output + repr(res.exception)
    return res.output


@pytest.fixture(scope="module")
def chain(tmp_path_factory, tiny_scene_dir, extracted_work):
    """tiny: reconstruct (short) then `ptovs extract`; returns (work, data, output)."""
    src, out = extracted_work
    work = copy_work(src, tmp_path_factory.mktemp("extract") / "work")
    return work, tiny_scene_dir, out


def _art(work: Path, stage: str) -> Artifact:
    (path,) = sorted((work / "tiny_s0" / stage).glob("*.h5"))
    return Artifact(path)


# ------------------------------------------------------------ selection --


def test_selection_respects_both_constraints():
    rng = np.random.default_rng(1)
    names = [f"img{i}" for i in range(40)]
    q = rng.random(40)
    emb = rng.normal(size=(40, 32))
    chosen, rep = select_targets(names, q, emb, 3, quality_quantile=0.25, seed=3)
    assert len(chosen) == 3 and len(set(chosen)) == 3
    idx = [names.index(c) for c in chosen]
    assert (q[idx] < rep["eps_q"]).all()
    assert rep["eps_q"] == pytest.approx(np.quantile(q, 0.25))
    d = pairwise_l1(emb[idx])
    assert d[~np.eye(3, dtype=bool)].min() > rep["eps_d"]
    assert rep["min_pairwise_l1"] == pytest.approx(d[~np.eye(3, dtype=bool)].min())
    # the initial ε_d is the candidates' median distance; deterministic per seed
    cand = np.flatnonzero(q < rep["eps_q"])
    dc = pairwise_l1(emb[cand])
    assert rep["eps_d_tried"][0] == pytest.approx(
        np.median(dc[~np.eye(len(cand), dtype=bool)]), rel=1e-5
    )
    assert select_targets(names, q, emb, 3, seed=3)[0] == chosen


def test_selection_too_few_candidates_is_reported():
    names = ["a", "b", "c", "d", "e", "f"]
    q = np.array([0.1, 0.5, 0.5, 0.5, 0.5, 0.5])
    emb = np.eye(6)
    chosen, rep = select_targets(names, q, emb, 3)
    assert chosen == ["a"]
    assert "only 1 of 3" in rep["note"]
    # identical embeddings can never be diverse: one of them only
    chosen, rep = select_targets(
        names, np.arange(6.0), np.ones((6, 4)), 3, quality_quantile=1.0
    )
    assert len(chosen) == 1 and "note" in rep


def test_selection_without_its_constraints():
    """Table 4's rows: no ε_q (any image is a candidate), no ε_d (a seeded draw)."""
    rng = np.random.default_rng(2)
    names = [f"img{i}" for i in range(30)]
    q, emb = rng.random(30), rng.normal(size=(30, 8))
    chosen, rep = select_targets(names, q, emb, 3, seed=1, use_diversity=False)
    assert len(set(chosen)) == 3 and rep["eps_d"] is None and not rep["diversity"]
    assert all(q[names.index(c)] < rep["eps_q"] for c in chosen)
    assert select_targets(names, q, emb, 3, seed=1, use_diversity=False)[0] == chosen
    chosen, rep = select_targets(names, q, emb, 3, seed=1, use_quality=False)
    assert rep["eps_q"] is None and rep["candidates"] == 30 and len(chosen) == 3
    chosen, rep = select_targets(
        names[:2], q[:2], emb[:2], 3, use_quality=False, use_diversity=False
    )
    assert len(chosen) == 2 and "only 2 of 3" in rep["note"]


def test_name_order_keeps_the_targets_when_a_photo_crosses_the_cut():
    """A 2 % change of the renders' errors moves a photo or two across ε_q. The
    seeded permutation of the candidates then reorders all of them; the name
    order moves the targets only where a crossing photo wins a place."""
    changed = {"draw": 0, "names": 0}
    for trial in range(40):
        rng = np.random.default_rng(100 + trial)
        names = [f"{trial:02d}_{i:03d}" for i in range(60)]
        q, emb = rng.random(60), rng.normal(size=(60, 16))
        q2 = q * (1 + 0.02 * rng.standard_normal(60))
        for order in changed:
            a = select_targets(names, q, emb, 3, seed=0, order=order)[0]
            b = select_targets(names, q2, emb, 3, seed=0, order=order)[0]
            changed[order] += set(a) != set(b)
    assert changed["names"] * 2 <= changed["draw"], changed
    assert select_targets(names, q, emb, 3, order="names")[1]["order"] == "names"
    with pytest.raises(ValueError, match="order"):
        select_targets(names, q, emb, 3, order="shuffle")


def test_name_order_depends_on_each_name_alone():
    from ptovs.field.appearance import name_order

    names = ["b", "a", "d", "c", "e"]
    full = [names[i] for i in name_order(names, 0, 0)]
    part = [names[i] for i in name_order(names[:3], 0, 0)]
    assert [n for n in full if n in part] == part  # the same relative order
    assert full != [names[i] for i in name_order(names, 1, 0)]  # the seed draws anew
    assert name_order([], 0, 0).size == 0


def test_render_error_metrics():
    """ε_q's errors against a float64 reference, and the bias "l1" has: a darker
    pair has a smaller L1 for the same relative error; the normalised ones do not."""
    rng = np.random.default_rng(0)
    photo = rng.uniform(0.2, 0.8, (24, 20, 3))
    render = np.clip(photo + rng.normal(0, 0.05, photo.shape), 0, 1)
    l1 = float(np.abs(render - photo).mean())
    assert render_error(render, photo, "l1") == pytest.approx(l1, rel=1e-12)
    assert render_error(render, photo, "l1-relative") == pytest.approx(
        l1 / photo.mean(), rel=1e-12
    )
    dark = 0.25
    assert render_error(dark * render, dark * photo, "l1") == pytest.approx(dark * l1)
    assert render_error(dark * render, dark * photo, "l1-relative") == pytest.approx(
        l1 / photo.mean()
    )
    d = render_error(render, photo, "dssim")
    assert 0.0 < d < 1.0
    # contrast halved about mid grey: SSIM's structure term keeps most of it
    flat = lambda x: 0.5 + 0.5 * (x - 0.5)  # noqa: E731
    assert render_error(flat(render), flat(photo), "dssim") < 2 * d
    # hard cases: identical constant images, black ones, no NaN
    for v in (0.0, 0.5, 1.0):
        c = np.full((8, 8, 3), v)
        for m in QUALITY_METRICS:
            assert render_error(c, c, m) == pytest.approx(0.0, abs=1e-12)
    assert np.isfinite(
        render_error(np.ones((8, 8, 3)), np.zeros((8, 8, 3)), "l1-relative")
    )
    with pytest.raises(ValueError, match="quality metric"):
        render_error(render, photo, "psnr")
    with pytest.raises(ValueError, match="shape"):
        render_error(render, photo[:-1], "l1")


def test_paper_targets_by_scene_name():
    assert paper_targets("trevi_fountain")[0] == "15457887_10227170235"
    assert paper_targets("Notre-Dame front facade") is not None
    assert paper_targets("tiny_s0") is None


# -------------------------------------------------------------- renders --


def test_extract_chain_and_cache(chain):
    work, data, out = chain
    for stage in ("render-appearances", "extract-features", "uncertainty"):
        assert stage in out
    again = _cli(work, "extract", "--data", str(data))
    assert again.count("cached") == 3, again


def test_renders_are_rgb_and_clamped(chain):
    work, data, _ = chain
    scene = load_scene(data)
    with _art(work, "render-appearances") as art:
        meta = read_json_dataset(art.root()["slots_json"])
        rep = read_json_dataset(art.root()["selection_json"])
        assert meta["slots"] == ["nov1", "nov2", "nov3", "self"]
        assert rep["mode"] == "select" and len(rep["chosen"]) == 3
        names = {v.name for v in scene.train_views()}
        assert set(meta["targets"]) <= names
        assert sorted(art.names()) == sorted(names)
        errs = []
        for v in scene.train_views():
            rgb = art[v.name]["rgb"]
            assert rgb.dtype == np.uint8 and rgb.shape == (4, v.height, v.width, 3)
            img = scene.load_image(v)
            self_r = rgb[-1].astype(np.float32) / 255
            assert (
                abs(float(np.abs(self_r - img).mean()) - float(art[v.name]["l1_self"]))
                < 0.01
            )
            errs.append(
                (np.abs(self_r - img).mean(), np.abs(self_r[..., ::-1] - img).mean())
            )
        errs = np.array(errs)
        # the authors' R/B swap would make the self render match its photo worse
        # in most views (with the swap this share would be below 0.2)
        assert (errs[:, 0] < errs[:, 1]).mean() > 0.8
        assert errs[:, 0].mean() < errs[:, 1].mean()
        assert rgb.max() <= 255 and rgb.min() >= 0  # uint8 from a clamped render


def test_explicit_targets_and_bgr_option(chain, tmp_path):
    # a copy: the scene records these --set items for its later commands
    work, data = copy_work(chain[0], tmp_path / "work"), chain[1]
    scene = load_scene(data)
    ids = [v.stem for v in scene.train_views()[:3]]
    targets = "targets=[" + ", ".join(f'"{i}"' for i in ids) + "]"
    _cli(
        work,
        "render-appearances",
        "--data",
        str(data),
        "--set",
        targets,
        "--set",
        "bgr_swap_renders=true",
    )
    arts = sorted(
        (work / "tiny_s0" / "render-appearances").glob("*.h5"),
        key=lambda p: p.stat().st_mtime,
    )
    assert len(arts) == 2
    with Artifact(arts[-1]) as art:
        meta = read_json_dataset(art.root()["slots_json"])
        assert [Path(t).stem for t in meta["targets"]] == ids
        v = scene.train_views()[5]
        swapped = art[v.name]["rgb"][-1]
    with Artifact(arts[0]) as art:
        plain = art[v.name]["rgb"][-1]
    assert np.array_equal(swapped, plain[..., ::-1])
    bad = CliRunner().invoke(
        main,
        [
            "--work-dir",
            str(work),
            *RECON,
            "render-appearances",
            "--data",
            str(data),
            "--set",
            'targets=["nope_1", "nope_2", "nope_3"]',
        ],
    )
    assert bad.exit_code != 0 and "nope_1" in str(bad.output) + str(bad.exception)


# ------------------------------------------------------------- features --


def test_feature_tables_are_consistent(chain):
    work, _, _ = chain
    with _art(work, "extract-features") as art:
        meta = read_json_dataset(art.root()["levels_json"])
        assert meta["levels"] == ["s", "m", "l"] and meta["apps"][0] == "orig"
        for name in art.names():
            view = art[name]
            assert view_apps(view) == ["orig", "nov1", "nov2", "nov3", "self"]
            for app in view_apps(view):
                f = SegmentFeatures.from_view(view, app)
                f.validate()
                assert f.seg.dtype == np.int16 and f.table.dtype == np.float16
                norms = np.linalg.norm(f.table.astype(np.float32), axis=1)
                assert np.allclose(norms, 1, atol=2e-3)
                o = f.offsets()
                for lv in range(f.levels):
                    ids = np.unique(f.seg[lv])
                    ids = ids[ids >= 0]
                    # every id in the map has a row of its level, every row is used
                    assert np.array_equal(ids, np.arange(o[lv], o[lv + 1]))
                    dense, ok = f.dense(lv)
                    assert np.array_equal(
                        dense[ok], f.table[f.seg[lv][ok]].astype(np.float32)
                    )


def _feats(seg: np.ndarray, table: np.ndarray, counts) -> SegmentFeatures:
    return SegmentFeatures(
        seg.astype(np.int16), table.astype(np.float16), np.asarray(counts, np.int32)
    )


def test_sentinel_never_reaches_a_lookup():
    seg = np.array([[[0, 1], [NO_SEGMENT, 1]]])
    table = np.array([[1.0, 0.0], [0.0, 1.0]])
    f = _feats(seg, table, [2])
    dense, ok = f.dense(0)
    assert not ok[1, 0] and np.array_equal(dense[1, 0], [0, 0])  # not table[-1]
    with pytest.raises(ValueError, match="references"):
        _feats(np.zeros((1, 2, 2)), table, [2]).validate()  # row 1 unused
    with pytest.raises(ValueError):
        _feats(np.full((1, 2, 2), -2), table, [2]).validate()


def test_empty_level_and_from_levels():
    a = Level(np.array([[0, 0], [1, 1]], np.int32))
    empty = Level(np.full((2, 2), NO_SEGMENT, np.int32))
    f = SegmentFeatures.from_levels(
        [a, empty, a], [np.eye(4)[:2], np.zeros((0, 4)), np.eye(4)[2:]], 4
    )
    f.validate()
    assert f.counts.tolist() == [2, 0, 2] and f.seg[2].max() == 3
    assert (f.seg[1] == NO_SEGMENT).all() and f.level_table(1).shape == (0, 4)


def test_langsplat_round_trip(chain, tmp_path):
    work, data, _ = chain
    out = tmp_path / "ls"
    _cli(work, "export-features", "--data", str(data), "--out", str(out))
    with _art(work, "extract-features") as art:
        name = art.names()[0]
        stem = Path(name).stem
        assert (out / f"{stem}_f.npy").is_file() and (
            out / f"{stem}_s_ma_3.npy"
        ).is_file()
        s = np.load(out / f"{stem}_s.npy")
        assert s.shape[0] == 4 and (s[0] == -1).all()  # no "default" level stored
        for app, suffix in (("orig", ""), ("nov2", "_ma_1"), ("self", "_ma_3")):
            want = SegmentFeatures.from_view(art[name], app)
            got = read_langsplat(out, stem, ("s", "m", "l"), suffix)
            assert np.array_equal(got.seg, want.seg) and np.array_equal(
                got.table, want.table
            )
            assert np.array_equal(got.counts, want.counts)
        # the stage imports the folder: same tables as the computed ones (in a copy
        # of the work dir: the scene records the --set for its later commands)
        own = copy_work(work, tmp_path / "import-work")
        _cli(own, "extract-features", "--data", str(data), "--set", f"import_dir={out}")
        arts = sorted(
            (own / "tiny_s0" / "extract-features").glob("*.h5"),
            key=lambda p: p.stat().st_mtime,
        )
        with Artifact(arts[-1]) as imp:
            for app in ("orig", "self"):
                a, b = (
                    SegmentFeatures.from_view(imp[name], app),
                    SegmentFeatures.from_view(art[name], app),
                )
                assert np.array_equal(a.seg, b.seg) and np.array_equal(a.table, b.table)
    # pickled npy files are refused
    bad = tmp_path / "bad"
    bad.mkdir()
    np.save(bad / "x_f.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    np.save(bad / "x_s.npy", np.zeros((4, 2, 2), np.int32))
    with pytest.raises(ValueError, match="plain npy"):
        read_langsplat(bad, "x", ("s",))
    with pytest.raises(FileNotFoundError, match="y_f.npy"):
        read_langsplat(bad, "y", ("s",))


def test_write_langsplat_keeps_level_order(tmp_path):
    lv = Level(np.array([[0, 1]], np.int32))
    f = SegmentFeatures.from_levels([lv, lv], [np.eye(3)[:2], np.eye(3)[1:]], 3)
    write_langsplat(tmp_path, "v", f, ("l", "s"), "")
    back = read_langsplat(tmp_path, "v", ("l", "s"))
    assert np.array_equal(back.table, f.table) and np.array_equal(back.seg, f.seg)


# ---------------------------------------------------------- uncertainty --


def test_transient_uncertainty_finds_occluders(chain):
    work, data, _ = chain
    scores, labels = [], []
    with _art(work, "uncertainty") as art:
        for name in art.names():
            ut, ua = art[name]["u_t"], art[name]["u_a"]
            assert (
                ut.dtype == np.float16
                and np.isfinite(ut).all()
                and np.isfinite(ua).all()
            )
            assert ut.min() >= 0 and ut.max() <= 1 and ua.min() >= 0 and ua.max() <= 1
            truth = np.load(data / "synthetic" / "truth" / f"{Path(name).stem}.npz")[
                "transient"
            ]
            scores.append(ut.ravel().astype(np.float32))
            labels.append(truth.ravel())
        assert art.path.with_suffix(".previews").is_dir()
        assert len(list(art.path.with_suffix(".previews").glob("*.png"))) == 4
    a = auroc(np.concatenate(scores), np.concatenate(labels))
    assert a > 0.65, a


def _view(apps: dict[str, SegmentFeatures]) -> dict[str, np.ndarray]:
    out = {}
    for app, f in apps.items():
        out.update(f.datasets(app))
    return out


def test_uncertainty_matches_dense_float64_reference():
    rng = np.random.default_rng(0)
    h, w, d = 6, 5, 16

    def rand_feats():
        levels, rows = [], []
        for n in (3, 2):
            lab = rng.integers(-1, n, size=(h, w)).astype(np.int32)
            lab[0, :n] = np.arange(n)  # every id present
            levels.append(Level(lab))
            t = rng.normal(size=(n, d))
            rows.append(t / np.linalg.norm(t, axis=1, keepdims=True))
        return SegmentFeatures.from_levels(levels, rows, d)

    apps = {a: rand_feats() for a in ("orig", "nov1", "nov2", "self")}
    cfg = unc.Config()
    ut, ua, ok_t, ok_a = unc.raw_maps(_view(apps), cfg)
    # dense float64 reference: per level, mean over channels, then over valid levels
    ref_t, ref_a = np.zeros((h, w)), np.zeros((h, w))
    cnt_t, cnt_a = np.zeros((h, w)), np.zeros((h, w))
    for lv in range(2):
        dense = {a: f.dense(lv) for a, f in apps.items()}
        f = {
            a: f.table.astype(np.float64)[np.maximum(f.seg[lv], 0)]
            for a, f in apps.items()
        }
        vt = dense["orig"][1] & dense["self"][1]
        ref_t += np.where(vt, ((f["self"] - f["orig"]) ** 2).mean(-1), 0)
        cnt_t += vt
        mem = ["nov1", "nov2", "self"]
        va = np.all([dense[m][1] for m in mem], axis=0)
        stack = np.stack([f[m] for m in mem])
        var = ((stack - stack.mean(0)) ** 2).mean(0).mean(-1)
        ref_a += np.where(va, var, 0)
        cnt_a += va
    assert np.array_equal(ok_t, cnt_t > 0) and np.array_equal(ok_a, cnt_a > 0)
    np.testing.assert_allclose(ut, ref_t / np.maximum(cnt_t, 1), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(ua, ref_a / np.maximum(cnt_a, 1), rtol=1e-4, atol=1e-6)
    # the code's variant: novel renders only
    _, ua_code, _, _ = unc.raw_maps(_view(apps), unc.Config(ua_members="novel"))
    assert not np.allclose(ua_code[ok_a], ua[ok_a])


@pytest.mark.parametrize("span", [5, 40_000])  # lookup table; past it, the sort
def test_tuple_ids_partition_as_numpy_unique(span):
    rng = np.random.default_rng(1)
    rows = rng.integers(0, span, size=(3_000, 4))
    rows[1000:2000] = rows[:1000]  # repeated tuples
    first, inv = tuple_ids(rows)
    uniq, ref_inv = np.unique(rows, axis=0, return_inverse=True)
    assert np.array_equal(rows[first], uniq)  # lexicographic, as numpy's
    assert np.array_equal(inv, ref_inv.ravel())
    assert np.array_equal(rows[first][inv], rows)
    f0, i0 = tuple_ids(np.zeros((0, 3), np.int64))
    assert f0.size == 0 and i0.size == 0


def test_uncertainty_hard_cases_are_finite():
    h, w = 4, 3
    const = Level(np.zeros((h, w), np.int32))
    none = Level(np.full((h, w), NO_SEGMENT, np.int32))
    row = np.ones((1, 8)) / np.sqrt(8)
    same = SegmentFeatures.from_levels([const, none], [row, np.zeros((0, 8))], 8)
    view = _view({"orig": same, "nov1": same, "self": same})
    ut, ua, ok_t, ok_a = unc.raw_maps(view, unc.Config())
    assert np.all(ut == 0) and np.all(ua == 0) and ok_t.all()
    # constant maps normalise to 0, without a division by zero
    out = unc.normalise(ut, ok_t, 0.0, 0.0)
    assert out.dtype == np.float16 and np.all(out == 0)
    # an all-invalid view: every pixel is fully uncertain, still finite
    empty = SegmentFeatures.from_levels([none], [np.zeros((0, 8))], 8)
    ut, ua, ok_t, ok_a = unc.raw_maps(
        _view({"orig": empty, "self": empty}), unc.Config()
    )
    assert not ok_t.any() and not ok_a.any()
    out = unc.normalise(ut, ok_t, np.inf, -np.inf)
    assert np.all(out == 1) and np.isfinite(out).all()
    # huge values stay finite and clipped
    big = unc.normalise(
        np.full((2, 2), 1e30, np.float32), np.ones((2, 2), bool), 0.0, 1.0
    )
    assert np.all(big == 1)
    # the authors' bug reads the last row where no segment is
    lab = Level(np.array([[0, -1]], np.int32))
    a = SegmentFeatures.from_levels([lab], [np.array([[1.0, 0.0]])], 2)
    b = SegmentFeatures.from_levels([lab], [np.array([[0.0, 1.0]])], 2)
    ut_bug, _, ok_bug, _ = unc.raw_maps(
        _view({"orig": a, "self": b}), unc.Config(seg_invalid="last_row")
    )
    assert ok_bug.all() and ut_bug[0, 1] == pytest.approx(1.0)
    ut_ok, _, ok, _ = unc.raw_maps(_view({"orig": a, "self": b}), unc.Config())
    assert not ok[0, 1]


def test_killed_extract_features_resumes(chain, monkeypatch):
    """A run that dies mid-stage keeps its finished views; the rerun does the rest."""
    import ptovs.stages.extract_features as ef

    work, data, _ = chain
    real = ef.image_features
    calls = {"n": 0}

    def dying(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] > 12:  # 5 images per view: dies in the third view
            raise KeyboardInterrupt
        return real(*args, **kwargs)

    monkeypatch.setattr(ef, "image_features", dying)
    sets = ["extract", "--data", str(data), "--set", "extract-features.graph_sigma=0.7"]
    res = CliRunner().invoke(main, ["--work-dir", str(work), *RECON, *sets])
    assert res.exit_code != 0
    parts = list((work / "tiny_s0" / "extract-features").glob("*.parts/*.h5"))
    assert len(parts) == 2  # two finished views survived
    calls["n"] = -1000
    out = _cli(work, *sets)
    assert "uncertainty" in out
    n_views = len(load_scene(data).train_views())
    assert calls["n"] == -1000 + 5 * (n_views - 2)  # only the missing views ran
