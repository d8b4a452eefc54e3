"""The config a scene was run with is recorded in its work dir (`ptovs.scene_config`):
a later command without --config uses it and says so, `status` shows the stages
done, and a different --config runs, says that it differs, and is recorded."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from click.testing import CliRunner

from ptovs.cli import main as cli

pytestmark = pytest.mark.usefixtures("toy_commands")


@pytest.fixture
def env(tmp_path: Path, scene_copy: Path):
    work = tmp_path / "work"

    def invoke(*args: str, ok: bool = True):
        r = CliRunner().invoke(cli, ["--work-dir", str(work), *args])
        if ok:
            assert r.exit_code == 0, r.output + repr(r.exception)
        return r

    def toml(name: str, gain: float) -> Path:
        path = tmp_path / name
        path.write_text(f"[toy-views]\ngain = {gain}\n")
        return path

    record = work / scene_copy.name / "config.json"
    return dict(invoke=invoke, toml=toml, data=str(scene_copy), record=record)


def _state(output: str, stage: str) -> str:
    line = next(ln for ln in output.splitlines() if ln.strip().startswith(stage + " "))
    return line.split()[2]


def _notes(output: str) -> list[str]:
    return [ln for ln in output.splitlines() if "config recorded for" in ln]


def test_status_without_config_uses_the_recorded_one(env):
    invoke, data = env["invoke"], env["data"]
    a = env["toml"]("a.toml", 2.0)
    r = invoke("--config", str(a), "toy-views", "--data", data)
    assert _notes(r.output) == []  # first run: recorded, nothing to warn about
    rec = json.loads(env["record"].read_text())
    assert rec["file"] == str(a.resolve()) and "gain = 2.0" in rec["toml"]
    r = invoke("status", "--data", data)
    assert _state(r.output, "toy-views") == "done"
    (note,) = _notes(r.output)
    assert note == (
        f"ptovs: using the config recorded for tiny_s0: {env['record']} (from {a}); "
        "give --config to choose another"
    )
    # a stage command without --config reads the recorded chain's artifacts
    r = invoke("toy-sum", "--data", data)
    assert len(_notes(r.output)) == 1
    assert _state(invoke("status", "--data", data).output, "toy-sum") == "done"
    # the same config again: no line at all
    r = invoke("--config", str(a), "status", "--data", data)
    assert _notes(r.output) == [] and _state(r.output, "toy-views") == "done"


def test_a_different_config_runs_says_so_and_is_recorded(env):
    invoke, data = env["invoke"], env["data"]
    a, b = env["toml"]("a.toml", 2.0), env["toml"]("b.toml", 3.0)
    invoke("--config", str(a), "toy-views", "--data", data)
    before = env["record"].read_text()
    # status with another --config: says so, shows its keys, records nothing
    r = invoke("--config", str(b), "status", "--data", data)
    (note,) = _notes(r.output)
    assert f"--config {b} differs from the config recorded for tiny_s0" in note
    assert "records nothing" in note and _state(r.output, "toy-views") == "stale"
    assert env["record"].read_text() == before
    # a stage with it: runs, says so, and b becomes the scene's config
    r = invoke("--config", str(b), "toy-views", "--data", data)
    (note,) = _notes(r.output)
    assert "differs" in note and "becomes tiny_s0's recorded config" in note
    assert json.loads(env["record"].read_text())["file"] == str(b.resolve())
    r = invoke("status", "--data", data)
    assert f"(from {b})" in _notes(r.output)[0]
    assert _state(r.output, "toy-views") == "done"
    kept = list((env["record"].parent / "toy-views").glob("*.h5"))
    assert len(kept) == 2  # both configs' artifacts are kept


def test_a_changed_or_deleted_source_file_still_gives_the_recorded_text(env):
    invoke, data = env["invoke"], env["data"]
    a = env["toml"]("a.toml", 2.0)
    invoke("--config", str(a), "toy-views", "--data", data)
    a.write_text("[toy-views]\ngain = 9.0\n")
    r = invoke("status", "--data", data)
    (note,) = _notes(r.output)
    assert "which has changed since: its recorded text is used" in note
    assert _state(r.output, "toy-views") == "done"
    a.unlink()
    r = invoke("status", "--data", data)
    (note,) = _notes(r.output)
    assert "which no longer exists: its recorded text is used" in note
    assert _state(r.output, "toy-views") == "done"


def test_the_groups_set_items_are_part_of_the_recorded_config(env):
    invoke, data = env["invoke"], env["data"]
    a = env["toml"]("a.toml", 2.0)
    invoke("--config", str(a), "--set", "toy-views.gain=5", "toy-views", "--data", data)
    r = invoke("status", "--data", data)
    assert f"(from {a} --set toy-views.gain=5)" in _notes(r.output)[0]
    assert _state(r.output, "toy-views") == "done"
    # a --set without --config goes on top of the recorded config, for this command
    r = invoke("--set", "toy-views.gain=7", "status", "--data", data)
    assert _state(r.output, "toy-views") == "stale"
    assert _state(invoke("status", "--data", data).output, "toy-views") == "done"


def test_no_config_no_record_and_status_writes_none(env):
    invoke, data = env["invoke"], env["data"]
    r = invoke("toy-views", "--data", data)
    assert _notes(r.output) == [] and not env["record"].exists()
    r = invoke("--config", str(env["toml"]("a.toml", 2.0)), "status", "--data", data)
    assert _notes(r.output) == [] and not env["record"].exists()


def test_a_damaged_record_names_the_fix(env):
    invoke, data = env["invoke"], env["data"]
    env["record"].parent.mkdir(parents=True)
    env["record"].write_text("{not json")
    r = invoke("status", "--data", data, ok=False)
    assert r.exit_code == 1
    assert f"the config recorded for this scene, {env['record']}, is damaged" in (
        r.output
    )
    assert "give --config FILE" in r.output and "Traceback" not in r.output
