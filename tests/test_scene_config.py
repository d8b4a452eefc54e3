"""The settings a scene was run with are recorded in its work dir
(`ptovs.scene_config`): every --config file, the group's --set items and a stage
command's own --set items. A later command without --config uses them and says so,
`status` shows the stages done and advises commands that repeat that chain, and a
different --config runs, says that it differs, and is recorded beside the earlier
settings, which `status` names too."""

from __future__ import annotations

import json
import shlex
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
    (run,) = json.loads(env["record"].read_text())["runs"]
    (conf,) = run["configs"]
    assert conf["file"] == str(a.resolve()) and "gain = 2.0" in conf["toml"]
    assert run["command"] == "toy-views" and run["sets"] == []
    r = invoke("status", "--data", data)
    assert _state(r.output, "toy-views") == "done"
    (note,) = _notes(r.output)
    assert note == (
        f"ptovs: using the config recorded for tiny_s0: {env['record']} (from --config {a}); "
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
    assert "in [toy-views]" in note  # the sections that differ
    assert "records nothing" in note and _state(r.output, "toy-views") == "stale"
    assert env["record"].read_text() == before
    # a stage with it: runs, says so, and b becomes the scene's config
    r = invoke("--config", str(b), "toy-views", "--data", data)
    (note,) = _notes(r.output)
    assert "differs" in note and "becomes tiny_s0's recorded config" in note
    runs = json.loads(env["record"].read_text())["runs"]
    assert [r["configs"][0]["file"] for r in runs] == [
        str(a.resolve()),
        str(b.resolve()),
    ]
    r = invoke("status", "--data", data)
    assert f"(from --config {b})" in _notes(r.output)[0]
    assert _state(r.output, "toy-views") == "done"
    # status names both settings the scene was run with, the latest first
    assert f"settings: --config {b} (toy-views, " in r.output
    assert "also run with other settings" in r.output
    assert f"earlier: --config {a} (toy-views, " in r.output
    kept = list((env["record"].parent / "toy-views").glob("*.h5"))
    assert len(kept) == 2  # both configs' artifacts are kept


def test_a_changed_or_deleted_source_file_still_gives_the_recorded_text(env):
    invoke, data = env["invoke"], env["data"]
    a = env["toml"]("a.toml", 2.0)
    invoke("--config", str(a), "toy-views", "--data", data)
    a.write_text("[toy-views]\ngain = 9.0\n")
    r = invoke("status", "--data", data)
    (note,) = _notes(r.output)
    assert f"{a} has changed since: its recorded text is used" in note
    assert _state(r.output, "toy-views") == "done"
    a.unlink()
    r = invoke("status", "--data", data)
    (note,) = _notes(r.output)
    assert f"{a} no longer exists: its recorded text is used" in note
    assert _state(r.output, "toy-views") == "done"


def test_the_groups_set_items_are_part_of_the_recorded_config(env):
    invoke, data = env["invoke"], env["data"]
    a = env["toml"]("a.toml", 2.0)
    invoke("--config", str(a), "--set", "toy-views.gain=5", "toy-views", "--data", data)
    r = invoke("status", "--data", data)
    assert f"(from --config {a} --set toy-views.gain=5)" in _notes(r.output)[0]
    assert _state(r.output, "toy-views") == "done"
    # a --set without --config goes on top of the recorded config, for this command
    r = invoke("--set", "toy-views.gain=7", "status", "--data", data)
    assert _state(r.output, "toy-views") == "stale"
    assert _state(invoke("status", "--data", data).output, "toy-views") == "done"


def test_a_run_without_config_records_the_defaults_and_status_writes_none(env):
    invoke, data = env["invoke"], env["data"]
    r = invoke("--config", str(env["toml"]("a.toml", 2.0)), "status", "--data", data)
    assert _notes(r.output) == [] and not env["record"].exists()  # read-only
    r = invoke("toy-views", "--data", data)
    assert _notes(r.output) == []
    (run,) = json.loads(env["record"].read_text())["runs"]
    assert run["configs"] == [] and run["sets"] == []
    r = invoke("status", "--data", data)
    assert "settings: the defaults (toy-views, " in r.output
    assert _state(r.output, "toy-views") == "done"


def test_a_stage_commands_set_items_are_recorded_and_status_repeats_them(env):
    """`--config A toy-views --set gain=5`: status without --config keys that chain
    (toy-views done, not stale), and the command it advises for the next stage,
    run as printed, uses toy-views' artifact instead of building another."""
    invoke, data = env["invoke"], env["data"]
    a = env["toml"]("a.toml", 2.0)
    invoke("--config", str(a), "toy-views", "--data", data, "--set", "gain=5")
    (run,) = json.loads(env["record"].read_text())["runs"]
    assert run["sets"] == ["toy-views.gain=5.0"] or run["sets"] == ["toy-views.gain=5"]
    r = invoke("status", "--data", data)
    assert _state(r.output, "toy-views") == "done"
    assert "settings: --config" in r.output and "--set toy-views.gain=5" in r.output
    line = next(ln for ln in r.output.splitlines() if ln.strip().startswith("toy-sum"))
    advice = shlex.split(line.split("run: ", 1)[1])
    assert advice[:2] == ["ptovs", "toy-sum"]  # no --config: the recorded settings
    r = invoke(*advice[1:])
    assert len(_notes(r.output)) == 1  # "using the config recorded for ..."
    views = env["record"].parent / "toy-views"
    assert len(list(views.glob("*.h5"))) == 1  # nothing rebuilt under other settings
    r = invoke("status", "--data", data)
    assert _state(r.output, "toy-views") == "done"
    assert _state(r.output, "toy-sum") == "done"
    assert "also run with other settings" not in r.output  # the same settings


def test_a_set_without_config_goes_on_the_recorded_settings_and_is_recorded(env):
    invoke, data = env["invoke"], env["data"]
    a = env["toml"]("a.toml", 2.0)
    invoke("--config", str(a), "toy-views", "--data", data)
    invoke("toy-sum", "--data", data, "--set", "scale=3")
    (*_, run) = json.loads(env["record"].read_text())["runs"]
    assert run["configs"][0]["file"] == str(a.resolve())
    assert run["sets"] == ["toy-sum.scale=3"] and run["command"] == "toy-sum"
    r = invoke("status", "--data", data)
    assert _state(r.output, "toy-views") == "done"  # a.toml's chain, kept
    assert _state(r.output, "toy-sum") == "done"  # with the scale it ran with
    assert f"earlier: --config {a} (toy-views, " in r.output


def test_config_files_compose_later_ones_winning_key_by_key(env, tmp_path):
    invoke, data = env["invoke"], env["data"]
    a = env["toml"]("a.toml", 2.0)
    b = tmp_path / "b.toml"
    b.write_text("[toy-sum]\nscale = 4.0\n")
    c = env["toml"]("c.toml", 3.0)
    r = invoke("--config", str(a), "--config", str(b), "--config", str(c),
               "toy-views", "--data", data)  # fmt: skip
    views = env["record"].parent / "toy-views"
    (art,) = views.glob("*.h5")
    import h5py

    with h5py.File(art) as f:
        assert json.loads(f.attrs["config_json"])["gain"] == 3.0  # c over a
    (run,) = json.loads(env["record"].read_text())["runs"]
    assert [x["given"] for x in run["configs"]] == [str(a), str(b), str(c)]
    invoke("toy-sum", "--data", data)  # the recorded three: b's scale, c's gain
    r = invoke("status", "--data", data)
    assert _state(r.output, "toy-views") == "done"
    assert f"settings: --config {a} --config {b} --config {c}" in r.output
    with h5py.File(next((env["record"].parent / "toy-sum").glob("*.h5"))) as f:
        assert json.loads(f.attrs["config_json"])["scale"] == 4.0
    # the same files in another order are other settings
    r = invoke("--config", str(c), "--config", str(a), "status", "--data", data)
    assert _state(r.output, "toy-views") == "stale"
    assert "differs" in _notes(r.output)[0] and "[toy-views]" in _notes(r.output)[0]


def test_the_first_records_layout_is_still_read(env):
    invoke, data = env["invoke"], env["data"]
    a = env["toml"]("a.toml", 2.0)
    invoke("--config", str(a), "toy-views", "--data", data)
    text = a.read_text()
    env["record"].write_text(json.dumps({
        "version": 1, "file": str(a.resolve()), "given": str(a),
        "sha256": __import__("hashlib").sha256(text.encode()).hexdigest(),
        "sets": [], "toml": text,
    }))  # fmt: skip
    r = invoke("status", "--data", data)
    assert _state(r.output, "toy-views") == "done"
    assert f"(from --config {a})" in _notes(r.output)[0]


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


def test_a_command_that_fails_leaves_the_recorded_settings_as_they_were(env):
    """A --set that makes a stage fail is not adopted by the next command."""
    invoke, data = env["invoke"], env["data"]
    a = env["toml"]("a.toml", 2.0)
    invoke("--config", str(a), "toy-views", "--data", data)
    before = env["record"].read_text()
    image = sorted((Path(data) / "dense" / "images").iterdir())[0]
    good = image.read_bytes()
    image.write_bytes(b"not an image")  # passes the checks, fails in the stage
    r = invoke("toy-views", "--data", data, "--set", "gain=9", ok=False)
    assert r.exit_code == 1 and "could not decode" in r.output, r.output
    assert env["record"].read_text() == before
    image.write_bytes(good)
    r = invoke("status", "--data", data)
    assert "gain=9" not in r.output
    assert _state(r.output, "toy-views") == "done"  # a.toml's chain, as recorded
