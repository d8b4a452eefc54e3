"""OpenMP wait settings on bench-sized training steps, alone and beside busy work.

python bench/omp_steps.py                                     # every setting, 0-2 busy
python bench/omp_steps.py --settings passive spin3k --competitors 0 1

`bench/busy.py` times whole (short) reconstruct runs from scratch on real photos,
where a step is ~1 s; here a step is ~0.15 s (141×250 pixels, 25k Gaussians) and made
of thousands of small tensor operations, which is where the wait policy matters. The
state after `--warm` steps of the default reconstruct on `bench` seed `--seed` is
trained once and kept (<work>/state_<seed>_<warm>.pt); each (setting, competitors)
pair then times `--steps` further training steps from it in a fresh process (the
OpenMP runtime reads its settings once, at load), beside that many CPU-bound
processes (`while True: pass`). The wait policy changes no result, only time.

Settings: passive (OMP_WAIT_POLICY=PASSIVE, issue 23's default), gomp (libgomp's
default spin, GOMP_SPINCOUNT=300000), spin<k> (GOMP_SPINCOUNT=k·1000; spin3k is
ptovs's default since issue 24).

Results go to <work>/bench_omp_steps.json and print as markdown rows (ms a step).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import OMP_SETTINGS, ROOT, Results, bench_scene  # noqa: E402  (same folder)

SETTINGS = {
    k: OMP_SETTINGS[k] for k in ("passive", "gomp", "spin1k", "spin3k", "spin10k")
}


def _setup(scene: Path):
    from ptovs.scene import load_scene
    from ptovs.stages.reconstruct import Config, _views_and_images

    sc = load_scene(scene)
    _, images, cams = _views_and_images(sc)
    return Config(), images, cams, (sc.points_xyz, sc.points_rgb)


def warm_state(scene: Path, path: Path, warm: int) -> None:
    """Train the default reconstruct for `warm` steps and keep its state."""
    import torch

    from ptovs.field.train import train

    cfg, images, cams, points = _setup(scene)
    cfg = dataclasses.replace(cfg, iterations=warm)
    state = train(cfg, images, cams, points, desc="warm-up")
    from ptovs.atomic import atomic_file

    with atomic_file(path) as tmp:
        torch.save(state.to_dict(), tmp)


def child(scene: Path, path: Path, steps: int) -> None:
    """Time `steps` training steps from the kept state; print ms a step."""
    import torch

    from ptovs.field.train import train

    cfg, images, cams, points = _setup(scene)
    saved = torch.load(path, weights_only=True)
    cfg = dataclasses.replace(
        cfg, iterations=saved["step"] + steps, checkpoint_every=10**9
    )
    t0 = time.perf_counter()
    train(cfg, images, cams, points, load=lambda: saved, desc="timed")
    print(f"{(time.perf_counter() - t0) / steps * 1000:.1f}")


def timed(args: argparse.Namespace, scene: Path, state: Path, setting: str, busy: int):
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")
    }
    env.update(SETTINGS[setting])
    cmd = [sys.executable, __file__, "--child", str(scene), str(state), str(args.steps)]
    spin = [sys.executable, "-c", "while True: pass"]
    competitors = [subprocess.Popen(spin) for _ in range(busy)]
    try:
        out = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
    finally:
        for c in competitors:
            c.kill()
            c.wait()
    return float(out.stdout.strip().splitlines()[-1])


def main() -> None:
    if len(sys.argv) == 5 and sys.argv[1] == "--child":
        child(Path(sys.argv[2]), Path(sys.argv[3]), int(sys.argv[4]))
        return
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--warm", type=int, default=1400, help="steps before timing")
    p.add_argument("--steps", type=int, default=80, help="steps timed")
    p.add_argument("--settings", nargs="+", default=list(SETTINGS))
    p.add_argument("--competitors", nargs="+", type=int, default=[0, 1, 2])
    p.add_argument("--data", type=Path, default=ROOT / "data")
    p.add_argument("--work", type=Path, default=ROOT / "work" / "omp_steps")
    args = p.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    scene = bench_scene(args.data, args.seed)
    state = args.work / f"state_{args.seed}_{args.warm}.pt"
    if not state.exists():
        warm_state(scene, state, args.warm)
    res = Results(args.work / "bench_omp_steps.json")
    print(
        "| setting | "
        + " | ".join(f"ms a step, {b} busy" for b in args.competitors)
        + " |"
    )
    print("|---|" + "---|" * len(args.competitors))
    for setting in args.settings:
        row = []
        for busy in args.competitors:
            ms = timed(args, scene, state, setting, busy)
            res[f"s{args.seed}/{args.warm}+{args.steps}/{setting}/{busy}"] = ms
            res.save()
            row.append(f"{ms:.0f}")
        print(f"| {setting} | " + " | ".join(row) + " |", flush=True)


if __name__ == "__main__":
    main()
