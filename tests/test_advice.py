"""An error's advice, applied as written, works: for each mistake a user
makes at first contact, the one-line error names a fix; the test takes the fix
from the message itself (a "did you mean", a folder to pass, a name to give),
applies it, and sees the command succeed. Messages about output paths are in
test_outputs.py, config ranges and sections in test_cli.py, SfM's tips in
test_sfm.py."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from click.testing import CliRunner

from conftest import RECON, copy_work
from ptovs.cli import main


@pytest.fixture(scope="module")
def work(tmp_path_factory, trained_work):
    return copy_work(trained_work[0], tmp_path_factory.mktemp("advice") / "work")


def _run(work: Path, *args: str):
    return CliRunner().invoke(main, ["--work-dir", str(work), *RECON, *args])


def _error(res) -> str:
    assert res.exit_code not in (0, None), res.output
    assert "Traceback" not in res.output, res.output
    lines = [ln for ln in res.output.splitlines() if ln.startswith("Error:")]
    assert len(lines) == 1, res.output
    return lines[0]


def _meant(line: str) -> str:
    m = re.search(r"did you mean \[?'?([^'?\]]+)'?\]?\?", line)
    assert m, line
    return m.group(1)


def test_a_misspelt_key_in_each_door_names_the_key_that_runs(
    work, tiny_scene_dir, tmp_path
):
    d = ["--data", str(tiny_scene_dir)]
    doors = {
        "group --set": lambda k: ["--set", f"query.{k}=0.5", "status", *d],
        "stage --set": lambda k: [
            "query",
            *d,
            "--set",
            f"{k}=0.5",
            "Wall",
            "--no-pictures",
        ],  # fmt: skip
    }
    for door, argv in doors.items():
        line = _error(_run(work, *argv("treshold")))
        fixed = _meant(line)
        assert fixed == "threshold", (door, line)
        assert _run(work, *argv(fixed)).exit_code == 0, door
    toml = tmp_path / "my.toml"
    toml.write_text("[querry]\nthreshold = 0.5\n")
    line = _error(_run(work, "--config", str(toml), "status", *d))
    toml.write_text(f"[{_meant(line)}]\nthreshold = 0.5\n")
    assert _run(work, "--config", str(toml), "status", *d).exit_code == 0


def test_a_misspelt_command_names_the_command_that_runs(work):
    line = _error(_run(work, "reconstuct", "--help"))
    assert _run(work, _meant(line), "--help").exit_code == 0


def test_a_folder_inside_a_scene_names_the_scene_folder_that_runs(work, tiny_scene_dir):
    for inner in ("dense", "dense/images", "dense/sparse"):
        line = _error(_run(work, "status", "--data", str(tiny_scene_dir / inner)))
        fixed = line.rsplit("pass --data ", 1)[1].split()[0].rstrip(";,.")
        assert Path(fixed) == tiny_scene_dir, line
        assert _run(work, "status", "--data", fixed).exit_code == 0


def test_an_unknown_phrase_names_the_phrase_that_runs(work, tiny_scene_dir):
    d = ["--data", str(tiny_scene_dir), "--no-pictures"]
    line = _error(_run(work, "query", *d, "Wal"))
    assert _run(work, "query", *d, _meant(line)).exit_code == 0


def test_an_unknown_view_is_told_where_the_names_are_and_one_runs(work,
                                                                  tiny_scene_dir):  # fmt: skip
    d = ["--data", str(tiny_scene_dir), "--no-pictures", "Wall"]
    line = _error(_run(work, "query", *d, "--views", "nope"))
    assert "dense/images" in line, line
    name = sorted((tiny_scene_dir / "dense" / "images").iterdir())[0]
    assert _run(work, "query", *d, "--views", name.stem).exit_code == 0
