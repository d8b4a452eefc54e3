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
