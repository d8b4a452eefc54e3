"""Is reconstruct's schedule long enough for the collection? (issue 43 item 3)

Reconstruct on one scene twice, side by side: the default schedule, and the same
stretched by --factor (iterations, the end of densification and the Gaussian ceiling
times F; the rest as it is). Per run: wall s, peak RSS MB, the Gaussians trained and
the held-out PSNR (the artifact's root metrics_json["psnr_test"]: each test view
rendered with its own embedding against the photo). The rule under test: the
default's held-out PSNR within 0.5 dB of the stretched run's.

python bench/schedule.py --scene work/growth/data/landmark_s0_p763 --factor 2 \
    --work work/schedule                               # issue 43's check, 763 photos
python bench/schedule.py --scene work/growth/data/landmark_s0_p100 --factor 2 \
    --reuse default=work/growth/landmark_s0_p100       # the default taken from growth

A run is each its own process, exactly as `make all` runs the stage (bench/threads.py's
run_stage), in <work>/<scene>/<label>; `--reuse LABEL=WORK` takes that run's artifact
from an earlier work folder (bench/growth.py's <work>/<scene>, say) instead of training
it again (its wall time and memory are then in that bench's results, not here).
Results: <work>/schedule.json (a run a label), then a markdown table.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT  # noqa: E402  (same folder)
from threads import machine_facts, ok, run_stage, thread_env  # noqa: E402

# the defaults a factor stretches (src/ptovs/stages/reconstruct.py's Config)
STRETCH = ("iterations", "densify_until", "max_gaussians")


def stretched(factor: float) -> list[str]:
    from ptovs.stages.reconstruct import Config

    cfg = Config()
    return [f"reconstruct.{k}={round(getattr(cfg, k) * factor)}" for k in STRETCH]


def artifact_of(folder: Path, scene: str) -> Path | None:
    arts = list((folder / scene / "reconstruct").glob("*.h5"))
    return arts[0] if len(arts) == 1 else None


def figures(art: Path) -> dict:
    from ptovs.artifacts import Artifact, read_json_dataset

    with Artifact(art, verify=False) as a:
        m = read_json_dataset(a.root()["metrics_json"])
    keys = ("psnr_test", "psnr_train", "gaussians_trained", "iterations",
            "seconds_per_iteration")  # fmt: skip
    return {k: m.get(k) for k in keys}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, required=True, help="a scene folder")
    ap.add_argument("--factor", type=float, default=2.0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--work", type=Path, default=ROOT / "work" / "schedule")
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "default.toml")
    ap.add_argument("--reuse", action="append", default=[], metavar="LABEL=WORK")
    args = ap.parse_args()
    if args.factor <= 0:
        ap.error("--factor must be > 0")
    scene = args.scene.resolve()
    reuse = dict(r.split("=", 1) for r in args.reuse)
    out = args.work / "schedule.json"
    results = json.loads(out.read_text()) if out.is_file() else {"runs": {}}
    results["machine"] = machine_facts()
    env = thread_env(args.threads)
    label_x = f"x{args.factor:g}"
    for label, sets in (("default", []), (label_x, stretched(args.factor))):
        key = f"{scene.name}/{label}"
        if label in reuse:
            folder = Path(reuse[label]).resolve()
            rec = {"reused": str(folder), "exit": 0, "set": sets}
        else:
            folder = (args.work / scene.name / label).resolve()
            logs = folder / "logs"
            logs.mkdir(parents=True, exist_ok=True)
            cmd = [sys.executable, "-m", "ptovs", "--work-dir", str(folder),
                   "--config", str(args.config), "-q", "--threads", str(args.threads),
                   *(f"--set={s}" for s in sets),
                   "reconstruct", "--scene", scene.name, "--data", str(scene)]  # fmt: skip
            rec = run_stage(cmd, env, logs, "reconstruct", None)
            rec["set"] = sets
        art = artifact_of(folder, scene.name) if ok(rec) else None
        if art is not None:
            rec.update(figures(art))
        results["runs"][key] = rec
        args.work.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps(results, indent=1))
        print(key, json.dumps({k: v for k, v in rec.items() if k != "stderr_tail"}),
              file=sys.stderr, flush=True)  # fmt: skip
    print(
        "| scene | run | wall s | peak MB | Gaussians | test PSNR dB | train PSNR dB |"
    )
    print("|---|---|---:|---:|---:|---:|---:|")
    for key, r in results["runs"].items():
        name, label = key.split("/", 1)
        print(f"| {name} | {label} | {r.get('wall_s', '–')} | {r.get('peak_rss_mb', '–')}"
              f" | {r.get('gaussians_trained', '–')} | {r.get('psnr_test', '–')} | "
              f"{r.get('psnr_train', '–')} |")  # fmt: skip


if __name__ == "__main__":
    main()
