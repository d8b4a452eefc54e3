"""Time `ptovs synth-scene` per preset (each in a fresh process) and print a table.

python bench/synth_timing.py                 # tiny and bench, seeds 0 1 2
python bench/synth_timing.py --presets scale --seeds 0
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--presets", nargs="+", default=["tiny", "bench"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for preset in args.presets:
            for seed in args.seeds:
                out = Path(tmp) / f"{preset}-{seed}"
                t0 = time.perf_counter()
                subprocess.run(
                    [
                        sys.executable,
                        "-m",
                        "ptovs",
                        "-q",
                        "synth-scene",
                        str(out),
                        "--preset",
                        preset,
                        "--seed",
                        str(seed),
                    ],
                    check=True,
                    stdout=subprocess.DEVNULL,
                    stderr=subprocess.DEVNULL,
                )
                wall = time.perf_counter() - t0
                scene = out / f"{preset}_s{seed}"
                cams = json.loads(
                    (scene / "synthetic" / "truth" / "cameras.json").read_text()
                )
                imgs = cams["images"]
                n_eval = sum(1 for im in imgs if im.get("eval"))
                px = sum(im["width"] * im["height"] for im in imgs)
                size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
                rows.append(
                    (preset, seed, len(imgs), n_eval, px / 1e6, wall, size / 2**20)
                )
    print(
        f"machine: {platform.processor() or platform.machine()}, python {platform.python_version()}"
    )
    print("| preset | seed | images | eval | Mpixels | wall (s) | on disk (MiB) |")
    print("|---|---|---|---|---|---|---|")
    for preset, seed, n, ne, mpx, wall, mib in rows:
        print(
            f"| {preset} | {seed} | {n} | {ne} | {mpx:.2f} | {wall:.1f} | {mib:.1f} |"
        )


if __name__ == "__main__":
    main()
