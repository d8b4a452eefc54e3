"""The stage framework through the real CLI: cache hits, --force, keys along the
chain, status, corruption, killed processes, resume and concurrent runs."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from click.testing import CliRunner

import toy_stages
from ptovs.cli import main as cli

TOY = Path(toy_stages.__file__)


pytestmark = pytest.mark.usefixtures("toy_commands")


@pytest.fixture
def env(tmp_path: Path, scene_copy: Path, monkeypatch: pytest.MonkeyPatch):
    log = tmp_path / "toy.log"
    monkeypatch.setenv("TOY_LOG", str(log))
    work = tmp_path / "work"

    def invoke(*args: str, ok: bool = True):
        result = CliRunner().invoke(cli, ["--work-dir", str(work), *args])
        if ok:
            assert result.exit_code == 0, result.output + repr(result.exception)
        return result

    def calls() -> list[str]:
        return log.read_text().splitlines() if log.exists() else []

    return dict(invoke=invoke, calls=calls, work=work, data=scene_copy, log=log)


def _h5(work: Path, stage: str) -> list[Path]:
    return sorted((work / "tiny_s0" / stage).glob("*.h5"))


def test_rerun_is_a_cache_hit_and_force_recomputes(env):
    invoke, calls, data = env["invoke"], env["calls"], str(env["data"])
    invoke("toy-views", "--data", data)
    n_views = len(calls())
    assert n_views >= 10  # the tiny preset has ~12 train views
    first = _h5(env["work"], "toy-views")
    assert len(first) == 1
    mtime = first[0].stat().st_mtime_ns
    r = invoke("toy-views", "--data", data)
    assert "cache hit" in r.output
    assert len(calls()) == n_views  # no work done
    assert first[0].stat().st_mtime_ns == mtime
    invoke("toy-views", "--data", data, "--force")
    assert len(calls()) == 2 * n_views
    invoke("--force", "toy-views", "--data", data)  # the group-level flag too
    assert len(calls()) == 3 * n_views
    assert _h5(env["work"], "toy-views") == first  # same key, same file


def test_config_and_upstream_changes_give_new_keys(env):
    invoke, calls, data = env["invoke"], env["calls"], str(env["data"])
    invoke("toy-views", "--data", data)
    invoke("toy-sum", "--data", data)
    (sum1,) = _h5(env["work"], "toy-sum")
    invoke("toy-sum", "--data", data, "--set", "scale=2")  # config → new key
    assert len(_h5(env["work"], "toy-sum")) == 2
    # upstream config change → new toy-views key → new toy-sum key
    r = invoke("toy-sum", "--data", data, "--set", "scale=1", ok=False)
    assert r.exit_code == 0  # same as the first: cache hit
    invoke("--set", "toy-views.gain=3", "toy-views", "--data", data)
    r = invoke("--set", "toy-views.gain=3", "toy-sum", "--data", data)
    assert len(_h5(env["work"], "toy-sum")) == 3
    assert calls().count("sum") == 3


def test_missing_upstream_names_the_fix(env):
    r = env["invoke"]("toy-sum", "--data", str(env["data"]), ok=False)
    assert r.exit_code != 0
    assert "no toy-views artifact for tiny_s0" in r.output
    assert "run: ptovs toy-views --scene tiny_s0" in r.output
    assert "Traceback" not in r.output


def test_bad_config_is_a_clear_error(env, tmp_path: Path):
    r = env["invoke"](
        "toy-views", "--data", str(env["data"]), "--set", "gian=2", ok=False
    )
    assert r.exit_code == 1 and "has no key" in r.output and "gain" in r.output
    bad = tmp_path / "bad.toml"
    bad.write_text("[toy-views\ngain=")
    r = env["invoke"](
        "--config", str(bad), "toy-views", "--data", str(env["data"]), ok=False
    )
    assert r.exit_code == 1 and "bad.toml" in r.output and "TOML" in r.output
    r = env["invoke"]("toy-views", "--data", str(tmp_path / "nowhere"), ok=False)
    assert r.exit_code == 1 and "nowhere" in r.output and "synth-scene" in r.output


def test_a_misspelt_section_or_key_is_an_error_in_every_door(env, tmp_path: Path):
    """The group's --set, a stage's --set and a --config file: a misspelt section
    or key never runs with the default silently, and the error names the fix."""
    data = str(env["data"])
    for args, near in (
        (["--set", "toy-veiws.gain=2", "toy-views", "--data", data], "[toy-views]"),
        (["--set", "toy-views.gian=2", "toy-views", "--data", data], "'gain'"),
        (["toy-views", "--data", data, "--set", "gian=2"], "gain"),
        (["toy-views", "--data", data, "--set", "toy-veiws.gain=2"], "'toy-views'?"),
    ):
        r = env["invoke"](*args, ok=False)
        assert r.exit_code != 0, args
        assert near in r.output and "Traceback" not in r.output, (args, r.output)
    for text, near in (
        ("[toy-veiws]\ngain = 2\n", "did you mean [toy-views]"),
        ("[toy-views]\ngian = 2\n", "did you mean 'gain'"),
        ("[toy-views]\ngain = 'two'\n", "toy-views.gain"),
        ("scene = 3\n", "must be a table"),
    ):
        bad = tmp_path / "bad.toml"
        bad.write_text(text)
        r = env["invoke"]("--config", str(bad), "toy-views", "--data", data, ok=False)
        assert r.exit_code == 1 and near in r.output, (text, r.output)
    assert not (Path(env["work"]) / "tiny_s0" / "toy-views").exists()


def test_status_reports_done_missing_stale(env):
    invoke, data = env["invoke"], str(env["data"])
    r = invoke("status", "--data", data)
    assert "toy-views" in r.output and "missing" in r.output
    invoke("toy-views", "--data", data)
    invoke("toy-sum", "--data", data)
    lines = {
        ln.split()[0]: ln
        for ln in invoke("status", "--data", data).output.splitlines()
        if ln.strip().startswith("toy-")
    }
    assert "done" in lines["toy-views"] and "done" in lines["toy-sum"]
    r = invoke("--set", "toy-views.gain=2", "status", "--data", data)
    lines = {
        ln.split()[0]: ln
        for ln in r.output.splitlines()
        if ln.strip().startswith("toy-")
    }
    assert "stale" in lines["toy-views"] and "config" in lines["toy-views"]
    assert (
        "stale" in lines["toy-sum"] and "upstream changed (views)" in lines["toy-sum"]
    )
    # changing the scene's data changes every key downstream of it
    img = sorted((env["data"] / "dense" / "images").glob("*.jpg"))[0]
    img.write_bytes(img.read_bytes() + b"\0")  # JPEG decoders ignore trailing bytes
    lines = {
        ln.split()[0]: ln
        for ln in invoke("status", "--data", data).output.splitlines()
        if ln.strip().startswith("toy-")
    }
    assert (
        "stale" in lines["toy-views"]
        and "upstream changed (scene)" in lines["toy-views"]
    )


def _tree(root: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns)
            for p in sorted(root.rglob("*"))} if root.exists() else {}  # fmt: skip


def test_read_only_commands_write_nothing(env, tmp_path: Path):
    """status (on an empty work dir, then beside artifacts, from another folder)
    and --help leave the work dir and the scene folder as they were, and status
    says which work dir it read."""
    invoke, data, work = env["invoke"], str(env["data"]), Path(env["work"])
    r = invoke("status", "--data", data)
    assert f"work dir: {work.resolve()}" in r.output
    assert not work.exists()  # not even the fingerprint cache
    invoke("toy-views", "--data", data)
    before = _tree(work), _tree(Path(data))
    for args in (["status", "--data", data], ["--set", "toy-views.gain=3", "status",
                 "--data", data], ["status", "--help"], ["toy-views", "--help"]):  # fmt: skip
        invoke(*args)
    assert (_tree(work), _tree(Path(data))) == before


def test_status_says_corrupt_when_an_artifacts_identity_was_changed(env):
    import h5py

    invoke, data = env["invoke"], str(env["data"])
    invoke("toy-views", "--data", data)
    (path,) = _h5(env["work"], "toy-views")
    with h5py.File(path, "a") as h5:
        h5.attrs["config_json"] = '{"gain": 7}'
    line = next(ln for ln in invoke("status", "--data", data).output.splitlines()
                if ln.strip().startswith("toy-views"))  # fmt: skip
    assert "corrupt" in line and "run: ptovs toy-views" in line
    invoke("toy-views", "--data", data)  # moved aside and recomputed
    assert path.with_name(path.name + ".corrupt").exists()
    line = next(ln for ln in invoke("status", "--data", data).output.splitlines()
                if ln.strip().startswith("toy-views"))  # fmt: skip
    assert "done" in line


def test_a_stage_commands_override_is_kept_for_the_next_command(env):
    """export-ply after `reconstruct --set iterations=400` used to say "no
    reconstruct artifact": the scene now records a stage command's --set items, so
    the next command without --config reads the same chain."""
    invoke, data = env["invoke"], str(env["data"])
    invoke("toy-views", "--data", data, "--set", "gain=2")
    res = invoke("toy-sum", "--data", data)
    assert "using the config recorded for tiny_s0" in res.output
    assert "--set toy-views.gain=2" in res.output
    assert len(_h5(env["work"], "toy-views")) == 1  # not rebuilt at the default


def test_missing_input_under_other_settings_names_the_override(env, tmp_path):
    """With a --config the artifact was not made with, the missing input's message
    lists the existing artifacts' overrides."""
    invoke, data = env["invoke"], str(env["data"])
    invoke("toy-views", "--data", data, "--set", "gain=2")
    other = tmp_path / "other.toml"
    other.write_text("[toy-sum]\nscale = 1.0\n")
    res = invoke("--config", str(other), "toy-sum", "--data", data, ok=False)
    assert res.exit_code == 1 and "Traceback" not in res.output
    assert "made with --set toy-views.gain=2" in res.output, res.output
    assert f"run: ptovs --config {other} toy-views" in res.output  # its settings
    invoke("--config", str(other), "--set", "toy-views.gain=2", "toy-sum",
           "--data", data)  # as it says  # fmt: skip


def test_corrupt_artifact_is_recomputed(env):
    invoke, calls, data = env["invoke"], env["calls"], str(env["data"])
    invoke("toy-views", "--data", data)
    n = len(calls())
    (path,) = _h5(env["work"], "toy-views")
    raw = path.read_bytes()
    path.write_bytes(raw[: len(raw) * 2 // 3])  # truncated
    r = invoke("toy-views", "--data", data)
    assert "cache hit" not in r.output and len(calls()) == 2 * n
    assert path.with_name(path.name + ".corrupt").exists()
    assert "cache hit" in invoke("toy-views", "--data", data).output


def _spawn(env, *args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, str(TOY), "--work-dir", str(env["work"]), *args],
        env={**os.environ, "TOY_LOG": str(env["log"])},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def test_killed_run_leaves_no_valid_artifact_and_resumes(env):
    invoke, calls, data = env["invoke"], env["calls"], str(env["data"])
    proc = _spawn(env, "toy-views", "--data", data, "--set", "sleep=0.3")
    deadline = time.time() + 60
    while len(calls()) < 4 and time.time() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)  # no chance to clean up
    proc.wait()
    done_before = calls()
    assert len(done_before) >= 4
    assert _h5(env["work"], "toy-views") == []  # nothing final, nothing valid
    status = invoke("--set", "toy-views.sleep=0.3", "status", "--data", data).output
    assert "partial" in status
    invoke("--set", "toy-views.sleep=0.3", "toy-views", "--data", data)
    after = calls()[len(done_before) :]
    n_train = sum(
        1
        for ln in (env["data"] / "tiny.tsv").read_text().splitlines()
        if "\ttrain\t" in ln
    )
    # only the views not yet stored are computed again (the one in flight at the
    # kill may or may not have been stored)
    assert n_train - len(done_before) <= len(after) <= n_train - len(done_before) + 1
    assert len(set(after) | set(done_before)) == n_train
    (path,) = _h5(env["work"], "toy-views")
    from ptovs.artifacts import Artifact

    with Artifact(path) as art:
        assert len(art.names()) == n_train


def test_concurrent_runs_do_not_corrupt(env):
    data = str(env["data"])
    procs = [
        _spawn(env, "toy-views", "--data", data, "--set", "sleep=0.05")
        for _ in range(2)
    ]
    outs = [p.communicate(timeout=120)[0] for p in procs]
    assert all(p.returncode == 0 for p in procs), outs
    assert (
        sum("cache hit" in o for o in outs) == 1
    )  # one computed, one waited and reused
    names = [c for c in env["calls"]()]
    assert len(names) == len(set(names))  # no view computed twice
    (path,) = _h5(env["work"], "toy-views")
    from ptovs.artifacts import Artifact

    with Artifact(path) as art:
        assert len(art.names()) == len(names)


def test_label_edits_rekey_only_the_stages_that_read_labels(scene_copy: Path):
    """A label edit changes the keys of query and evaluate, and of nothing before
    them: reconstruct and training are reused."""
    from ptovs.chain import Chain, RunContext
    from ptovs.config import load_config
    from ptovs.locate import resolve_scene
    from ptovs.pipeline import PIPELINE

    def keys() -> dict[str, str]:
        ctx = RunContext(scene_copy.parent / "work", load_config(None))
        chain = Chain(ctx, resolve_scene(ctx, None, scene_copy))
        return {stage: chain.key(stage) for stage in PIPELINE}

    before = keys()
    labels = sorted((scene_copy.parent / "label" / scene_copy.name).glob("*.json"))
    assert labels
    labels[0].write_text(labels[0].read_text() + "\n")  # same labels, new bytes
    after = keys()
    changed = {stage for stage in PIPELINE if before[stage] != after[stage]}
    assert changed == {"query", "evaluate"}
