"""The CI smoke run: every implemented stage, in pipeline order, on `tiny`, via the CLI.

Each stage runs as `ptovs --config configs/ci.toml <stage>` in a real process, then
`ptovs status` must show the whole chain done. Stages join this test by existing.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from ptovs.pipeline import PIPELINE
from ptovs.registry import STAGE_MODULES

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "ci.toml"


def _ptovs(work: Path, *args: str) -> subprocess.CompletedProcess:
    cmd = [
        sys.executable,
        "-m",
        "ptovs",
        "--work-dir",
        str(work),
        "--config",
        str(CONFIG),
    ]
    return subprocess.run([*cmd, *args], capture_output=True, text=True, timeout=900)


def test_whole_chain_on_tiny(tmp_path, tiny_scene_dir):
    stages = [s for s in PIPELINE if s in STAGE_MODULES]
    assert stages, "no stage is implemented"
    work = tmp_path / "work"
    for stage in stages:
        res = _ptovs(work, stage, "--data", str(tiny_scene_dir))
        assert res.returncode == 0, f"{stage} failed:\n{res.stderr[-3000:]}"
        assert "nan" not in res.stdout.lower()
    res = _ptovs(work, "status", "--data", str(tiny_scene_dir))
    assert res.returncode == 0, res.stderr
    for stage in stages:
        line = next(x for x in res.stdout.splitlines() if x.strip().startswith(stage))
        assert " done " in line, line
    if "reconstruct" in stages:
        ply = tmp_path / "tiny.ply"
        res = _ptovs(
            work, "export-ply", "--data", str(tiny_scene_dir), "--out", str(ply)
        )
        assert res.returncode == 0, res.stderr
        assert ply.stat().st_size > 1000


def test_makefile_stages_follow_the_pipeline():
    """The Makefile's STAGES and the CLI's stage groups are the one PIPELINE."""
    from ptovs.registry import EXTRACT_STAGES, TRAIN_STAGES

    root = Path(__file__).resolve().parents[1]
    out = subprocess.run(["make", "-s", "print-STAGES"], cwd=root, capture_output=True,
                         text=True, check=True).stdout  # fmt: skip
    assert tuple(out.split()) == PIPELINE
    assert set(STAGE_MODULES) == {"sfm", *PIPELINE}  # sfm: the stage before the chain
    assert EXTRACT_STAGES == ("render-appearances", "extract-features", "uncertainty")
    assert TRAIN_STAGES == ("train-ae", "train-male")


def test_set_grammar_is_one_for_every_command():
    import click
    import pytest

    from ptovs.options import split_sets

    got = split_sets(
        ["iterations=10", "train-ae.lr=1e-3", "scene.downscale=2", "x.y=a.b=c"],
        (*PIPELINE, "scene", "x"),
        default="train-male",
    )
    assert got["train-male"] == ["iterations=10"]
    assert got["train-ae"] == ["lr=1e-3"]
    assert got["scene"] == ["downscale=2"]
    assert got["x"] == ["y=a.b=c"]
    for bad in (["nope.x=1"], ["iterations=1"], ["train-ae.lr"]):
        with pytest.raises(click.UsageError, match="STAGE.KEY=VALUE"):
            split_sets(bad, PIPELINE)  # no default section: KEY=VALUE is refused
