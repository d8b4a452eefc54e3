"""The stand-in for CLIP: version 5's features of fixed crops and phrases stay
what tests/data/standin_v5_reference.npz holds (tools/standin_reference.py)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

TOOL = Path(__file__).resolve().parents[1] / "tools" / "standin_reference.py"


def _tool():
    spec = importlib.util.spec_from_file_location("standin_reference", TOOL)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_version_5_matches_its_reference() -> None:
    tool = _tool()
    with np.load(tool.REFERENCE, allow_pickle=False) as f:
        want = {k: f[k] for k in f.files}
    assert tool.REFERENCE.stat().st_size < 300_000
    assert len(want["images"]) >= 20 and len(want["texts"]) >= 8
    got = tool.features()
    assert tool.compare(got, want, tol=1e-5) == []


def test_fit_tool_finds_the_separating_directions() -> None:
    """tools/fit_standin.py's Fisher discriminant: classes apart along one
    statistic, with a larger nuisance along another; the first direction is the
    separating one, the nuisance is ignored."""
    from ptovs.encoders import standin_stats as st

    spec = importlib.util.spec_from_file_location(
        "fit_standin", TOOL.parent / "fit_standin.py"
    )
    fit = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(fit)
    rng = np.random.default_rng(0)
    bank = st._bank()
    mean, sd = bank.mean(0), np.maximum(bank.std(0), 1e-3)
    sep, nui = st._offset("fine"), st._offset("fine") + 1
    rows, cls = [], []
    for c in range(4):
        r = np.tile(mean, (200, 1)) + 0.05 * sd * rng.standard_normal((200, len(mean)))
        r[:, sep] += 0.5 * c * sd[sep]
        r[:, nui] += 2.0 * sd[nui] * rng.standard_normal(200)
        rows.append(r)
        cls += [c] * 200
    raw, cls = np.concatenate(rows), np.array(cls)
    mu, V, scale, ev = fit.fisher(raw, cls, k=3)
    assert ev[0] > 10 * ev[1] and scale > 0 and np.isfinite(V).all()
    z = st.standardised(raw)[0]
    y = (z - mu) @ V[:, 0]
    means = np.array([y[cls == c].mean() for c in range(4)])
    within = np.mean([y[cls == c].std() for c in range(4)])
    assert np.all(np.abs(np.diff(np.sort(means))) > 5 * within)  # classes apart
    assert abs(np.corrcoef(y, raw[:, nui])[0, 1]) < 0.2  # the nuisance ignored
    assert abs(np.corrcoef(y, raw[:, sep])[0, 1]) > 0.95
    # where the leading principal component follows the nuisance
    pc = (z - z.mean(0)) @ np.linalg.svd(z - z.mean(0), full_matrices=False)[2][0]
    assert abs(np.corrcoef(pc, raw[:, nui])[0, 1]) > 0.9
    assert len(fit.bank_lights()) == 7
