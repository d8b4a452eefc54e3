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


def test_each_perturbation_changes_rounding_only(st):
    p = st.PERTURBATIONS
    assert [p[k]["threads"] for k in ("t1", "t2", "t3")] == [1, 2, 3]
    env = p["avx2"]["env"]
    assert env["ATEN_CPU_CAPABILITY"] == "avx2" and env["PTOVS_MARCH"] == "x86-64-v3"
    assert all(s.endswith(".backend=torch") for s in p["torch"]["sets"])
    # nothing that changes the method: no set but the raster backend
    assert all("sets" not in v for k, v in p.items() if k != "torch")


def test_answers_read_from_a_finished_chain(st, trained_work, tiny_scene_dir, tmp_path):
    work = copy_work(trained_work[0], tmp_path / "work")
    run_cli(work, "evaluate", "--data", str(tiny_scene_dir))
    a = st.answers(work, tiny_scene_dir, None, False)
    assert 0 <= a["miou"] <= 1 and a["gaussians"] > 0 and a["psnr_test"] > 0
    assert a["pairs"] and all(
        set(v) == {"level", "iou", "area", "score"} for v in a["pairs"].values()
    )
    assert "select" not in a and "style" not in a
