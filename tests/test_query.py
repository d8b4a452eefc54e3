"""query and evaluate (issue: query/evaluate): relevancy, fusion, masks, metrics, CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from conftest import RECON, copy_work, run_cli
from ptovs.artifacts import Artifact
from ptovs.cli import main
from ptovs.field import relevancy as rel
from ptovs.field.query import read_results
from ptovs.metrics import markdown_table, pair_metrics, read_metrics, summarise


@pytest.fixture(scope="module")
def queried(tmp_path_factory, tiny_scene_dir, trained_work):
    work = copy_work(trained_work[0], tmp_path_factory.mktemp("query") / "work")
    out = run_cli(work, "evaluate", "--data", str(tiny_scene_dir))
    return work, tiny_scene_dir, out


# ---------------------------------------------------------------- relevancy --


def test_relevancy_matches_the_exponential_form_in_float64():
    g = torch.Generator().manual_seed(0)
    pos = torch.rand(500, generator=g, dtype=torch.float64) * 2 - 1
    neg = torch.rand(500, 5, generator=g, dtype=torch.float64) * 2 - 1
    tau = 10.0
    e_q = torch.exp(tau * pos)[:, None]
    literal = (e_q / (e_q + torch.exp(tau * neg))).amin(-1)
    got = rel.relevancy(pos.float(), neg.float(), tau).double()
    assert torch.allclose(got, literal, atol=1e-6)


def test_relevancy_is_finite_for_extreme_inputs():
    huge = torch.tensor([1e30, -1e30, 3e38, float("inf"), float("-inf"), float("nan")])
    pos = huge[:, None].expand(6, 6).reshape(-1)
    neg = huge[None, :].expand(6, 6).reshape(-1, 1)
    out = rel.relevancy(pos, neg, 10.0)
    assert torch.isfinite(out).all()
    assert ((out >= 0) & (out <= 1)).all()
    # the literal exp form overflows here: exp(10 * 1e30) = inf, inf / inf = nan
    assert rel.relevancy(torch.tensor([1e30]), torch.tensor([[-1e30]]))[0] == 1.0
    assert rel.relevancy(torch.tensor([0.2]), torch.tensor([[0.2]]))[0] == 0.5
    with pytest.raises(ValueError, match="canonical"):
        rel.relevancy(torch.zeros(3), torch.zeros(3, 0))


@pytest.mark.parametrize("mode", rel.FUSIONS)
def test_every_fusion_mode_reduces_to_the_single_map_for_one_appearance(mode):
    s = torch.rand(3, 1, 9, 7, generator=torch.Generator().manual_seed(1))
    assert torch.allclose(rel.fuse(s, mode), s[:, 0], atol=1e-6)


@pytest.mark.parametrize("mode", rel.FUSIONS)
def test_fusion_weights_are_a_convex_combination_on_hard_inputs(mode):
    """Equal maps fuse to themselves (the weights sum to 1), all-zero scores give
    zeros, and saturated maps (0 and 1 only, all-equal columns) stay finite and
    inside the per-pixel [min, max] of the appearances."""
    const = torch.full((2, 4, 5, 6), 0.37)
    torch.testing.assert_close(rel.fuse(const, mode), const[:, 0])
    zero = torch.zeros(2, 4, 5, 6)
    assert (rel.fuse(zero, mode) == 0).all()
    sat = torch.rand(2, 4, 5, 6, generator=torch.Generator().manual_seed(3)) > 0.5
    sat = sat.float()
    sat[:, :, 0] = 1.0  # a row where every appearance is saturated
    out = rel.fuse(sat, mode)
    assert torch.isfinite(out).all()
    assert (out >= sat.amin(1) - 1e-6).all() and (out <= sat.amax(1) + 1e-6).all()
    assert (out[:, 0] == 1.0).all()


def test_fusion_modes_on_a_hand_example():
    a = torch.zeros(1, 2, 1, 2)
    a[0, 0, 0] = torch.tensor([0.8, 0.2])  # peak 0.8
    a[0, 1, 0] = torch.tensor([0.1, 0.4])  # peak 0.4
    w = torch.tensor([0.8, 0.4]) / 1.2
    expect = w[0] * a[0, 0, 0] + w[1] * a[0, 1, 0]
    assert torch.allclose(rel.fuse(a, "weighted")[0, 0], expect)
    assert torch.allclose(rel.fuse(a, "pixmax")[0, 0], torch.tensor([0.8, 0.4]))
    assert torch.allclose(rel.fuse(a, "pixavg")[0, 0], torch.tensor([0.45, 0.3]))
    assert torch.allclose(rel.fuse(a, "imglvlmax")[0, 0], a[0, 0, 0])
    # all-zero maps: equal weights, no 0/0
    assert torch.isfinite(rel.fuse(torch.zeros(2, 3, 4, 4), "weighted")).all()
    with pytest.raises(ValueError):
        rel.fuse(a, "nope")


def test_background_filter_forms():
    # K phrases: 0 query, 1 sky, 2 background
    cos = torch.zeros(2, 3, 4, 5, 3)
    cos[..., 1] = 1.0  # every pixel looks like sky
    b = rel.background(cos, 0, [1, 2], "paper")
    assert b.shape == (2, 4, 5)
    assert torch.allclose(b, torch.sigmoid(torch.tensor(10.0)))
    code = rel.background(cos, 0, [1], "code", image_queries=[0])
    assert code.shape == (1, 4, 5)
    assert torch.allclose(code, torch.tensor(0.5))  # sky against itself caps it
    assert rel.background(cos, 0, [1, 2], "off") is None


def test_threshold_relative_rule_and_constant_map():
    s = np.linspace(0, 1, 11, dtype=np.float32)[None]
    m = rel.threshold(s, 0.4, "relative")
    assert m.tolist() == [[x > 0.7 + 1e-6 for x in np.linspace(0, 1, 11)]]
    assert not rel.threshold(np.full((4, 4), 0.3, np.float32)).any()
    assert rel.threshold(s, 0.4, "absolute").sum() == 7  # 0.4 .. 1.0


def test_the_stable_cut_keeps_a_mask_where_a_fixed_cut_jumps():
    """A part that stands out (steep sides) on a background whose level sits near
    τ: the fixed relative cut takes in or drops the background with a tiny change
    of the map; the stable cut stays on the part's plateau."""
    yy, xx = np.mgrid[:64, :64]
    part = ((yy - 32) ** 2 + (xx - 32) ** 2 < 100).astype(np.float64)
    slope = 0.7 * xx / 63  # a gentle ramp up to just above the fixed cut
    areas = {"relative": [], "stable": []}
    for shift in (-0.01, 0.0, 0.01):
        m = np.maximum(part, slope + shift) * 0.8
        for mode in areas:
            areas[mode].append(int(rel.threshold(m, 0.4, mode).sum()))
    fixed, stable = np.ptp(areas["relative"]), np.ptp(areas["stable"])
    assert stable * 5 < fixed, areas
    assert min(areas["stable"]) >= part.sum() - 8  # the part, whole
    # hard cases: constant, empty and huge maps
    assert not rel.threshold(np.full((4, 4), 0.3), 0.4, "stable").any()
    assert rel.threshold(np.zeros((0, 3)), 0.4, "stable").shape == (0, 3)
    huge = np.where(part > 0, 1e30, -1e30)
    torch.testing.assert_close(
        torch.from_numpy(rel.threshold(huge, 0.4, "stable")), torch.from_numpy(part > 0)
    )
    assert rel.stable_cut(np.linspace(0, 1, 101), 0.4) == pytest.approx(
        0.4
    )  # even ramp
    with pytest.raises(ValueError, match="stable"):
        rel.threshold(part, 0.4, "otsu")


def test_peak_of_is_the_maximum_or_a_quantile_and_hard_cases():
    v = np.arange(1001, dtype=np.float32)
    assert rel.peak_of(v) == 1000.0 and rel.peak_of(v, 1.0) == 1000.0
    assert rel.peak_of(v, 0.99) == pytest.approx(990.0)
    assert rel.peak_of(np.zeros(0, np.float32), 0.9) == 0.0
    assert rel.peak_of(np.full(7, 0.25, np.float32), 0.5) == 0.25
    big = np.array([1e30, -1e30, 3e38], np.float32)
    assert np.isfinite(rel.peak_of(big, 0.5))


def test_choose_level_is_argmax_or_a_softmax_blend():
    level, w = rel.choose_level(np.array([0.45, 0.46, 0.30]))
    assert level == 1 and w.tolist() == [0.0, 1.0, 0.0]
    level, w = rel.choose_level(np.array([0.45, 0.46, 0.30]), 0.01)
    assert level == 1 and w.sum() == pytest.approx(1.0)
    assert 0.2 < w[0] < 0.5 and w[2] < 1e-6  # the near-tie shares, the far one not
    _, w = rel.choose_level(np.array([0.2, 0.6]), 0.01)
    assert w[1] > 0.999999  # a clear winner is the argmax's choice
    _, w = rel.choose_level(np.array([0.5]), 0.01)
    assert w.tolist() == [1.0]


def test_threshold_with_a_robust_top():
    s = np.linspace(0, 1, 11, dtype=np.float32)[None]
    assert (rel.threshold(s, 0.4, "relative", None) == rel.threshold(s, 0.4)).all()
    # top 0.5: n = s / 0.5, so s > 0.35 passes (values over the top count as n = 1)
    m = rel.threshold(s, 0.4, "relative", 0.5)
    assert m.tolist() == [[x > 0.35 + 1e-6 for x in np.linspace(0, 1, 11)]]
    assert not rel.threshold(np.zeros((0, 3), np.float32), 0.4, "relative", 0.5).size


def _spiked(value: float) -> np.ndarray:
    """A [2, 1, 40, 40] score stack: level 1 has a clear 12×12 part at 0.5 over 0.1,
    level 0 the same at 0.45, and one pixel of level 1 at `value`."""
    s = np.full((2, 1, 40, 40), 0.1, np.float32)
    s[1, 0, 10:22, 10:22] = 0.5
    s[0, 0, 10:22, 10:22] = 0.45
    s[1, 0, 30, 30] = value
    return s


def test_a_single_outlier_pixel_cannot_shrink_the_mask_under_a_robust_peak():
    plain = rel.QuerySettings(background_filter="off", smooth_kernel=1, majority=1)
    robust = rel.QuerySettings(background_filter="off", smooth_kernel=1, majority=1,
                               peak_quantile=0.95)  # fmt: skip
    base = rel.finish(torch.from_numpy(_spiked(0.5)), None, plain)
    assert base.level == 1 and base.mask.sum() == 144 + 1
    spike = rel.finish(torch.from_numpy(_spiked(0.99)), None, plain)
    assert spike.mask.sum() == 1  # the maximum follows one pixel: the part is lost
    r = rel.finish(torch.from_numpy(_spiked(0.99)), None, robust)
    assert r.level == 1 and r.mask[10:22, 10:22].all() and r.mask.sum() == 145


def test_defaults_keep_the_papers_finish_exactly():
    """peak_quantile = 1 and level_softness = 0: the old rule, bit for bit."""
    rng = np.random.default_rng(7)
    s = torch.from_numpy(rng.random((3, 2, 30, 40), np.float32))
    st = rel.QuerySettings(background_filter="off")
    res = rel.finish(s, None, st)
    fused = rel.fuse(s, st.fusion).numpy()
    k, win = st.filter_sizes(30, 40)
    sm = np.stack([rel.smooth(m, k) for m in fused])
    level = int(np.argmax(sm.reshape(3, -1).max(1)))
    lo = float(sm[level].min())
    n = (sm[level] - lo) / (float(sm[level].max() - lo) + rel.DIV_EPS)
    old = rel.majority(np.clip(2 * n - 1, 0, 1) > st.threshold, win)
    assert res.level == level and np.array_equal(res.mask, old)
    assert res.score == float(sm[level].max())


def test_a_level_near_tie_moves_the_mask_a_little_when_blended():
    """Two levels, peaks 0.50 vs 0.50 ± 0.002: the argmax switches the whole mask,
    the blend moves it by a few pixels."""

    def stack(delta):
        s = np.full((2, 1, 40, 40), 0.1, np.float32)
        s[0, 0, 5:15, 5:15] = 0.5 + delta  # a small part
        s[1, 0, 5:30, 5:30] = 0.5 - delta  # a large one around it
        return torch.from_numpy(s)

    def iou(a, b):
        return (a & b).sum() / max((a | b).sum(), 1)

    hard = rel.QuerySettings(background_filter="off", smooth_kernel=1, majority=1)
    soft = rel.QuerySettings(background_filter="off", smooth_kernel=1, majority=1,
                             level_softness=0.02)  # fmt: skip
    a, b = (rel.finish(stack(d), None, hard).mask for d in (0.002, -0.002))
    assert iou(a, b) < 0.2
    a, b = (rel.finish(stack(d), None, soft).mask for d in (0.002, -0.002))
    assert iou(a, b) > 0.9


def test_select_uses_the_same_robust_peak_and_blend():
    s = torch.full((2, 1, 1000), 0.1)
    s[1, 0, :100] = 0.5
    s[0, 0, :100] = 0.45
    s[1, 0, 999] = 0.99  # one outlier Gaussian
    plain = rel.select(s, None, rel.QuerySettings(background_filter="off"))
    robust = rel.select(s, None, rel.QuerySettings(background_filter="off",
                                                   peak_quantile=0.95))  # fmt: skip
    assert plain.mask.sum() == 1 and robust.mask[:100].all()
    assert robust.mask.sum() == 101 and robust.level == 1


@pytest.mark.parametrize("bad", [{"peak_quantile": 0.0}, {"peak_quantile": 1.5},
                                 {"level_softness": -0.1},
                                 {"level_softness": float("nan")}])  # fmt: skip
def test_out_of_range_level_knobs_are_refused(bad):
    with pytest.raises(ValueError, match="query\\."):
        rel.QuerySettings(**bad)


def _majority_loop(mask, size, exact):
    h, w = mask.shape
    r = size // 2
    out = np.zeros_like(mask)
    for i in range(h):
        for j in range(w):
            y1 = min(i + r + 1, h - 1 if exact else h)
            x1 = min(j + r + 1, w - 1 if exact else w)
            win = mask[max(i - r, 0) : y1, max(j - r, 0) : x1]
            out[i, j] = win.size > 0 and 2 * win.sum() > win.size
    return out


@pytest.mark.parametrize("exact", [False, True])
def test_majority_filter_matches_a_loop(exact):
    mask = np.random.default_rng(2).random((13, 17)) > 0.5
    assert np.array_equal(rel.majority(mask, 7, exact), _majority_loop(mask, 7, exact))
    assert rel.majority(np.zeros((0, 0), bool)).shape == (0, 0)


def test_table_decode_close_to_exact():
    from ptovs.nets.autoencoder import LanguageAE

    torch.manual_seed(0)
    ae = LanguageAE().eval()
    phrases = torch.nn.functional.normalize(torch.randn(6, 512), dim=1)
    exact = rel.PhraseDecoder(ae.decode, phrases, "exact")
    table = rel.PhraseDecoder(ae.decode, phrases, "table", size=64)
    c = torch.nn.functional.normalize(torch.randn(4000, 3), dim=1)
    c = c * torch.rand(4000, 1)  # blends: anywhere in the ball
    err = (table(c) - exact(c)).abs()
    assert err.max() < 0.02 and err.mean() < 2e-3  # the documented bound
    # grid points themselves are exact
    g = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    assert torch.allclose(table(g), exact(g), atol=1e-5)


def test_answer_end_to_end_on_a_synthetic_map():
    # query phrase 0 matches a square; canonical 1; sky 2, background 3
    L, N, H, W = 3, 2, 40, 50
    cos = torch.zeros(L, N, H, W, 4)
    cos[..., 0] = 0.1
    cos[..., 1] = 0.3
    cos[:, :, 10:30, 15:35, 0] = 0.9
    res = rel.answer(cos, 0, [1], [2, 3], rel.QuerySettings())
    gt = np.zeros((H, W), bool)
    gt[10:30, 15:35] = True
    assert pair_metrics(res.mask, gt)["iou"] > 0.8
    assert res.smoothed.shape == (L, H, W) and np.isfinite(res.smoothed).all()
    nan_cos = torch.full_like(cos, float("nan"))
    res2 = rel.answer(nan_cos, 0, [1], [2, 3], rel.QuerySettings())
    assert np.isfinite(res2.smoothed).all() and not res2.mask.any()


# ------------------------------------------------------------------ metrics --


def test_metrics_hand_computed_cases():
    gt = np.zeros((4, 5), bool)
    gt[1:3, 1:3] = True  # 4 of 20 pixels
    empty = pair_metrics(np.zeros_like(gt), gt)
    assert empty == {"iou": 0.0, "pa": 16 / 20, "p": 0.0, "recall": 0.0}
    full = pair_metrics(np.ones_like(gt), gt)
    assert full == {"iou": 4 / 20, "pa": 4 / 20, "p": 4 / 20, "recall": 1.0}
    perfect = pair_metrics(gt, gt)
    assert perfect == {"iou": 1.0, "pa": 1.0, "p": 1.0, "recall": 1.0}
    half = gt.copy()
    half[1, 1:3] = False
    half[0, 0] = True  # 2 TP, 1 FP, 2 FN
    m = pair_metrics(half, gt)
    assert m["iou"] == pytest.approx(2 / 5) and m["p"] == pytest.approx(2 / 3)
    assert m["pa"] == pytest.approx(17 / 20)
    pairs = [
        {"query": "a", "pred_pixels": 0, **empty},
        {"query": "b", "pred_pixels": 20, **full},
        {"query": "a", "pred_pixels": 4, **perfect},
    ]
    s = summarise(pairs)
    assert s["miou"] == pytest.approx((0 + 0.2 + 1) / 3)
    assert s["mp"] == pytest.approx((0 + 0.2 + 1) / 3)
    assert s["per_query_miou"] == {"a": 0.5, "b": pytest.approx(0.2)}
    assert s["empty_predictions"] == 1
    table = markdown_table({"male": {"s1": s, "s2": None}})
    assert "failed" in table and "*" in table


def test_query_absent_from_an_image_is_not_a_pair(queried):
    work, data, _ = queried
    (path,) = sorted((work / "tiny_s0" / "evaluate").glob("*.h5"))
    with Artifact(path) as art:
        summary, pairs = read_metrics(art)
    from ptovs.scene import load_labels, load_scene

    scene = load_scene(data)
    expected = sum(
        int(m.any())
        for v in scene.labelled_views()
        for m in load_labels(scene, v).values()
    )
    assert summary["pairs"] == len(pairs) == expected
    for p in pairs:  # every pair is a category of that very image's label
        assert p["query"] in load_labels(scene, scene.view(p["view"]))


# -------------------------------------------------------------- CLI / chain --


def test_evaluate_metrics_are_numbers_in_range(queried):
    work, data, out = queried
    assert "| male |" in out
    report = json.loads((work / "tiny_s0" / "evaluate.json").read_text())
    m = report["results"]["male"]["tiny_s0"]
    for key in ("miou", "mpa", "mp"):
        assert 0.0 <= m[key] <= 1.0
    assert m["pairs"] > 0
    assert "empty_prediction" in report["conventions"]
    assert (work / "tiny_s0" / "evaluate.md").read_text().startswith("mIoU")


def test_query_cli_writes_pictures_and_json_and_is_deterministic(queried, tmp_path):
    work, data, _ = queried
    from ptovs.scene import label_categories, load_scene

    text = label_categories(load_scene(data))[0]
    args = ["query", text, "--data", str(data), "--out", str(tmp_path / "a")]
    run_cli(work, *args)
    res = json.loads((tmp_path / "a" / "results.json").read_text())["results"]
    assert res and all(r["query"] == text for r in res)
    import cv2

    for r in res:
        mask = cv2.imread(r["mask"], cv2.IMREAD_UNCHANGED)
        over = cv2.imread(r["overlay"])
        assert mask.shape[0] == over.shape[0] and over.shape[1] > mask.shape[1]
        assert set(np.unique(mask)) <= {0, 255}
        assert (mask > 0).sum() == r["mask_pixels"]
    # same query again, recomputed: identical masks
    first = {r["view"]: cv2.imread(r["mask"], cv2.IMREAD_UNCHANGED) for r in res}
    run_cli(work, *args[:-1], str(tmp_path / "b"), "--force")
    res_b = json.loads((tmp_path / "b" / "results.json").read_text())["results"]
    for r in res_b:
        assert np.array_equal(
            cv2.imread(r["mask"], cv2.IMREAD_UNCHANGED), first[r["view"]]
        )


def test_one_folder_holds_one_query_run(queried, tmp_path):
    """A second query into the same folder replaces the first run's pictures:
    results.json and the PNGs beside it always agree; a user's own file stays."""
    work, data, _ = queried
    from ptovs.scene import label_categories, load_scene

    first, second = label_categories(load_scene(data))[:2]
    out = tmp_path / "q"
    run_cli(work, "query", first, "--data", str(data), "--out", str(out))
    (out / "notes.txt").write_text("mine")
    run_cli(work, "query", second, "--data", str(data), "--out", str(out))
    res = json.loads((out / "results.json").read_text())["results"]
    listed = {Path(r[k]).resolve() for r in res for k in ("mask", "heatmap", "overlay")}
    assert {p.resolve() for p in out.rglob("*.png")} == listed
    assert all(r["query"] == second for r in res)
    assert (out / "notes.txt").read_text() == "mine"


def test_clearing_a_previous_run_treats_its_json_as_hostile(tmp_path):
    from ptovs.stages.query import clear_previous

    out, outside = tmp_path / "out", tmp_path / "outside_mask.png"
    (out / "v").mkdir(parents=True)
    outside.write_bytes(b"keep")
    ours = out / "v" / "wall_mask.png"
    ours.write_bytes(b"x")
    other = out / "v" / "photo.png"
    other.write_bytes(b"keep")
    (out / "results.json").write_text(json.dumps({"results": [
        {"mask": str(ours), "overlay": str(outside), "heatmap": str(other)},
        {"mask": "../../outside_mask.png"}, "junk", {"mask": 7}]}))  # fmt: skip
    assert clear_previous(out) == 1
    assert not ours.exists() and outside.read_bytes() == b"keep"
    assert other.read_bytes() == b"keep" and not (out / "results.json").exists()
    (out / "results.json").write_text("not json")
    assert clear_previous(out) == 0


def test_unknown_phrase_is_a_clear_error(queried):
    work, data, _ = queried
    res = CliRunner().invoke(
        main,
        [
            "--work-dir",
            str(work),
            *RECON,
            "query",
            "Flying Saucer",
            "--data",
            str(data),
        ],
    )
    assert res.exit_code != 0
    assert "Flying Saucer" in res.output and "vocabulary" in res.output


def test_query_every_ensemble_mode_and_filter_runs(queried):
    work, data, _ = queried
    for sets in (
        ["--set", "query.fusion=pixweighted", "--set", "query.background_filter=code"],
        ["--set", "query.threshold_mode=stable"],
        ["--set", "query.fusion=imglvlmax", "--set", "query.background_filter=off"],
        ["--set", "query.decode=exact", "--set", "query.threshold_mode=absolute"],
    ):
        run_cli(work, "query", "--data", str(data), "--no-pictures", *sets)
    arts = sorted((work / "tiny_s0" / "query").glob("*.h5"))
    assert len(arts) >= 4
    for p in arts:
        with Artifact(p) as art:
            meta, views = read_results(art)
            for d in views.values():
                assert np.isfinite(d["smoothed"].astype(np.float32)).all()
                assert d["mask"].shape[0] == len(meta["queries"])


def test_evaluate_variants_side_by_side(queried):
    work, data, _ = queried
    out = run_cli(
        work, "evaluate", "--data", str(data), "--variant", "male",
        "--variant", "pixavg", "--variant", "no-bg-filter",
    )  # fmt: skip
    for v in ("| male |", "| pixavg |", "| no-bg-filter |"):
        assert v in out
    report = json.loads((work / "tiny_s0" / "evaluate.json").read_text())
    assert set(report["results"]) == {"male", "pixavg", "no-bg-filter"}


def test_per_query_tables_match_exact_decoding():
    """The table path (relevancy and background tabulated per query) against
    decoding every pixel, on a smooth random code field and a random AE."""
    from ptovs.nets.autoencoder import LanguageAE

    torch.manual_seed(3)
    ae = LanguageAE().eval()
    k = 9  # query, 5 canonical, sky, background, another query
    phrases = torch.nn.functional.normalize(torch.randn(k, 512), dim=1)
    exact = rel.PhraseDecoder(ae.decode, phrases, "exact")
    table = rel.PhraseDecoder(ae.decode, phrases, "table", size=64)
    L, N, H, W = 3, 4, 24, 32
    low = torch.randn(L * N * 3, 4, 5)
    field = torch.nn.functional.interpolate(low[None], (H, W), mode="bilinear")[0]
    codes = field.reshape(L, N, 3, H, W).permute(0, 1, 3, 4, 2)
    codes = torch.nn.functional.normalize(codes, dim=-1) * torch.rand(L, N, H, W, 1)
    for mode in ("paper", "code", "off"):
        st = rel.QuerySettings(background_filter=mode)
        bg = [6] if mode == "code" else [6, 7]
        ref = rel.answer(exact(codes), 0, [1, 2, 3, 4, 5], bg, st, [0, 8])
        s, b = rel.score_maps(table.grid_cosines, 0, [1, 2, 3, 4, 5], bg, st, [0, 8])
        tab = torch.stack([s] if b is None else [s, b])
        vals = table.lookup(codes, tab)
        got = rel.finish(vals[..., 0], vals[..., 1] if b is not None else None, st)
        assert np.abs(got.smoothed - ref.smoothed).max() < 0.02
        assert (got.mask != ref.mask).mean() < 0.01


def test_vocabulary_change_renews_query_keys_only(scene_copy, tmp_path):
    """Text embeddings come from synthetic/vocabulary.json, which the scene
    fingerprint leaves out: a changed vocabulary gives query (and so evaluate)
    new keys, and leaves the trained field's keys alone."""
    from ptovs.chain import Chain, RunContext
    from ptovs.locate import resolve_scene

    def keys() -> dict[str, str]:
        ctx = RunContext(tmp_path / "work")
        chain = Chain(ctx, resolve_scene(ctx, None, scene_copy))
        return {s: chain.key(s) for s in ("train-male", "query", "evaluate")}

    before = keys()
    assert before == keys()  # stable
    path = scene_copy / "synthetic/vocabulary.json"
    vocab = json.loads(path.read_text())
    vocab["phrases"]["Extra Phrase"] = next(iter(vocab["phrases"].values()))
    path.write_text(json.dumps(vocab))
    after = keys()
    assert after["train-male"] == before["train-male"]
    assert after["query"] != before["query"]
    assert after["evaluate"] != before["evaluate"]


def test_an_unqueried_label_category_names_its_label_file(queried):
    """evaluate over a query that was asked fewer texts than the labels hold: the
    message names the label file, the category and the queries there were."""
    work, data, _ = queried
    res = CliRunner().invoke(main, ["--work-dir", str(work), *RECON, "--set",
                                    'query.queries=["Brick Facade"]', "evaluate",
                                    "--data", str(data)])  # fmt: skip
    assert res.exit_code == 1 and isinstance(res.exception, SystemExit), res.output
    line = next(ln for ln in res.output.splitlines() if ln.startswith("Error:"))
    assert "was not queried" in line and ".json" in line and "Brick Facade" in line


def test_query_embeds_texts_with_the_features_encoder():
    """One place for the language model: query follows the encoder recorded with
    the features unless told otherwise, and refuses an override that cannot match."""
    from types import SimpleNamespace

    from ptovs.errors import InputError
    from ptovs.field.query import QueryConfig, resolve_text_encoder

    real, synth = SimpleNamespace(synthetic=False), SimpleNamespace(synthetic=True)
    rec = {"name": "openclip", "model": "ViT-L-14", "checkpoint": "ckpt/l14.pt",
           "pretrained": "datacomp_xl_s13b_b90k"}  # fmt: skip
    got = resolve_text_encoder(QueryConfig(), real, rec)
    assert got == {**rec, "tokenizer": ""}  # the tag travels with the features
    assert resolve_text_encoder(QueryConfig(clip_model="ViT-L-14"), real, rec) == got
    for bad, msg in ((QueryConfig(clip_model="ViT-B-16"), "clip_model"),
                     (QueryConfig(clip_checkpoint="other.pt"), "clip_checkpoint"),
                     (QueryConfig(encoder="synthetic"), "query.encoder")):  # fmt: skip
        with pytest.raises(InputError, match=msg):
            resolve_text_encoder(bad, real, rec)
    # no record (features made before it existed): the old rule
    assert resolve_text_encoder(QueryConfig(), synth, None)["name"] == "synthetic"
    old = resolve_text_encoder(QueryConfig(), real, None)
    assert old == {"name": "openclip", "model": "ViT-B-16", "checkpoint": "",
                   "pretrained": "", "tokenizer": ""}  # fmt: skip
    # the stand-in's versions are one family
    v2 = resolve_text_encoder(QueryConfig(), synth, {"name": "synthetic-v2"})
    assert v2["name"] == "synthetic"
