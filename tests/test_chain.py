"""The CI smoke run: every implemented stage, in pipeline order, on `tiny`, via the CLI.

Each stage runs as `ptovs --config configs/ci.toml <stage>` in a real process, then
`ptovs status` must show the whole chain done. Stages join this test by existing.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from ptovs.stage import PIPELINE
from ptovs.stages import STAGE_MODULES

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
