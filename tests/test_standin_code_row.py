"""bench/standin_profile.py's scene-code row: crops read
through the chain's 3-d autoencoder. A scene whose crops form a few tight concept
clusters keeps its closed-set accuracy through the code, even under isotropic noise
in many dimensions; one whose crops vary more along a few other directions than
their concepts differ loses it (the code spends its 3 dimensions on that
variation); the cluster-bootstrap interval brackets the point figure."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _profile():
    sys.path.insert(0, str(ROOT / "bench"))
    spec = importlib.util.spec_from_file_location(
        "bench_standin_profile", ROOT / "bench" / "standin_profile.py"
    )
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _unit(x: np.ndarray) -> np.ndarray:
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def _scene(spread: float, dims: int, seed: int = 0):
    """Four concepts (text rows) and 400 crops of them: each crop its concept's
    direction plus noise of relative size `spread` in `dims` random directions."""
    rng = np.random.default_rng(seed)
    text = _unit(rng.standard_normal((4, 512)))
    basis = _unit(rng.standard_normal((dims, 512)))
    truth = np.repeat(np.arange(4), 100)
    noise = rng.standard_normal((400, dims)) @ basis * spread / np.sqrt(dims)
    crops = _unit(text[truth] + noise)
    canon = _unit(rng.standard_normal((5, 512)))
    return {"clean": crops}, {"clean": truth}, text, canon


def test_concept_clusters_survive_the_code_and_other_variation_does_not() -> None:
    sp = _profile()
    for spread, dims in ((0.3, 8), (2.5, 400)):  # tight; isotropic in 400-d
        t = np.array(sp.code_rows(*_scene(spread, dims))["crops"])
        assert t.shape == (400, 7)
        assert np.isfinite(t).all()
        assert (t[:, 0] == t[:, 1]).mean() >= 0.95  # raw
        assert (t[:, 0] == t[:, 2]).mean() >= 0.95  # four clusters fit a 3-d code
    spread = np.array(sp.code_rows(*_scene(spread=3.0, dims=6))["crops"])
    raw, code = (
        (spread[:, 0] == spread[:, 1]).mean(),
        (spread[:, 0] == spread[:, 2]).mean(),
    )
    assert raw >= 0.95
    assert code / raw - 1.0 < -0.5  # the code holds the 6-d variation, not the concepts


def test_summary_interval_brackets_the_figure() -> None:
    sp = _profile()
    res = [{"seed": s, "code": sp.code_rows(*_scene(1.5, 300, seed=s))} for s in (0, 1)]
    c = sp.summarise_code(res)
    assert c["n"] == 800
    lo, hi = c["relative_ci"]
    assert lo <= c["relative"] <= hi
    assert -1.0 <= lo <= hi
    assert len(c["heldout_cos"]) == 2
