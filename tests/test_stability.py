"""bench/stability.py: the spreads it reports over perturbations, what each
perturbation changes, and the answers it reads from a finished chain."""

from __future__ import annotations

import json

import pytest

from conftest import bench_module, copy_work, run_cli


@pytest.fixture(scope="module")
def st():
    yield from bench_module("stability")


def _run(miou, sel, levels, areas, scores, winner="Art Deco", psnr=20.0):
    return {
        "miou": miou, "mpa": 0.9, "mp": 0.5, "psnr_test": psnr,
        "psnr_test_nerfw": psnr + 1, "gaussians": 1000,
        "pairs": {
            f"v|{i}": {"level": lv, "iou": miou, "area": a, "score": s}
            for i, (lv, a, s) in enumerate(zip(levels, areas, scores, strict=True))
        },
        "select": {"selected": sel, "level": "m"},
        "style": {"winner": winner, "votes": {}},
    }  # fmt: skip


def test_spreads_over_runs(st):
    runs = {
        "t1": _run(0.12, 738, ["s", "m"], [10, 100], [0.40, 0.50], psnr=12.0),
        "t2": _run(0.17, 110, ["s", "s"], [20, 100], [0.57, 0.50], psnr=12.2),
        "t3": _run(0.37, 3586, ["s", "m"], [10, 50], [0.45, 0.50], "Moorish", 12.1),
    }
    s = st.scene_spread(runs)
    assert s["runs"] == ["t1", "t2", "t3"]
    assert s["miou_range"] == pytest.approx(0.25)
    assert s["select_ratio"] == pytest.approx(3586 / 110)
    assert s["psnr_test_range"] == pytest.approx(0.2)
    assert s["pairs"] == 2 and s["level_flips"] == 1
    assert s["level_agreement"] == pytest.approx((1 + 2 / 3) / 2)
    assert s["area_ratio_median"] == pytest.approx(2.0)  # both pairs' max/min are 2
    assert s["score_range_mean"] == pytest.approx(0.17 / 2)
    assert s["style_agreement"] == pytest.approx(2 / 3)


def test_identical_runs_have_no_spread(st):
    r = _run(0.3, 500, ["m"], [42], [0.5])
    s = st.scene_spread({"a": r, "b": json.loads(json.dumps(r))})
    assert s["miou_range"] == 0 and s["select_ratio"] == 1 and s["level_flips"] == 0
    assert s["style_agreement"] == 1 and s["area_ratio_median"] == 1


def test_hard_cases_of_the_spreads(st):
    assert st.ratio_counts([0, 5]) == 5.0  # an empty selection counts as one
    assert st.spread_numbers([None, 1.0, 3.0]) == 2.0
    assert st.agreement([]) == 1.0


def test_each_perturbation_changes_what_it_names_only(st):
    p = st.PERTURBATIONS
    assert st.HEADLINE == ("t2", "jpeg95", "floats", "seed1")
    assert [p[k]["threads"] for k in ("t1", "t2", "t3")] == [1, 2, 3]
    env = p["avx2"]["env"]
    assert env["ATEN_CPU_CAPABILITY"] == "avx2" and env["PTOVS_MARCH"] == "x86-64-v3"
    moved = p["floats"]["env"]
    assert (
        moved["ATEN_CPU_CAPABILITY"] == "default" and moved["MKL_CBWR"] == "COMPATIBLE"
    )
    assert moved["ONEDNN_MAX_CPU_ISA"] == "SSE41"
    assert p["jpeg95"]["photos"] == 95 and "sets" not in p["jpeg95"]
    assert all(s.endswith(".backend=torch") for s in p["torch"]["sets"])
    assert p["seed1"]["sets"] == ["reconstruct.seed=1", "render-appearances.seed=1"]
    # nothing that changes the method: no set but the raster backend and the seeds
    assert all("sets" not in v for k, v in p.items() if k not in ("torch", "seed1"))


def test_photos_resaved_look_the_same_but_are_other_bytes(st, tmp_path):
    import cv2
    import numpy as np

    scene = tmp_path / "data" / "demo_s0"
    (scene / "dense" / "images").mkdir(parents=True)
    (scene / "truth.json").write_text("{}")
    (tmp_path / "data" / "label" / "demo_s0").mkdir(parents=True)
    (tmp_path / "data" / "label" / "demo_s0" / "a.json").write_text("{}")
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 256, (64, 80, 3), np.uint8)
    img = cv2.GaussianBlur(noise, (0, 0), 4)  # photo-like: smooth, little detail
    path = scene / "dense" / "images" / "a.jpg"
    cv2.imwrite(str(path), img, [cv2.IMWRITE_JPEG_QUALITY, 90])
    before = path.read_bytes()
    out = st.resaved(scene, tmp_path / "q95", 95)
    assert out == tmp_path / "q95" / "demo_s0" and (out / "truth.json").is_file()
    assert (tmp_path / "q95" / "label" / "demo_s0" / "a.json").is_file()
    new = out / "dense" / "images" / "a.jpg"
    assert new.read_bytes() != before and path.read_bytes() == before
    diff = np.abs(cv2.imread(str(new)).astype(int) - cv2.imread(str(path)).astype(int))
    assert 0 < diff.max() <= 16 and diff.mean() < 2  # a few steps, not identical
    stamp = new.stat().st_mtime_ns
    assert st.resaved(scene, tmp_path / "q95", 95) == out  # once: a rerun reuses it
    assert new.stat().st_mtime_ns == stamp
    (scene / "dense" / "images" / "b.jpg").write_text("not a jpeg")
    with pytest.raises(RuntimeError, match="b.jpg"):
        st.resaved(scene, tmp_path / "other", 95)


def test_the_report_follows_the_chain_stage_by_stage(st, capsys):
    runs = {
        "t2": _run(0.5, 100, ["s"], [10], [0.5]) | {"targets": ["a", "b", "c"]},
        "jpeg95": _run(0.4, 140, ["m"], [30], [0.6]) | {"targets": ["a", "b", "d"]},
    }
    s = st.scene_spread(runs)
    assert s["targets_same"] == [True, False]
    assert s["targets_shared"] == pytest.approx([1.0, 2 / 3])
    st.print_stages(s)
    out = capsys.readouterr().out
    order = ["reconstruct", "render-appearances", "query", "evaluate", "select"]
    assert [out.index(k) for k in order] == sorted(out.index(k) for k in order)
    assert "equal to the reference in 0 of 1 runs; 67% shared" in out


def test_answers_read_from_a_finished_chain(st, trained_work, tiny_scene_dir, tmp_path):
    work = copy_work(trained_work[0], tmp_path / "work")
    run_cli(work, "evaluate", "--data", str(tiny_scene_dir))
    a = st.answers(work, tiny_scene_dir, None, False)
    assert 0 <= a["miou"] <= 1 and a["gaussians"] > 0 and a["psnr_test"] > 0
    assert a["pairs"] and all(
        set(v) == {"level", "iou", "area", "score"} for v in a["pairs"].values()
    )
    assert len(a["targets"]) == 3  # the novel targets render-appearances chose
    assert "select" not in a and "style" not in a


def test_attribution_links_the_reference_up_to_a_stage(st, tmp_path):
    base = tmp_path / "ref"
    for stage in (*st.CHAIN, "query", "evaluate"):
        (base / "scene" / stage).mkdir(parents=True)
        (base / "scene" / stage / "a.h5").write_text(stage)
    (base / "scene" / "select.json").write_text("{}")
    work = st.seeded_work(base, tmp_path / "w", st.CHAIN[:3])
    linked = sorted(p.parent.name for p in (work / "scene").rglob("*.h5"))
    assert linked == sorted(st.CHAIN[:3])
    assert (work / "scene" / "extract-features" / "a.h5").stat().st_nlink == 2
    whole = st.seeded_work(base, tmp_path / "w2")  # a --set run: up to train-male
    assert sorted(p.parent.name for p in whole.rglob("*.h5")) == sorted(st.CHAIN)


def test_attribution_drops_the_settings_of_linked_stages(st, monkeypatch, tmp_path):
    calls = []
    monkeypatch.setattr(st, "_ptovs", lambda w, t, env, sets, *a: calls.append(sets))
    monkeypatch.setattr(st, "answers", lambda *a: {"miou": 0.5})
    scene = tmp_path / "s"
    st.run_scene("seed1", scene, tmp_path / "w", None, False, None, after="reconstruct")
    st.run_scene("seed1", scene, tmp_path / "w", None, False, None, after="train-ae")
    st.run_scene("seed1", scene, tmp_path / "w", None, False, None)
    assert calls == [
        ["render-appearances.seed=1"],
        [],
        ["reconstruct.seed=1", "render-appearances.seed=1"],
    ]
    with pytest.raises(ValueError, match="photos"):  # a re-save acts from the start
        st.run_scene(
            "jpeg95", scene, tmp_path / "w", None, False, None, after="reconstruct"
        )


def test_equal_maps_cut_otherwise_show_as_masks_not_maps(
    st, trained_work, tiny_scene_dir, tmp_path
):
    a = copy_work(trained_work[0], tmp_path / "a")
    b = copy_work(trained_work[0], tmp_path / "b")
    run_cli(a, "query", "--data", str(tiny_scene_dir), "--no-pictures")
    run_cli(b, "--set", "query.threshold=0.1", "query", "--data",
            str(tiny_scene_dir), "--no-pictures")  # fmt: skip
    (scene,) = [p.name for p in a.iterdir() if (p / "query").is_dir()]
    same = st.map_agreement(a / scene, a / scene)
    assert same["pairs"] > 0
    assert same["map_corr_median"] == pytest.approx(1.0)
    assert same["mask_iou_median"] == 1.0
    cut = st.map_agreement(a / scene, b / scene)
    assert cut["map_corr_median"] == pytest.approx(1.0)  # the same maps ...
    assert cut["mask_iou_median"] < 0.9  # ... cut lower: larger masks


def test_attribution_runs_each_change_after_each_stage(st, monkeypatch, tmp_path):
    import argparse

    calls = []

    def fake_run(label, scene, work, text, style, config, extra=(), after=None):
        calls.append((label, work.name, extra, after))
        return {"miou": 0.5}

    monkeypatch.setattr(st, "run_scene", fake_run)
    monkeypatch.setattr(st, "map_agreement", lambda ref, work: {"pairs": 1})
    (tmp_path / "work" / "demo" / "t2+rule" / "demo_s0" / "reconstruct").mkdir(
        parents=True
    )
    args = argparse.Namespace(
        work=tmp_path / "work", data=tmp_path / "data", text="Minaret",
        demo_perturbations=["t2", "jpeg95", "floats", "seed1"],
        after=["reconstruct", "train-ae"], set=["query.threshold=0.5"], name="rule",
    )  # fmt: skip

    class Res(dict):
        def save(self):
            pass

    res = Res()
    st.part_attribute(args, res)
    # the reference and a re-save are not attributed; each run keeps the rule
    assert [(c[0], c[3]) for c in calls] == [
        ("floats", "reconstruct"), ("floats", "train-ae"),
        ("seed1", "reconstruct"), ("seed1", "train-ae"),
    ]  # fmt: skip
    assert all(c[2] == ("query.threshold=0.5",) for c in calls)
    assert calls[0][1] == "floats@reconstruct+rule"
    assert set(res["attribute"]["demo"]) == {
        "floats@reconstruct", "floats@train-ae", "seed1@reconstruct", "seed1@train-ae",
    }  # fmt: skip
    st.part_attribute(args, res)  # finished runs are kept, not rerun
    assert len(calls) == 4
