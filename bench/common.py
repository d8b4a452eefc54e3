"""What the bench scripts share: the repository root, the bench scenes, `ptovs` in a
fresh process, the results file every script keeps, camera pose errors, a chain's
stages run one process each (bench/growth.py, bench/real_chain.py).

    from common import ROOT, Results, bench_scene, run_ptovs   # (bench/ is on sys.path)
    from common import seed_list                                 # "0-17" "20" -> seeds
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

from ptovs.pipeline import PIPELINE  # stdlib only: torch stays out

ROOT = Path(__file__).resolve().parents[1]


def machine() -> dict:
    """Where and when a figure was measured."""
    return dict(
        platform=platform.platform(),
        cpus=os.cpu_count(),
        date=time.strftime("%Y-%m-%d"),
    )


class Results(dict):
    """A bench script's results file: what an earlier run left is kept (so one part
    can be rerun alone), stamped with this machine and date, saved atomically."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        super().__init__(
            json.loads(self.path.read_text()) if self.path.exists() else {}
        )
        self["machine"] = machine()

    def save(self) -> None:
        save_json(self.path, self)


def save_json(path: Path, data: dict) -> None:
    """`data` as indented JSON at `path`, written atomically."""
    from ptovs.atomic import atomic_file

    with atomic_file(path, keep_suffix=False) as tmp:
        tmp.write_text(json.dumps(data, indent=1))


def run_ptovs(work: Path, *args: str) -> tuple[float, float, str]:
    """Run `ptovs` in a fresh process; (wall s, peak RSS MB of that process, stdout).

    The peak RSS comes from GNU time when present: `wait4`'s ru_maxrss would also
    count the pages the child shares with this (large) benchmark process between
    fork and exec.
    """
    cmd = [sys.executable, "-m", "ptovs", "-q", "--work-dir", str(work), *args]
    gnu_time = shutil.which("time") or (
        "/usr/bin/time" if Path("/usr/bin/time").exists() else None
    )
    full = [gnu_time, "-f", "PTOVS_PEAK_KB %M", *cmd] if gnu_time else cmd
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        full, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    out, err = proc.communicate()
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{err[-3000:]}")
    peak = [ln for ln in err.splitlines() if ln.startswith("PTOVS_PEAK_KB ")]
    rss = float(peak[-1].split()[1]) / 1024.0 if peak else float("nan")
    return wall, rss, out


def bench_scene(data: Path, seed: int) -> Path:
    """The `bench` preset scene of `seed` under `data`, generated on first use."""
    scene = data / f"bench_s{seed}"
    if not (scene / "dense").is_dir():
        subprocess.run(
            [
                sys.executable,
                "-m",
                "ptovs",
                "-q",
                "synth-scene",
                str(data),
                "--preset",
                "bench",
                "--seed",
                str(seed),
            ],
            check=True,
        )
    return scene


def seed_list(items: list[str]) -> list[int]:
    """Seeds from items such as "0-17" and "20", in order, each once."""
    out: list[int] = []
    for it in items:
        a, _, b = it.partition("-")
        out += list(range(int(a), int(b) + 1)) if b else [int(a)]
    return list(dict.fromkeys(out))


def camera_pose(cam_from_world) -> tuple:
    """(R camera-to-world [3, 3], centre [3]) of a [3, 4] or [4, 4] cam_from_world."""
    import numpy as np

    m = np.asarray(cam_from_world, dtype=np.float64)
    r = m[:3, :3].T
    return r, -(r @ m[:3, 3])


def _angle_deg(d) -> float:
    """The rotation angle of a 3×3 rotation matrix, in degrees."""
    import numpy as np

    return float(np.degrees(np.arccos(np.clip((np.trace(d) - 1) / 2, -1, 1))))


def pose_error(est: dict, truth: dict) -> dict:
    """Pose error of estimated cameras against the true ones after a Sim3 alignment
    of the camera centres, and (rot_aligned_*) after the world rotation that best
    aligns the camera rotations alone. Both map a photo name to (R camera-to-world [3, 3],
    centre [3]); names in both count. Rotations in degrees, centres in the truth's
    units."""
    import numpy as np
    import pycolmap

    names = sorted(set(est) & set(truth))
    e = np.array([est[n][1] for n in names], dtype=np.float64)
    g = np.array([truth[n][1] for n in names], dtype=np.float64)
    sim = pycolmap.estimate_sim3d(e, g)
    rs = sim.rotation.matrix()
    rot = []
    for n in names:
        rot.append(_angle_deg((rs @ est[n][0]).T @ truth[n][0]))
    centre = np.linalg.norm(np.array([sim * p for p in e]) - g, axis=1)
    # rotations alone: the world rotation that best maps the estimated camera
    # rotations onto the true ones (orthogonal Procrustes), free of the centres
    m = sum(est[n][0] @ truth[n][0].T for n in names)
    u, _, vt = np.linalg.svd(m)
    a = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    rot_only = [_angle_deg((a.T @ est[n][0]).T @ truth[n][0]) for n in names]
    return dict(
        rot_aligned_median_deg=float(np.median(rot_only)),
        rot_aligned_p90_deg=float(np.percentile(rot_only, 90)),
        rot_aligned_over5=int(np.sum(np.array(rot_only) > 5.0)),
        posed=len(names),
        rot_median_deg=float(np.median(rot)),
        rot_p90_deg=float(np.percentile(rot, 90)),
        rot_max_deg=float(np.max(rot)),
        centre_median=float(np.median(centre)),
        centre_max=float(np.max(centre)),
    )


def print_header(*columns: str) -> None:
    """A markdown table's header and rule line."""
    print("| " + " | ".join(columns) + " |")
    print("|" + "---|" * len(columns), flush=True)


# ------------------------------------------- a chain's stages, each its own process

SECTIONS = ("scene", *PIPELINE)  # what a --set item may name
PRESETS = ("tiny", "small", "bench", "landmark", "scale")  # synth-scene's
SAME_MACHINE = ("cpu_model", "cpu_count")  # an earlier run is kept on the same CPU


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


def stage_command(args: argparse.Namespace, work: Path, scene: Path, n: int,
                  stage: str) -> list[str]:  # fmt: skip
    """`make all`'s command for one stage of the scene, on `n` threads."""
    cmd = [sys.executable, "-m", "ptovs", "--work-dir", str(work),
           "--config", str(args.config), "-q", "--threads", str(n)]  # fmt: skip
    cmd += [f"--set={s}" for s in args.set]
    return [*cmd, stage, "--scene", scene.name, "--data", str(scene)]


def run_stage(cmd: list[str], env: dict, logs: Path, stage: str) -> dict:
    """One stage in its own process: wall s, its peak RSS (its own rusage from
    wait4), exit status, stderr's tail on failure."""
    out, err = logs / f"{stage}.out", logs / f"{stage}.err"
    with out.open("w") as fo, err.open("w") as fe:
        load0 = os.getloadavg()[0]
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, env=env, stdout=fo, stderr=fe,
                                start_new_session=True)  # fmt: skip
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)  # reaped here, not by Popen
    # its CPU seconds and the machine's 1-min load average before and after: a
    # stage that shared the machine shows a load above its threads
    res = {"wall_s": round(wall, 2), "peak_rss_mb": round(usage.ru_maxrss / 1024, 1),
           "cpu_s": round(usage.ru_utime + usage.ru_stime, 1),
           "load": [round(load0, 2), round(os.getloadavg()[0], 2)],
           "exit": proc.returncode, "cmd": shlex.join(cmd)}  # fmt: skip
    if proc.returncode != 0:
        res["stderr_tail"] = err.read_text(errors="replace")[-3000:]
    return res


def ok(rec: dict | None) -> bool:
    return bool(rec) and rec.get("exit") == 0


def fmt_s(rec: dict | None) -> str:
    if rec is None or "skipped" in rec:
        return "–"
    if rec.get("exit") != 0:
        return f"failed ({rec.get('exit')})"
    return f"{rec['wall_s']:.1f}"


def report_stage(label: str, stage: str, rec: dict, extra: str = "") -> str:
    """Print a stage's line (and the tail of its stderr when it failed); returns
    why the chain stops there ("" when it went on)."""
    print(f"{label}  {stage:<20} {fmt_s(rec):>12}{' s' if ok(rec) else ''}"
          f"  {rec['peak_rss_mb']:7.0f} MB{extra}", file=sys.stderr, flush=True)  # fmt: skip
    if rec["exit"] == 0:
        return ""
    print(rec["stderr_tail"][-1500:], file=sys.stderr)
    return f"{stage} failed"


def thread_env(n: int) -> dict:
    """The stages' environment at `n` threads (OpenMP's count; --threads sets torch's)."""
    env = {k: v for k, v in os.environ.items() if k != "PTOVS_THREADS"}
    env["OMP_NUM_THREADS"] = str(n)
    return env
