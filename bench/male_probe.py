"""train-male's peak memory at a larger collection's Gaussian count (issue 43 item 4).

python bench/male_probe.py --work work/growth/landmark_s0_p400 \
    --data work/growth/data/landmark_s0_p400 --gaussians 153217 42263 0

The whole chain at 2,934 photos takes about 5 h on 2 cores, more than one sitting,
and train-male comes last. Its memory depends on the Gaussians (the lift's sums,
[Gaussians, levels, slots, 512] floats up to cache_mb, and each view's blend
weights) and on one view's size, not on how many views it goes over (its views
are read one at a time; tests/test_field.py's leak test and the probe of
docs/benchmarks.md keep it so). So this runs the real stage, `ptovs train-male
--force`, on a finished chain (growth.py's work folder of one size) with the
reconstructed field's Gaussians multiplied to a given count: each copy of a
Gaussian moved by half its mean scale in a random direction, the same shape,
opacity and colour, so the views see a denser cloud of the same world, as a larger
collection's SfM cloud is. Every other input (the views, their segments, features,
codes and uncertainty) is the chain's own.

A count of 0 runs the field as it is, to show what the probe itself adds against
growth.json's figure for the stage. Each count runs in its own process, on a
hard-linked copy of the work folder (the stage's artifact is written beside it by
an atomic rename, so the measured chain's files are never touched; the copy is
removed after), one at a time. Reported: peak RSS (os.wait4's ru_maxrss, MB), wall s,
the Gaussians and views the stage's artifact records, and its lift passes. Results
in <out> (default <work>/../male_probe.json).
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

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT  # noqa: E402  (same folder)
from threads import cpu_model, thread_env  # noqa: E402  (same folder)

CHILD = (
    "import sys; sys.path.insert(0, sys.argv[1]); import male_probe; "
    "male_probe.patch(int(sys.argv[2])); from ptovs.cli import main; main(sys.argv[3:])"
)
"""The probe's process: the field's loader patched, then the command line."""


def inflate(field, target: int, seed: int = 0):
    """`field` with `target` Gaussians: every Gaussian once (first, unchanged), then
    copies of Gaussians drawn at random, each moved by half its mean scale in a
    random direction (shape, opacity and colour kept). 0 or its own count: as is."""
    import torch

    n = len(field)
    if target <= 0 or target == n:
        return field
    gen = torch.Generator().manual_seed(seed)
    extra = torch.randint(0, n, (max(target - n, 0),), generator=gen)
    keep = torch.cat([torch.arange(n), extra])[:target]
    out = field.subset(keep)
    g = out.gaussians
    step = torch.randn(len(keep), 3, generator=gen)
    step = step / step.norm(dim=1, keepdim=True).clamp_min(1e-12)
    moved = torch.arange(len(keep)) >= n
    g.means[moved] += 0.5 * g.scales[moved].mean(1, keepdim=True) * step[moved]
    return out


def patch(target: int) -> None:
    """Make `WildField.from_artifact` return the field inflated to `target`."""
    from ptovs.field import render

    load = render.WildField.from_artifact
    render.WildField.from_artifact = classmethod(
        lambda cls, art: inflate(load(art), target)
    )


def run_one(args: argparse.Namespace, count: int) -> dict:
    """One probe run in its own process on a hard-linked copy of the work folder."""
    copy = args.work.parent / f".male_probe_{args.work.name}"
    if copy.exists():
        shutil.rmtree(copy)
    subprocess.run(["cp", "-al", str(args.work), str(copy)], check=True)
    try:
        cmd = [sys.executable, "-c", CHILD, str(Path(__file__).resolve().parent), str(count),
               "--work-dir", str(copy), "--config", str(args.config), "-q",
               "--threads", str(args.threads), "train-male", "--scene",
               args.data.name, "--data", str(args.data), "--force"]  # fmt: skip
        t0 = time.perf_counter()
        said = copy.parent / f"{copy.name}.out"
        with said.open("w") as fo:  # the command's one line: "train-male: <artifact>"
            proc = subprocess.Popen(cmd, env=thread_env(args.threads), cwd=ROOT,
                                    stdout=fo)  # fmt: skip
            _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        rec = {"gaussians_asked": count, "exit": os.waitstatus_to_exitcode(status),
               "wall_s": round(wall, 1), "peak_mb": round(usage.ru_maxrss / 1024),
               "cpu_s": round(usage.ru_utime + usage.ru_stime, 1)}  # fmt: skip
        lines = [
            x for x in said.read_text().splitlines() if x.startswith("train-male: ")
        ]
        if rec["exit"] == 0 and lines:
            rec.update(artifact_metrics(Path(lines[-1].split(": ", 1)[1])))
        return rec
    finally:
        shutil.rmtree(copy, ignore_errors=True)
        (copy.parent / f"{copy.name}.out").unlink(missing_ok=True)


def artifact_metrics(path: Path) -> dict:
    """The train-male artifact's own record: Gaussians, views, lift passes."""
    import h5py

    from ptovs.artifacts import read_json_dataset

    with h5py.File(path, "r") as f:
        m = read_json_dataset(f["root"]["metrics_json"][()])
    keys = ("gaussians", "gaussians_seen", "views", "lift_passes", "loss_views",
            "train_seconds")  # fmt: skip
    return {k: m.get(k) for k in keys}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    ap.add_argument("--work", type=Path, required=True,
                    help="growth.py's work folder of one size (its chain finished)")  # fmt: skip
    ap.add_argument("--data", type=Path, required=True, help="that size's scene folder")
    ap.add_argument("--gaussians", type=int, nargs="+", required=True,
                    help="Gaussian counts to run at; 0 = the field as it is")  # fmt: skip
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "default.toml")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    args.work, args.data = args.work.resolve(), args.data.resolve()
    for path, what in ((args.work, "--work"), (args.data / "dense", "--data")):
        if not path.is_dir():
            raise SystemExit(
                f"{what}: {path} is not a folder (run bench/growth.py first)"
            )
    out = args.out or args.work.parent / "male_probe.json"
    results = json.loads(out.read_text()) if out.is_file() else {"runs": []}
    results.update(cpu=cpu_model(), threads=args.threads, scene=args.data.name)
    for count in args.gaussians:
        rec = run_one(args, count)
        rec["when"] = time.strftime("%Y-%m-%d %H:%M:%S")
        results["runs"].append(rec)
        out.write_text(json.dumps(results, indent=1))
        print(json.dumps(rec), flush=True)
    print(
        "| Gaussians | views | lift passes | peak RSS MB | s |\n|---:|---:|---:|---:|---:|"
    )
    for r in results["runs"]:
        print(f"| {r.get('gaussians')} | {r.get('views')} | {r.get('lift_passes')} | "
              f"{r['peak_mb']:,} | {r['wall_s']:.0f} |")  # fmt: skip


if __name__ == "__main__":
    main()
