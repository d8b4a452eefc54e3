"""Shared fixtures: one tiny synthetic scene per test session, CLI helpers."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def synth_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder holding the `tiny` synthetic scene (seed 0) in PT-OVS layout."""
    from ptovs.synthetic import generate_scene

    root = tmp_path_factory.mktemp("synth")
    generate_scene(root, preset="tiny", seed=0, progress=False)
    return root


@pytest.fixture(scope="session")
def tiny_scene_dir(synth_root: Path) -> Path:
    """The tiny scene folder (read-only: copy it before changing anything)."""
    return synth_root / "tiny_s0"


@pytest.fixture
def scene_copy(tiny_scene_dir: Path, tmp_path: Path) -> Path:
    """A private, writable copy of the tiny scene (with its labels)."""
    dst = tmp_path / "data"
    shutil.copytree(tiny_scene_dir, dst / tiny_scene_dir.name)
    labels = tiny_scene_dir.parent / "label" / tiny_scene_dir.name
    if labels.is_dir():
        shutil.copytree(labels, dst / "label" / tiny_scene_dir.name)
    return dst / tiny_scene_dir.name
