"""Statistics of the accuracy benchmark: cluster means and the cluster bootstrap.

The benchmark scores (image, query) pairs, but pairs of the same query on the
same scene are not independent: they share the landmark, the part's texture and
the field. The unit of resampling is therefore the cluster (scene seed, query):
each cluster's mean IoU is one observation, a method's mIoU is the mean over
clusters, and a comparison of two methods is the mean of their paired
per-cluster differences, with a percentile bootstrap over clusters for its 95 %
confidence interval.
"""

from __future__ import annotations

from collections.abc import Hashable, Iterable, Mapping
from dataclasses import dataclass

import numpy as np

N_BOOT = 10_000
LEVEL = 0.95


@dataclass(frozen=True)
class Estimate:
    """A mean over clusters and its bootstrap confidence interval."""

    mean: float
    lo: float
    hi: float
    n: int  # clusters

    @property
    def half_width(self) -> float:
        return (self.hi - self.lo) / 2

    @property
    def excludes_zero(self) -> bool:
        return self.lo > 0 or self.hi < 0

    def fmt(self, signed: bool = False) -> str:
        f = "{:+.3f}" if signed else "{:.3f}"
        return f"{f.format(self.mean)} [{f.format(self.lo)}, {f.format(self.hi)}]"


def cluster_means(
    records: Iterable[Mapping],
    key: str = "iou",
    by: tuple[str, ...] = ("seed", "query"),
) -> dict[tuple, float]:
    """Mean of `key` per cluster (the values of the `by` fields) of pair records."""
    acc: dict[tuple, list[float]] = {}
    for r in records:
        acc.setdefault(tuple(r[b] for b in by), []).append(float(r[key]))
    return {c: float(np.mean(v)) for c, v in sorted(acc.items())}


def bootstrap_mean(
    values: np.ndarray,
    n_boot: int = N_BOOT,
    level: float = LEVEL,
    seed: int = 0,
) -> Estimate:
    """Mean of per-cluster values and its percentile bootstrap interval.

    Args:
        values: [n] one value per cluster (finite).
        n_boot: bootstrap resamples (clusters drawn with replacement).
        level: confidence level.
        seed: seeds the resampling (the same data give the same interval).

    Returns:
        The estimate; with fewer than 2 clusters the interval is the point.
    """
    v = np.asarray(values, np.float64).ravel()
    if not np.all(np.isfinite(v)):
        raise ValueError("bootstrap_mean: values must be finite")
    if len(v) == 0:
        raise ValueError("bootstrap_mean: no clusters")
    m = float(v.mean())
    if len(v) < 2:
        return Estimate(m, m, m, len(v))
    rng = np.random.default_rng(seed)
    means = np.empty(n_boot)
    step = max(1, (1 << 22) // len(v))  # resamples per block: bounded memory
    for a in range(0, n_boot, step):
        b = min(n_boot, a + step)
        means[a:b] = v[rng.integers(0, len(v), (b - a, len(v)))].mean(1)
    alpha = (1.0 - level) / 2
    lo, hi = np.quantile(means, [alpha, 1.0 - alpha])
    return Estimate(m, float(lo), float(hi), len(v))


def paired_difference(
    a: Mapping[Hashable, float],
    b: Mapping[Hashable, float],
    n_boot: int = N_BOOT,
    level: float = LEVEL,
    seed: int = 0,
) -> Estimate:
    """Mean of a − b over the clusters both have, with its bootstrap interval."""
    common = [c for c in a if c in b]
    if not common:
        raise ValueError("paired_difference: no cluster in common")
    d = np.array([a[c] - b[c] for c in common])
    return bootstrap_mean(d, n_boot, level, seed)


__all__ = [
    "Estimate",
    "LEVEL",
    "N_BOOT",
    "bootstrap_mean",
    "cluster_means",
    "paired_difference",
]
