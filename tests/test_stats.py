"""The accuracy benchmark's statistics (ptovs.stats): cluster means, bootstrap CIs."""

from __future__ import annotations

import numpy as np
import pytest

from ptovs.stats import bootstrap_mean, cluster_means, paired_difference


def test_cluster_means_group_by_seed_and_query() -> None:
    recs = [
        {"seed": 0, "query": "Dome", "iou": 0.2},
        {"seed": 0, "query": "Dome", "iou": 0.4},
        {"seed": 1, "query": "Dome", "iou": 1.0},
        {"seed": 0, "query": "Wall", "iou": 0.0},
    ]
    cm = cluster_means(recs)
    assert cm == {(0, "Dome"): pytest.approx(0.3), (0, "Wall"): 0.0, (1, "Dome"): 1.0}
    assert cluster_means(recs, "iou", ("query",))[("Dome",)] == pytest.approx(1.6 / 3)


def test_bootstrap_is_seeded_and_brackets_the_mean() -> None:
    v = np.random.default_rng(1).normal(0.3, 0.1, 40)
    a, b = bootstrap_mean(v), bootstrap_mean(v)
    assert a == b  # same data, same interval
    assert a.lo < a.mean < a.hi and a.n == 40
    assert a.mean == pytest.approx(v.mean())
    # the percentile interval is about ±1.96 standard errors
    se = v.std(ddof=1) / np.sqrt(len(v))
    assert a.half_width == pytest.approx(1.96 * se, rel=0.15)


def test_bootstrap_edge_cases() -> None:
    one = bootstrap_mean(np.array([0.25]))
    assert (one.mean, one.lo, one.hi, one.n) == (0.25, 0.25, 0.25, 1)
    const = bootstrap_mean(np.full(10, 0.5))
    assert const.lo == const.hi == 0.5 and const.excludes_zero
    assert not bootstrap_mean(np.zeros(10)).excludes_zero
    with pytest.raises(ValueError):
        bootstrap_mean(np.array([]))
    with pytest.raises(ValueError):
        bootstrap_mean(np.array([0.1, np.nan]))
    big = bootstrap_mean(np.full(5, 1e300))  # huge values stay finite
    assert np.isfinite([big.mean, big.lo, big.hi]).all()
    with pytest.raises(ValueError, match="in common"):
        paired_difference({("a",): 1.0}, {("b",): 1.0})


def test_paired_difference_uses_common_clusters() -> None:
    a = {(0, "q"): 0.5, (1, "q"): 0.7, (2, "q"): 0.2}
    b = {(0, "q"): 0.4, (1, "q"): 0.5}
    d = paired_difference(a, b)
    assert d.n == 2 and d.mean == pytest.approx(0.15)


def test_cluster_bootstrap_covers_a_planted_difference() -> None:
    """Simulated benchmarks with a known difference δ between two methods: the
    95 % cluster-bootstrap interval of the paired difference covers δ in about
    95 % of them (clusters with their own random effect shared by both methods,
    a few pairs each, IoU-like skewed noise)."""
    rng = np.random.default_rng(20)
    delta, n_sim, n_clusters = 0.05, 300, 48
    hits = 0
    for _ in range(n_sim):
        base = rng.beta(2, 3, n_clusters)  # each cluster's difficulty
        a, b = {}, {}
        for c in range(n_clusters):
            pairs = rng.integers(3, 12)
            noise = rng.normal(0, 0.15, pairs)
            a[c] = float(np.mean(base[c] + delta + noise + rng.normal(0, 0.05, pairs)))
            b[c] = float(np.mean(base[c] + noise))
        est = paired_difference(a, b, n_boot=2000, seed=int(rng.integers(1 << 30)))
        hits += est.lo <= delta <= est.hi
    coverage = hits / n_sim
    assert 0.9 <= coverage <= 0.99, coverage
