"""Reconstruct on a busy machine: steps/s alone and beside a CPU-bound process.

python bench/busy.py                                  # real photos, every setting
python bench/busy.py --scene tiny --iterations 300    # the synthetic CI scene

Run it from a checkout nobody edits meanwhile, on a machine with nothing else
running: the competing process is the only other work there should be.

Each setting is an environment for `ptovs reconstruct` (OpenMP wait policy, thread
count); each runs alone and beside `--competitors` CPU-bound processes (Python busy
loops, the "other work" of a shared machine). The figure is training steps per
second, from the artifact's own training clock (`train_seconds`), so start-up and
SfM (cached after the first run) are not in it.

Settings:
  spin      OMP_WAIT_POLICY=ACTIVE: threads spin between parallel regions
  gomp      the OpenMP runtime's default (libgomp: spin 300k rounds, ~3 ms, then
            sleep; GOMP_SPINCOUNT=300000 says so explicitly): `ptovs` before
            issue 23
  passive   OMP_WAIT_POLICY=PASSIVE: threads sleep at once (issue 23's default)
  spin3k    GOMP_SPINCOUNT=3000: spin ~30 µs, then sleep (issue 24's default)
  1thread   --threads 1 (PTOVS_THREADS=1)

Results go to <work>/bench_busy.json and print as markdown rows.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import h5py

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import OMP_SETTINGS, ROOT, Results  # noqa: E402  (same folder)

REAL = ROOT / "data" / "real" / "fountain_p11"  # see bench/real.py
SETTINGS = {
    **{k: OMP_SETTINGS[k] for k in ("spin", "gomp", "passive", "spin3k")},
    "1thread": {"PTOVS_THREADS": "1"},
}


def scene_data(args: argparse.Namespace) -> Path:
    """The photo folder (real, unposed: SfM runs once and is cached) or the
    synthetic scene."""
    if args.scene == "real":
        folder = args.work / "data" / "fountain"
        if not folder.is_dir():
            shutil.copytree(args.photos / "images", folder / "images")
        return folder
    data = args.work / "data"
    scene = data / f"{args.scene}_s0"
    if not scene.is_dir():
        subprocess.run(
            [sys.executable, "-m", "ptovs", "-q", "synth-scene", str(data)]
            + ["--preset", args.scene, "--seed", "0"],
            check=True,
        )
    return scene


def run(args: argparse.Namespace, data: Path, setting: str, busy: bool) -> float:
    """Steps per second of one forced reconstruct under `setting`."""
    env = dict(os.environ, **SETTINGS[setting])
    work = args.work / "runs"
    sets = [
        f"reconstruct.iterations={args.iterations}",
        f"scene.downscale={args.downscale}",
    ]
    cmd = [sys.executable, "-m", "ptovs", "-q", "--work-dir", str(work)]
    cmd += [f"--set={s}" for s in sets]
    cmd += ["reconstruct", "--data", str(data), "--force"]
    spin = [sys.executable, "-c", "while True: pass"]
    competitors = [
        subprocess.Popen(spin) for _ in range(args.competitors if busy else 0)
    ]
    try:
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    finally:
        for competitor in competitors:
            competitor.kill()
            competitor.wait()
    if proc.returncode != 0:
        raise RuntimeError(proc.stderr[-3000:])
    path = Path(proc.stdout.strip().split(": ", 1)[1])
    with h5py.File(path) as f:
        metrics = json.loads(f["root/metrics_json"][()].tobytes())
    return args.iterations / metrics["train_seconds"]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scene", default="real", choices=["real", "tiny", "small"])
    p.add_argument("--photos", type=Path, default=REAL, help="a real photo set")
    p.add_argument("--iterations", type=int, default=20)
    p.add_argument(
        "--downscale",
        default="2",
        help="scene.downscale (2: the 1536×1024 steps of the issue's report)",
    )
    p.add_argument("--settings", nargs="+", default=list(SETTINGS))
    p.add_argument(
        "--competitors", type=int, default=1, help="CPU-bound processes beside it"
    )
    p.add_argument("--work", type=Path, default=ROOT / "work" / "busy")
    args = p.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    res = Results(args.work / "bench_busy.json")
    data = scene_data(args)
    print("| scene | setting | steps/s alone | steps/s busy | busy / alone |")
    print("|---|---|---|---|---|")
    for setting in args.settings:
        t0 = time.perf_counter()
        alone = run(args, data, setting, busy=False)
        busy = run(args, data, setting, busy=True)
        res[f"{args.scene}/{args.iterations}/{setting}/{args.competitors}"] = dict(
            alone=alone, busy=busy, wall_s=time.perf_counter() - t0
        )
        res.save()
        print(
            f"| {args.scene} ({args.iterations} its, {args.competitors} busy) | "
            f"{setting} | {alone:.3f} | "
            f"{busy:.3f} | {busy / alone:.2f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
