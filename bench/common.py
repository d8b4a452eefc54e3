"""What the bench scripts share: the repository root, the bench scenes, `ptovs` in a
fresh process, and the results file every script keeps.

    from common import ROOT, Results, bench_scene, run_ptovs   # (bench/ is on sys.path)
    from common import seed_list                                 # "0-17" "20" -> seeds
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

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
        from ptovs.atomic import atomic_file

        with atomic_file(self.path, keep_suffix=False) as tmp:
            tmp.write_text(json.dumps(self, indent=1))


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


def probe_parser(doc: str, preset: str) -> argparse.ArgumentParser:
    """The arguments of the dev diagnostics that read the instrument's scenes and
    artifacts (bench/ae_probe.py); `--seeds` takes ranges."""
    ap = argparse.ArgumentParser(description=doc.split("\n")[0])
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--preset", default=preset)
    ap.add_argument("--standin", type=int, default=5, choices=(1, 5))
    ap.add_argument("--seeds", nargs="+", required=True, help="seeds or ranges (0-8)")
    return ap


def instrument_chain(scene: Path, work: Path, config: Path, variant: str = "male"):
    """The accuracy instrument's chain of `variant` on `scene` (bench/accuracy.py's
    layout: artifacts under <work>/runs, its config file). Its keys say whether a
    result measured earlier still describes today's code and config."""
    from ptovs.config import load_config
    from ptovs.stage import Chain, RunContext, resolve_scene
    from ptovs.variants import variant_sets

    ctx = RunContext(work / "runs", load_config(config))
    return Chain(ctx, resolve_scene(ctx, None, scene), variant_sets(variant))


OMP_SETTINGS = {
    "spin": {"OMP_WAIT_POLICY": "ACTIVE"},
    "gomp": {"GOMP_SPINCOUNT": "300000"},
    "passive": {"OMP_WAIT_POLICY": "PASSIVE"},
    "spin1k": {"GOMP_SPINCOUNT": "1000"},
    "spin3k": {"GOMP_SPINCOUNT": "3000"},
    "spin10k": {"GOMP_SPINCOUNT": "10000"},
}
"""OpenMP wait settings the busy-machine benchmarks compare (environment overrides)."""


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
