"""bench/speed_error.py: which points are on a front, and the reconstruct target's
two figures (the fitted recipe against the better and the faster fixed one)."""

from __future__ import annotations

import json

import pytest

from conftest import bench_module


@pytest.fixture(scope="module")
def se():
    yield from bench_module("speed_error")


def test_the_front_keeps_what_nothing_beats(se):
    pts = [(100, 0.40), (50, 0.40), (200, 0.45), (60, 0.30), (50, 0.40)]
    # (100, .40) is beaten by (50, .40); (60, .30) by (50, .40); equal points stay
    assert se.pareto(pts) == [False, True, True, False, True]
    assert se.pareto([]) == [] and se.pareto([(1, 0.0)]) == [True]


def test_the_fitted_reconstruct_is_read_against_both_fixed_ones(se, tmp_path):
    rows = {
        "a/wild": {"scene": "a", "recipe": "wild", "reconstruct_s": 250.0, "psnr_test": 24.9},
        "a/plain": {"scene": "a", "recipe": "plain", "reconstruct_s": 100.0, "psnr_test": 21.8},
        "a/auto": {"scene": "a", "recipe": "auto", "reconstruct_s": 240.0, "psnr_test": 24.8},
        "b/auto": {"scene": "b", "recipe": "auto", "reconstruct_s": 10.0, "psnr_test": None},
    }  # fmt: skip
    path = tmp_path / "r.json"
    path.write_text(json.dumps(rows))
    out = {(r["scene"], r["recipe"]): r for r in se.recon_rows(path)}
    fitted = out[("a", "auto")]
    assert fitted["vs_best_db"] == pytest.approx(-0.1)
    assert fitted["vs_fastest_time"] == pytest.approx(2.4)
    # each is faster or better than the others: all three on the front
    assert all(out[("a", k)]["on_front"] for k in ("plain", "auto", "wild"))
    assert "vs_best_db" not in out[("b", "auto")]  # no PSNR, no pair: nothing read


def test_a_csv_reads_back_as_written(se, tmp_path):
    """One front re-run keeps the other's recorded rows: they read back as numbers."""
    rows = [
        {"recipe": "male", "chain_s": 263.3, "on_front": False, "seeds_kind": "test"},
        {"recipe": "auto", "chain_s": 244.7, "on_front": True, "seeds_kind": "dev",
         "delta": -0.01},
    ]  # fmt: skip
    path = tmp_path / "c.csv"
    se.write_csv(path, rows)
    back = se.read_csv(path)
    assert back[0] == rows[0]  # the missing delta stays missing, not ""
    assert back[1]["delta"] == -0.01 and back[1]["on_front"] is True
