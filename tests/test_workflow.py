"""The batch drivers: `make all` and the Snakemake workflow over tiny scenes, one
list of stages and scenes for both, the resource table, resume, and the workflow
on a real single-node Slurm (`make test-slurm` runs that one alone)."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from conftest import copy_work, need_slurm_host
from ptovs.pipeline import (
    FLOOR_MB,
    PIPELINE,
    REF_PHOTOS,
    RESOURCES,
    SCENE_NAME,
    SceneNameError,
    check_scene_names,
    is_scene_name,
    rule_name,
    scene_folders,
    scene_photos,
)

ROOT = Path(__file__).resolve().parents[1]
SNAKEFILE = ROOT / "workflow" / "Snakefile"
# the conftest chain's reconstruct (conftest.RECON) as a config file
FAST = "[reconstruct]\niterations = 300\nmask_warmup = 100\n"


def snakemake(cwd: Path, *args: str) -> subprocess.CompletedProcess:
    """The workflow, run from `cwd` (where Snakemake keeps its .snakemake records)."""
    cmd = [sys.executable, "-m", "snakemake", "-s", str(SNAKEFILE), *args]
    return subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)


def local(data: Path, work: Path, config: Path, *extra: str) -> list[str]:
    return ["--profile", str(ROOT / "workflow" / "profiles" / "local"), "--cores", "2",
            "--config", f"data={data}", f"work={work}", f"config={config}", *extra]  # fmt: skip


def table_rows(table: str) -> list[str]:
    """The table's lines that hold numbers (no paths: the logs differ)."""
    return [line for line in table.splitlines() if line.startswith("|")]


# --------------------------------------------------------- one list, one table --


def test_resource_table_has_every_stage():
    """A new stage must say what it needs on a cluster: this fails until it does."""
    assert set(RESOURCES) == set(PIPELINE), set(PIPELINE) ^ set(RESOURCES)
    for stage, r in RESOURCES.items():
        assert r.threads >= 1 and r.peak_mb > 0 and r.minutes > 0, stage
        assert r.mem_mb >= 1.5 * r.peak_mb and r.mem_mb % 256 == 0, stage
        assert r.device in ("", "device"), stage
        # a scene's size moves its requests one way: more photos never ask for less
        sizes = (0, 12, 100, REF_PHOTOS, 2934)
        mems = [r.mem_mb_for(n) for n in sizes]
        assert mems == sorted(mems) and mems[0] >= 1.5 * FLOOR_MB, (stage, mems)
        assert mems[3] == r.mem_mb
        assert [r.minutes_for(n) for n in sizes[:4]] == [r.minutes] * 4, stage
        assert r.minutes_for(2 * REF_PHOTOS) == 2 * r.minutes, stage
        if r.mb_per_photo == 0:  # a flat stage asks for the same at any size
            assert len(set(mems)) == 1, (stage, mems)


def test_scene_photos_counts_the_photos_a_stage_reads(tmp_path):
    """dense/images, then images/, then the folder itself; other files do not count."""
    posed = tmp_path / "posed"
    (posed / "dense" / "images").mkdir(parents=True)
    for name in ("a.jpg", "b.PNG", "c.txt"):
        (posed / "dense" / "images" / name).write_bytes(b"")
    (posed / "dense" / "images" / "d.jpg").mkdir()  # a folder named like a photo
    assert scene_photos(posed) == 2
    photos = tmp_path / "photos"
    (photos / "images").mkdir(parents=True)
    (photos / "images" / "x.jpeg").write_bytes(b"")
    (photos / "y.jpg").write_bytes(b"")
    assert scene_photos(photos) == 1
    (tmp_path / "flat").mkdir()
    for i in range(3):
        (tmp_path / "flat" / f"{i}.tif").write_bytes(b"")
    assert scene_photos(tmp_path / "flat") == 3
    (tmp_path / "empty" / "dense").mkdir(parents=True)
    assert scene_photos(tmp_path / "empty") == 0
    assert scene_photos(tmp_path / "missing") == 0


def test_workflow_has_a_rule_per_stage(tmp_path):
    (tmp_path / "data" / "a").mkdir(parents=True)
    proc = snakemake(tmp_path, "--list-rules", "--config", f"data={tmp_path / 'data'}",
                     f"work={tmp_path / 'work'}")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    rules = set(proc.stdout.split())
    assert {rule_name(s) for s in PIPELINE} | {"all"} <= rules, proc.stdout


def test_makefile_and_workflow_read_one_scene_list(tmp_path):
    data = tmp_path / "data"
    for name in ("b", "a", "label", ".hidden"):
        (data / name).mkdir(parents=True)
    (data / "notes.txt").write_text("not a scene")
    make = subprocess.run(["make", "-s", "print-SCENES", f"DATA={data}"], cwd=ROOT,
                          capture_output=True, text=True, check=True)  # fmt: skip
    assert make.stdout.split() == [p.name for p in scene_folders(data)] == ["a", "b"]
    stdlib = subprocess.run(  # the system Python, no venv: what make runs
        ["python3", "-m", "ptovs.pipeline", "scenes", str(data)],
        env={**os.environ, "PYTHONPATH": str(ROOT / "src")}, capture_output=True,
        text=True, check=True,
    )  # fmt: skip
    assert stdlib.stdout.split() == ["a", "b"]


def test_workflow_refuses_a_missing_data_folder(tmp_path):
    proc = snakemake(
        tmp_path, "-n", "--cores", "1", "--config", f"data={tmp_path / 'x'}"
    )
    assert proc.returncode != 0
    assert "no scene folders under" in proc.stdout + proc.stderr
    proc = snakemake(tmp_path, "-n", "--cores", "1")
    assert "--config data=DIR" in proc.stdout + proc.stderr


# ------------------------------------------------ scene names into a shell --

# the names in use (tests, README, bench, PT-OVS / PhotoTourism, real sets)
NORMAL = ["tiny_s0", "bench_s1", "small_s17", "broken", "fountain_p11", "herzjesu_p8",
          "brandenburg_gate", "notre_dame_front_facade", "trevi_fountain", "Scene.v2-b"]  # fmt: skip
# folder names that ran a command when a driver put them in a shell unquoted
HOSTILE = ["x;touch INJECTED;", "$(touch INJECTED2)", "`touch INJECTED3`",
           "a b", "it's", 'say "hi"', "new\nline", "-rf"]  # fmt: skip


def hostile_data(root: Path) -> Path:
    """A data folder with a normal scene and every HOSTILE name as a folder."""
    data = root / "data"
    for name in ("tiny_s0", "label", ".hidden", *HOSTILE):
        (data / name).mkdir(parents=True)
    return data


def assert_nothing_injected(*folders: Path) -> None:
    for folder in (*folders, ROOT, Path.cwd()):
        assert not list(folder.glob("INJECTED*")), folder
    for folder in folders:
        assert not list(folder.rglob("INJECTED*")), folder


def assert_refused(
    output: str, names: list[str], fix: str = "rename the folder"
) -> None:
    assert "not allowed" in output and fix in output, output
    assert "letters, digits, '.', '_' and '-'" in output, output
    for name in names:
        assert repr(name) in output, (name, output)


def test_scene_name_pattern_admits_the_names_in_use_and_no_shell_syntax(tmp_path):
    for name in NORMAL:
        assert is_scene_name(name), name
        assert re.fullmatch(SCENE_NAME, name), name
    for name in [*HOSTILE, "", ".", "..", ".hidden", "a/b", "-", "_x", "caf\u00e9", "a\n",
                 "a\x00b", "tab\tx", "x|y", "x&y", "x>y", "x*", "~x", "{scene}"]:  # fmt: skip
        assert not is_scene_name(name), name
    assert check_scene_names(NORMAL, "here") == NORMAL
    with pytest.raises(SceneNameError, match="not allowed in here"):
        check_scene_names(["ok", "x;y"], "here")
    data = tmp_path / "data"
    for name in NORMAL:
        (data / name).mkdir(parents=True)
    assert [p.name for p in scene_folders(data)] == sorted(NORMAL)


def test_workflow_refuses_scene_names_a_shell_would_run(tmp_path):
    """A scene folder (or a --config scenes= name) that is not a SCENE_NAME stops
    the workflow before any job, with the names and the fix; nothing runs. A real
    run (not -n): had a job started, `true ARGS` would have run the injection."""
    data = hostile_data(tmp_path)
    run = tmp_path / "run"
    run.mkdir()
    work = tmp_path / "work"
    proc = snakemake(run, "--cores", "1", "--config", f"data={data}", f"work={work}",
                     "ptovs=true")  # fmt: skip
    assert proc.returncode != 0, proc.stdout
    assert_refused(proc.stdout + proc.stderr, HOSTILE)
    assert "WorkflowError" in proc.stdout + proc.stderr
    good = tmp_path / "good"
    (good / "tiny_s0").mkdir(parents=True)
    given = "tiny_s0 x;touch INJECTED; $(touch INJECTED2) `touch INJECTED3`"
    proc = snakemake(run, "--cores", "1", "--config", f"data={good}", f"work={work}",
                     "ptovs=true", f"scenes={given}")  # fmt: skip
    assert proc.returncode != 0, proc.stdout
    assert_refused(proc.stdout + proc.stderr, ["x;touch", "$(touch", "`touch"],
                   fix="give other names")  # fmt: skip
    assert not work.exists() and not (run / "tiny_s0").exists()
    assert_nothing_injected(tmp_path, data, run)


def test_make_refuses_scene_names_a_shell_would_run(tmp_path):
    """`make all` (and print-SCENES, and the stdlib lister it calls) over the same
    folder: refused at parse time with the message; no recipe runs, nothing made."""
    data = hostile_data(tmp_path)
    work = tmp_path / "work"
    for goal in ("all", "print-SCENES"):
        made = subprocess.run(["make", "-s", goal, f"DATA={data}", f"WORK={work}", "SETUP=",
                               "PTOVS_BIN=true"], cwd=ROOT, capture_output=True,
                              text=True)  # fmt: skip
        assert made.returncode != 0, made.stdout
        assert made.stdout == "", made.stdout
        assert_refused(made.stderr, HOSTILE)
        assert "nothing was run" in made.stderr, made.stderr
    given = subprocess.run(["make", "-s", "all", "SCENES=tiny_s0 x;touch INJECTED;",
                            f"DATA={tmp_path / 'none'}", f"WORK={work}", "SETUP=",
                            "PTOVS_BIN=true"], cwd=ROOT, capture_output=True,
                           text=True)  # fmt: skip
    assert given.returncode != 0, given.stdout
    assert_refused(given.stderr, ["x;touch"], fix="give other names")
    stdlib = subprocess.run(  # the system Python, no venv: what make runs
        ["python3", "-m", "ptovs.pipeline", "scenes", str(data)],
        env={**os.environ, "PYTHONPATH": str(ROOT / "src")}, capture_output=True,
        text=True,
    )  # fmt: skip
    assert stdlib.returncode == 3 and stdlib.stdout == ""
    assert_refused(stdlib.stderr, HOSTILE)
    assert not work.exists()
    assert_nothing_injected(tmp_path, data)


def test_drivers_admit_the_names_in_use(tmp_path):
    """make's scene list and the workflow's wildcard constraint take every NORMAL
    name: one job chain per scene in a dry run."""
    data = tmp_path / "data"
    for name in NORMAL:
        (data / name).mkdir(parents=True)
    made = subprocess.run(["make", "-s", "print-SCENES", f"DATA={data}"], cwd=ROOT,
                          capture_output=True, text=True, check=True)  # fmt: skip
    assert made.stdout.split() == sorted(NORMAL)
    proc = snakemake(tmp_path, "-n", "--cores", "1", "--config", f"data={data}",
                     f"work={tmp_path / 'work'}")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout + proc.stderr
    for name in NORMAL:
        assert out.count(f"wildcards: scene={name}\n") == len(PIPELINE), name


@pytest.fixture(scope="module")
def batch_data(tmp_path_factory, tiny_scene_dir, trained_work):
    """Two tiny scenes (seed 0 with its trained chain to copy, seed 1 to train) and
    a broken one (no model: reconstruct fails), with the conftest chain's config."""
    from ptovs.synthetic import generate_scene

    root = tmp_path_factory.mktemp("batch")
    data = root / "data"
    name = tiny_scene_dir.name
    shutil.copytree(tiny_scene_dir, data / name)
    shutil.copytree(tiny_scene_dir.parent / "label" / name, data / "label" / name)
    generate_scene(data, preset="tiny", seed=1, progress=False)
    (data / "broken" / "dense").mkdir(parents=True)
    config = root / "fast.toml"
    config.write_text(FAST)
    return data, config, trained_work[0] / name


def fresh_work(path: Path, seed0_chain: Path) -> Path:
    copy_work(seed0_chain, path / seed0_chain.name)
    return path


@pytest.fixture(scope="module")
def make_all(batch_data, tmp_path_factory):
    """`make -j2 all` from the seed-0 chain alone: (work dir, its output)."""
    data, config, seed0 = batch_data
    if shutil.which("make") is None:
        pytest.fail("GNU make is needed for the batch target")
    work = fresh_work(tmp_path_factory.mktemp("make"), seed0)
    cmd = ["make", "-s", "-j2", "all", f"DATA={data}", f"WORK={work}", f"CONFIG={config}",
           "SETUP=", f"PTOVS_BIN={sys.executable} -m ptovs"]  # fmt: skip
    made = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    assert made.returncode != 0, made.stdout  # --strict: a scene has no numbers
    assert (work / "table.md").read_text() in made.stdout
    return work


def check_batch(work: Path, log: str, reference: Path) -> None:
    """The table `make all` wrote under `reference`, digit for digit; broken marked."""
    table = (work / "table.md").read_text()
    assert table_rows(table) == table_rows((reference / "table.md").read_text())
    head = next(x for x in table.splitlines() if x.startswith("| variant"))
    assert head == "| variant | broken | tiny_s0 | tiny_s1 | mean |"
    row = next(x for x in table.splitlines() if x.startswith("| male"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1] == "failed" and cells[4].endswith("*")
    for cell in cells[2:4]:
        values = [float(x) for x in cell.split(" / ")]
        assert len(values) == 3 and all(0.0 <= v <= 1.0 for v in values)
    failed = (work / "broken" / "FAILED").read_text()
    assert f"reconstruct failed; see {work / 'broken' / log}" in failed
    assert "broken: failed (reconstruct failed" in table


def test_make_all_and_the_local_profile_give_one_table(batch_data, make_all, tmp_path):
    """`make -j2 all` and the workflow's local profile, each from the seed-0 chain
    alone: seed 1 is trained by each, broken is marked by each, and the per-scene
    tables are the same, digit for digit."""
    data, config, seed0 = batch_data
    check_batch(make_all, "run.log", make_all)
    w_smk = fresh_work(tmp_path / "smk", seed0)
    smk = snakemake(tmp_path, *local(data, w_smk, config))
    assert smk.returncode != 0, smk.stdout  # a job failed (and --strict)
    check_batch(w_smk, "log/reconstruct.log", make_all)
    assert not (w_smk / "broken" / "done" / "reconstruct.json").exists()  # no target
    # the workflow's targets name the artifacts the table read
    for stage in PIPELINE:
        record = json.loads((w_smk / "tiny_s1" / "done" / f"{stage}.json").read_text())
        art = record["artifacts"]["male"]
        assert record["stage"] == stage and Path(art["path"]).is_file()
        assert Path(art["path"]).stem == art["key"][:12]
        mine = make_all / "tiny_s1" / stage / Path(art["path"]).name
        assert mine.is_file(), f"make and the workflow keyed {stage} differently"
        bench = (w_smk / "tiny_s1" / "bench" / f"{stage}.tsv").read_text().splitlines()
        assert bench[0].split("\t")[:3] == ["s", "h:m:s", "max_rss"]


def test_stages_the_config_puts_on_a_gpu_go_to_the_gpu_partition(batch_data, tmp_path):
    data, _, _ = batch_data
    config = tmp_path / "gpu.toml"
    config.write_text(FAST + '[extract-features]\ndevice = "cuda"\n')
    proc = snakemake(tmp_path, "-n", *local(data, tmp_path / "w", config,
                                            "gpu_partition=a100"))  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    jobs = re.split(r"\n(?:local)?rule ", proc.stdout + proc.stderr)[1:]
    jobs = {j.split(":", 1)[0]: j for j in jobs if "wildcards: scene=tiny_s1" in j}
    assert "slurm_partition=a100" in jobs["extract_features"]
    assert "gpu=1" in jobs["extract_features"]
    for rule in ("reconstruct", "uncertainty", "query"):
        assert "slurm_partition" not in jobs[rule] and "gpu=" not in jobs[rule]


def _artifacts(work: Path) -> dict[str, float]:
    return {str(p.relative_to(work)): p.stat().st_mtime_ns
            for p in work.rglob("*.h5")}  # fmt: skip


def test_killed_workflow_resumes_from_its_cache(batch_data, tmp_path):
    """Kill the workflow while a stage runs; the rerun leaves every finished stage
    alone (same done-files, same artifacts) and finishes. Then a config edited
    (Snakemake reruns every rule) costs only cache hits: no artifact rewritten."""
    data, shared, _ = batch_data
    config = tmp_path / "fast.toml"
    shutil.copy(shared, config)
    only = tmp_path / "data"  # seed 1 alone, from nothing
    shutil.copytree(data / "tiny_s1", only / "tiny_s1")
    shutil.copytree(data / "label" / "tiny_s1", only / "label" / "tiny_s1")
    work = tmp_path / "work"
    cmd = [
        sys.executable,
        "-m",
        "snakemake",
        "-s",
        str(SNAKEFILE),
        *local(only, work, config),
    ]
    proc = subprocess.Popen(cmd, cwd=tmp_path, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)  # fmt: skip
    first = work / "tiny_s1" / "done" / "reconstruct.json"
    second = work / "tiny_s1" / "log" / "render-appearances.log"
    deadline = time.monotonic() + 600
    while not (first.exists() and second.exists()) and time.monotonic() < deadline:
        assert proc.poll() is None, "the workflow ended before it could be killed"
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGTERM)  # snakemake and its running job
    proc.wait(60)
    assert not (work / "tiny_s1" / "done" / "evaluate.json").exists()
    before = first.read_text(), first.stat().st_mtime_ns
    recon = _artifacts(work / "tiny_s1" / "reconstruct")
    assert len(recon) == 1

    again = snakemake(tmp_path, *local(only, work, config))
    assert again.returncode == 0, again.stdout + again.stderr
    assert (first.read_text(), first.stat().st_mtime_ns) == before
    assert "rule reconstruct:" not in again.stdout + again.stderr
    assert _artifacts(work / "tiny_s1" / "reconstruct") == recon
    assert "| male | " in (work / "table.md").read_text()

    arts = _artifacts(work)
    keys = {s: (work / "tiny_s1" / "done" / f"{s}.json").read_text() for s in PIPELINE}
    with config.open("a") as f:  # an edit that changes no stage: Snakemake
        f.write("# a comment\n")  # sees a new input and reruns every rule
    third = snakemake(tmp_path, *local(only, work, config))
    assert third.returncode == 0, third.stdout + third.stderr
    assert "rule reconstruct:" in third.stdout + third.stderr  # it did rerun ...
    assert _artifacts(work) == arts  # ... and every stage was a cache hit
    assert keys == {
        s: (work / "tiny_s1" / "done" / f"{s}.json").read_text() for s in PIPELINE
    }


# ------------------------------------------------- a real Slurm, single node --

SLURM_LOCAL = ROOT / "workflow" / "slurm-local"
SLURM_NEEDS = (
    "munged",
    "mariadbd",
    "slurmdbd",
    "slurmctld",
    "slurmd",
    "sbatch",
    "sacct",
)


@pytest.fixture(scope="module")
def slurm_cluster():
    """munged, MariaDB, slurmdbd, slurmctld and slurmd on 127.0.0.1 in a temporary
    folder (workflow/slurm-local/start.sh): the environment its clients need. Fails,
    never skips, when they cannot start, saying what failed."""
    need_slurm_host(SLURM_NEEDS)
    folder = Path(tempfile.mkdtemp(prefix="ptovs-slurm-", dir="/tmp"))
    start = subprocess.run(["bash", str(SLURM_LOCAL / "start.sh"), str(folder)],
                           capture_output=True, text=True, timeout=300)  # fmt: skip
    try:
        if start.returncode != 0:
            pytest.fail(f"the single-node Slurm did not start:\n{start.stderr[-4000:]}")
        path = f"{folder / 'bin'}:{os.environ['PATH']}"
        yield {**os.environ, "SLURM_CONF": str(folder / "slurm.conf"), "PATH": path}
    finally:
        subprocess.run(["bash", str(SLURM_LOCAL / "stop.sh"), str(folder)],
                       capture_output=True, timeout=120)  # fmt: skip
        shutil.rmtree(folder, ignore_errors=True)


@pytest.mark.slurm
def test_slurm_profile_gives_make_alls_table(batch_data, make_all, slurm_cluster,
                                             tmp_path):  # fmt: skip
    """The slurm profile on a single-node cluster: one job per stage and scene, the
    same table as `make all`, broken marked; sacct has every job, with its wall
    time, memory and the rule and scene it ran; broken's reconstruct came back once
    with twice the memory (retries)."""
    data, config, seed0 = batch_data
    work = fresh_work(tmp_path / "work", seed0)
    cmd = [sys.executable, "-m", "snakemake", "-s", str(SNAKEFILE),
           "--profile", str(ROOT / "workflow" / "profiles" / "slurm"),
           "--default-resources", "slurm_partition=cpu", "slurm_account=ptovs",
           "--max-threads", "1",  # the test node has 2 CPUs
           "--slurm-init-seconds-before-status-checks", "2", "--latency-wait", "5",
           "--config", f"data={data}", f"work={work}", f"config={config}"]  # fmt: skip
    proc = subprocess.run(cmd, cwd=tmp_path, env=slurm_cluster, capture_output=True,
                          text=True, timeout=1200)  # fmt: skip
    assert proc.returncode != 0, proc.stdout[-3000:]  # broken failed (and --strict)
    check_batch(work, "log/reconstruct.log", make_all)

    fields = "JobID,Comment%80,Partition,State,Elapsed,ReqMem,AllocCPUS,MaxRSS"
    acct = subprocess.run(["sacct", "-a", "-P", "-o", fields], env=slurm_cluster,
                          capture_output=True, text=True, check=True)  # fmt: skip
    rows = [dict(zip(fields.replace("%80", "").split(","), line.split("|"), strict=True))
            for line in acct.stdout.splitlines()[1:]]  # fmt: skip
    jobs = {r["JobID"]: r for r in rows if "." not in r["JobID"]}
    steps = {r["JobID"].split(".")[0]: r for r in rows if r["JobID"].endswith(".0")}
    unsampled = []
    for scene in ("tiny_s0", "tiny_s1"):
        for stage in PIPELINE:
            tag = f"rule_{rule_name(stage)}_wildcards_{scene}"
            done = [j for j, r in jobs.items() if r["Comment"] == tag]
            assert len(done) == 1, (tag, acct.stdout)
            job, step = jobs[done[0]], steps[done[0]]
            assert job["State"] == "COMPLETED" and job["Partition"] == "cpu"
            assert job["AllocCPUS"] == "1" and job["Elapsed"] != "00:00:00"
            mem = RESOURCES[stage].mem_mb_for(scene_photos(data / scene))
            assert _mb(job["ReqMem"]) == mem
            if not step["MaxRSS"]:
                # jobacct_gather/linux samples a step every JobAcctGatherFrequency
                # s; a step of a few seconds can end before its first sample
                unsampled.append((tag, step["Elapsed"]))
                continue
            assert 10 < _mb(step["MaxRSS"]) < mem
    # a stage's memory is checked against its request on nearly every job
    assert len(unsampled) <= 2, (unsampled, acct.stdout)
    broken = [
        r for r in jobs.values() if r["Comment"] == "rule_reconstruct_wildcards_broken"
    ]
    assert [r["State"] for r in broken] == ["FAILED", "FAILED"]
    mem = RESOURCES["reconstruct"].mem_mb_for(0)  # broken holds no photos
    assert [_mb(r["ReqMem"]) for r in broken] == [mem, 2 * mem]


def _mb(text: str) -> float:
    """sacct's memory figures ("2.50G", "602480K", "1280M") in MB (of 1024 KB)."""
    scale = {"K": 1 / 1024, "M": 1.0, "G": 1024.0, "T": 1024.0**2}
    return round(float(text[:-1]) * scale[text[-1]], 1)
