"""Every stage's speed-up with the thread count (issue 43 item 5).

The default chain, stage by stage, at 1, 2 and, on a machine with more cores, 4, 8
and 16 threads:

python bench/threads.py --preset small --seed 0 --threads 1 2 4 8 16 --work work/threads
python bench/threads.py --preset tiny --threads 1 2 --set reconstruct.iterations=300 \
    --timeout 800                                      # a short schedule, a wall budget
python bench/threads.py --preset landmark --photos 20 --until train-male \
    --set reconstruct.iterations=80 --threads 2 16 8 4  # real photo sizes, few photos

The `--preset` scene of `--seed` (at `--photos` train photos, when given) is generated
once under --data (kept and reused); `--until STAGE` ends the chain after that stage.
Then, one thread count after the other (never two at once), every stage of the chain
(src/ptovs/pipeline.py's PIPELINE) runs in order, each in its own process, exactly as
`make all` runs it, in a work folder emptied first (<work>/t<N>: nothing is cached
from another thread count):

    OMP_NUM_THREADS=N python -m ptovs --work-dir <work>/t<N> --config <config> -q \
        --threads N [--set STAGE.KEY=VALUE ...] <stage> --scene <name> --data <scene>

A `--set` item goes to every stage's command (on the group, as a --config file's key
would): a stage's key holds its upstreams' configs, so `reconstruct.iterations=300`
given to reconstruct alone would leave render-appearances looking for the default
reconstruct. Per stage: its wall time (the parent's clock around the process), the
process's peak RSS (os.wait4's ru_maxrss: the stage and the processes it waited for;
it also counts this small script's pages, ~20 MB, shared between fork and exec), its
exit status and, when it failed, the tail of its stderr. A failed stage ends that
thread count's chain; the next thread count runs. A thread count above os.cpu_count()
is skipped (said so). `--timeout S` is a wall budget for the whole run: the stage
running when it ends is killed (recorded with "timeout": true) and every stage after
it is recorded as skipped. Logs: <work>/t<N>/logs/<stage>.{out,err}.

Results: <work>/threads.json (written after every stage, so a killed run keeps what it
measured; runs of other thread counts from an earlier run with the same preset, seed,
--set items, config and CPU are kept), then a markdown table: a row a stage and the
chain's total, per thread count its seconds and its speed-up over the smallest thread
count measured; and the peak RSS a stage and thread count.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, machine  # noqa: E402  (same folder)

from ptovs.pipeline import PIPELINE  # noqa: E402  (stdlib only: torch stays out)

SECTIONS = ("scene", *PIPELINE)  # what a --set item may name
PRESETS = ("tiny", "small", "bench", "landmark", "scale")  # synth-scene's
# an earlier threads.json's runs are kept when these (and the CPU) are the same
SAME = ("preset", "seed", "photos", "set", "config", "stages")
SAME_MACHINE = ("cpu_model", "cpu_count")


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo ("" where there is none)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith(("model name", "hardware", "cpu model")):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return ""


def machine_facts() -> dict:
    """The machine, and torch's own thread defaults (asked in a fresh process without
    the OpenMP settings, so this process never loads torch)."""
    facts = machine()
    facts.update(
        cpu_count=os.cpu_count(),
        affinity=len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        processor=platform.processor(),
        cpu_model=cpu_model(),
        python=platform.python_version(),
        omp_env={k: os.environ[k] for k in sorted(os.environ)
                 if k.startswith(("OMP_", "GOMP_", "MKL_", "PTOVS_THREADS"))},
    )  # fmt: skip
    env = {k: v for k, v in os.environ.items()
           if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "PTOVS_THREADS")}  # fmt: skip
    probe = (
        "import json, torch; print(json.dumps(dict(torch=torch.__version__, "
        "torch_threads=torch.get_num_threads(), "
        "torch_interop_threads=torch.get_num_interop_threads())))"
    )
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True,
                         text=True)  # fmt: skip
    if out.returncode == 0:
        facts.update(json.loads(out.stdout.strip().splitlines()[-1]))
    else:
        facts["torch_error"] = out.stderr[-1000:]
    git = subprocess.run(["git", "-C", str(ROOT), "describe", "--always", "--dirty"],
                         capture_output=True, text=True)  # fmt: skip
    facts["commit"] = git.stdout.strip()
    return facts


def scene_folder(args: argparse.Namespace) -> tuple[Path, float | None]:
    """The scene folder, generated when missing; (folder, seconds it took or None)."""
    name = f"{args.preset}_s{args.seed}"
    more = []
    if args.photos is not None:  # synth-scene's name and option for a given count
        name, more = f"{name}_p{args.photos}", ["--photos", str(args.photos)]
    scene = args.data / name
    if (scene / "dense").is_dir():
        return scene, None
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "ptovs", "-q", "synth-scene", str(args.data),
                    "--preset", args.preset, "--seed", str(args.seed), *more],
                   check=True)  # fmt: skip
    return scene, round(time.perf_counter() - t0, 1)


def stage_command(args: argparse.Namespace, work: Path, scene: Path, n: int,
                  stage: str) -> list[str]:  # fmt: skip
    """`make all`'s command for one stage of the scene, on `n` threads."""
    cmd = [sys.executable, "-m", "ptovs", "--work-dir", str(work),
           "--config", str(args.config), "-q", "--threads", str(n)]  # fmt: skip
    cmd += [f"--set={s}" for s in args.set]
    return [*cmd, stage, "--scene", scene.name, "--data", str(scene)]


def _kill_group(pid: int, killed: threading.Event) -> None:
    killed.set()
    try:
        os.killpg(pid, signal.SIGKILL)
    except ProcessLookupError:  # ended meanwhile
        pass


def run_stage(cmd: list[str], env: dict, logs: Path, stage: str,
              budget: float | None) -> dict:  # fmt: skip
    """One stage in its own process: wall s, its peak RSS (its own rusage from
    wait4), exit status, stderr's tail on failure. Killed (with what it started)
    after `budget` s."""
    out, err = logs / f"{stage}.out", logs / f"{stage}.err"
    with out.open("w") as fo, err.open("w") as fe:
        load0 = os.getloadavg()[0]
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, env=env, stdout=fo, stderr=fe,
                                start_new_session=True)  # fmt: skip
        timer, killed = None, threading.Event()
        if budget is not None:
            timer = threading.Timer(budget, _kill_group, (proc.pid, killed))
            timer.daemon = True
            timer.start()
        try:
            _, status, usage = os.wait4(proc.pid, 0)
        finally:
            if timer is not None:
                timer.cancel()
        wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here, not by Popen
    # its CPU seconds and the machine's 1-min load average before and after: a
    # stage that shared the machine shows a load above its threads
    res = {"wall_s": round(wall, 2), "peak_rss_mb": round(usage.ru_maxrss / 1024, 1),
           "cpu_s": round(usage.ru_utime + usage.ru_stime, 1),
           "load": [round(load0, 2), round(os.getloadavg()[0], 2)],
           "exit": proc.returncode, "cmd": shlex.join(cmd)}  # fmt: skip
    if proc.returncode != 0:
        if killed.is_set():
            res["timeout"] = True
        res["stderr_tail"] = err.read_text(errors="replace")[-3000:]
    return res


def ok(rec: dict | None) -> bool:
    return bool(rec) and rec.get("exit") == 0


def fmt_s(rec: dict | None) -> str:
    if rec is None or "skipped" in rec:
        return "–"
    if rec.get("exit") != 0:
        return "timeout" if rec.get("timeout") else f"failed ({rec.get('exit')})"
    return f"{rec['wall_s']:.1f}"


def print_tables(runs: dict[str, dict], stages: tuple[str, ...] = PIPELINE) -> None:
    """Seconds and speed-up a stage and thread count, then peak RSS."""
    ns = sorted(runs, key=int)
    measured = [n for n in ns if any("skipped" not in r for r in runs[n].values())]
    if not measured:
        print("nothing measured")
        return
    base = next((n for n in measured if any(map(ok, runs[n].values()))), measured[0])

    def chain(n: str) -> dict | None:
        recs = [runs[n].get(s) for s in stages]
        if all(ok(r) for r in recs):
            return {"wall_s": sum(r["wall_s"] for r in recs), "exit": 0}
        return None

    cols = [c for n in measured for c in (f"{n} thr s", f"×{n} vs {base}")]
    print("| stage | " + " | ".join(cols) + " |")
    print("|---|" + "---:|" * len(cols))
    for name in (*stages, "chain"):
        cells = []
        ref = runs[base].get(name) if name != "chain" else chain(base)
        for n in measured:
            rec = runs[n].get(name) if name != "chain" else chain(n)
            cells.append(fmt_s(rec))
            both = ok(rec) and ok(ref) and rec["wall_s"] > 0
            cells.append(f"{ref['wall_s'] / rec['wall_s']:.2f}" if both else "–")
        print(f"| {name} | " + " | ".join(cells) + " |")
    print()
    print("| peak RSS MB | " + " | ".join(f"{n} thr" for n in measured) + " |")
    print("|---|" + "---:|" * len(measured))
    for name in stages:
        cells = []
        for n in measured:
            rec = runs[n].get(name)
            cells.append(f"{rec['peak_rss_mb']:.0f}" if rec and "peak_rss_mb" in rec
                         else "–")  # fmt: skip
        print(f"| {name} | " + " | ".join(cells) + " |")
    print(flush=True)


def report_stage(label: str, stage: str, rec: dict, extra: str = "") -> str:
    """Print a stage's line (and the tail of its stderr when it failed); returns
    why the chain stops there ("" when it went on)."""
    print(f"{label}  {stage:<20} {fmt_s(rec):>12}{' s' if ok(rec) else ''}"
          f"  {rec['peak_rss_mb']:7.0f} MB{extra}", file=sys.stderr, flush=True)  # fmt: skip
    if rec["exit"] == 0:
        return ""
    print(rec["stderr_tail"][-1500:], file=sys.stderr)
    return "the --timeout budget ran out" if rec.get("timeout") else f"{stage} failed"


def add_run_options(p: argparse.ArgumentParser, what: str = "scene") -> None:
    """The options every chain benchmark takes (this one and bench/growth.py)."""
    p.add_argument("--data", type=Path, default=None,
                   help=f"where the {what} generated (default <work>/data)")  # fmt: skip
    p.add_argument("--config", type=Path, default=ROOT / "configs" / "default.toml",
                   help="the --config every stage gets (make all's default)")  # fmt: skip
    p.add_argument("--set", action="append", default=[], metavar="STAGE.KEY=VALUE",
                   help="passed to every stage's command (repeatable)")  # fmt: skip
    p.add_argument("--timeout", type=float, default=None,
                   help="wall budget of the whole run, s: the rest is skipped")  # fmt: skip


def check_run_options(p: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse a malformed --set item; make the paths absolute."""
    for item in args.set:
        section, dot, _ = item.partition("=")[0].partition(".")
        if "=" not in item or not dot or section not in SECTIONS:
            p.error(f"--set {item!r}: write STAGE.KEY=VALUE, STAGE one of "
                    + ", ".join(SECTIONS))  # fmt: skip
    args.work = args.work.resolve()
    args.data = (args.data or args.work / "data").resolve()
    args.config = args.config.resolve()


def earlier_runs(
    path: Path, results: dict, same: tuple[str, ...], old: dict | None = None
) -> dict | None:
    """An earlier results file at `path` (or its content `old`, already read), when
    it measured the same setup (`same` keys of `results`) on the same CPU; else None."""
    if old is None:
        if not path.exists():
            return None
        old = json.loads(path.read_text())
    if all(old.get(k) == results[k] for k in same) and all(
        old.get("machine", {}).get(k) == results["machine"][k] for k in SAME_MACHINE
    ):
        return old
    return None


def write_results(path: Path, results: dict) -> None:
    from ptovs.atomic import atomic_file

    with atomic_file(path, keep_suffix=False) as tmp:
        tmp.write_text(json.dumps(results, indent=1))


def thread_env(n: int) -> dict:
    """The stages' environment at `n` threads (OpenMP's count; --threads sets torch's)."""
    env = {k: v for k, v in os.environ.items() if k != "PTOVS_THREADS"}
    env["OMP_NUM_THREADS"] = str(n)
    return env


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", choices=PRESETS, default="small")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2, 4, 8, 16])
    p.add_argument("--work", type=Path, default=ROOT / "work" / "threads")
    p.add_argument("--photos", type=int, default=None,
                   help="the preset's world at this many train photos (synth-scene "
                   "--photos; default: the preset's own count)")  # fmt: skip
    p.add_argument("--until", choices=PIPELINE, default=PIPELINE[-1],
                   help="the last stage run (default: the whole chain); the chain's "
                   "total then covers the stages up to it")  # fmt: skip
    add_run_options(p, "scene is")
    args = p.parse_args()
    stages = PIPELINE[: PIPELINE.index(args.until) + 1]
    t_start = time.perf_counter()
    deadline = None if args.timeout is None else t_start + args.timeout
    check_run_options(p, args)
    args.work.mkdir(parents=True, exist_ok=True)

    path = args.work / "threads.json"
    facts = machine_facts()
    results = {"machine": facts, "preset": args.preset, "seed": args.seed,
               "photos": args.photos, "set": list(args.set), "config": str(args.config),
               "stages": list(stages), "runs": {}, "skipped": {}}  # fmt: skip
    old = earlier_runs(path, results, SAME)
    if old:  # an earlier run of the same setup keeps its other thread counts
        results["runs"] = old.get("runs", {})
        results["total_s"] = old.get("total_s", {})

    def save() -> None:
        write_results(path, results)

    cpus = os.cpu_count() or 1
    counts = []
    for n in dict.fromkeys(args.threads):
        if n < 1 or n > cpus:
            why = f"{n} threads: this machine has {cpus} CPUs"
            print(f"skipped: {why}", file=sys.stderr)
            results["skipped"][str(n)] = why
            results["runs"].pop(str(n), None)
        else:
            counts.append(n)
    scene, synth_s = scene_folder(args)
    results["scene"], results["synth_s"] = str(scene), synth_s
    save()

    for n in counts:
        runs = results["runs"][str(n)] = {}
        work = args.work / f"t{n}"
        shutil.rmtree(work, ignore_errors=True)
        logs = work / "logs"
        logs.mkdir(parents=True)
        env = thread_env(n)
        t0, stop = time.perf_counter(), ""
        for stage in stages:
            left = None if deadline is None else deadline - time.perf_counter()
            if not stop and left is not None and left <= 0:
                stop = "the --timeout budget ran out"
            if stop:
                runs[stage] = {"skipped": stop}
                continue
            cmd = stage_command(args, work, scene, n, stage)
            rec = runs[stage] = run_stage(cmd, env, logs, stage, left)
            save()
            stop = report_stage(f"{n} threads", stage, rec)
        if any("skipped" not in r for r in runs.values()):
            total = round(time.perf_counter() - t0, 1)
            results.setdefault("total_s", {})[str(n)] = total
        save()

    print(f"\n{args.preset} seed {args.seed}"
          + (f", {args.photos} photos" if args.photos is not None else "")
          + (f", --set {' '.join(args.set)}" if args.set else "")
          + f"; {facts['cpu_model'] or facts['processor']}, {cpus} CPUs; "
          f"torch {facts.get('torch')} ({facts.get('torch_threads')} threads by default)\n")  # fmt: skip
    print_tables(results["runs"], stages)
    print(f"results: {path}")


if __name__ == "__main__":
    main()
