"""Real photos from the folder to evaluate-ready artifacts, on tiny budgets.

    python bench/photo_chain.py --real data/real --sets fountain_p11 herzjesu_p8 \
        --saturate fountain_p11 --downscale 4 3 1 --work work/photo_chain

Each set's photos (`<real>/<set>/images/*.jpg`, no cameras used) go through `sfm`,
`reconstruct`, `render-appearances`, `extract-features`, `uncertainty`, `train-ae`
and `train-male` with `configs/paper.toml`, at each working scale given (`1`: native
size; after SfM's undistortion every other factor is a non-integer one). The
budgets are tiny (30 reconstruct steps, 2 autoencoder epochs, 20 language-field
steps) and the encoder is a random-weight 3.6 M-parameter OpenCLIP with the `hier`
segmenter: this checks that real photo sizes and exposures pass every stage, and
what each stage costs at that size, not what the answers are. `--saturate SET` adds
`SET_sat`: the photos brightened 2.5× and clipped (a blown-out sky), as JPEG q95.
Prints one row per set and scale: each stage's wall seconds and the exit status.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("sfm", "reconstruct", "render-appearances", "extract-features",
          "uncertainty", "train-ae", "train-male")  # fmt: skip
TINY = (
    "from ptovs.encoders.openclip import register_tiny; register_tiny(); "
    "from ptovs.cli import main; main()"
)  # `ptovs` with the tests' tiny OpenCLIP config registered


def saturate(src: Path, dst: Path, gain: float = 2.5) -> None:
    import cv2
    import numpy as np

    (dst / "images").mkdir(parents=True, exist_ok=True)
    for p in sorted((src / "images").glob("*.jpg")):
        im = cv2.imread(str(p)).astype(np.float32) * gain
        im = np.clip(im, 0, 255).astype(np.uint8)
        cv2.imwrite(str(dst / "images" / p.name), im, [cv2.IMWRITE_JPEG_QUALITY, 95])


def tiny_checkpoint(path: Path) -> None:
    import torch

    from ptovs.encoders.openclip import build_net, register_tiny

    torch.manual_seed(0)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(build_net(register_tiny(), None).state_dict(), path)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--real", type=Path, default=ROOT / "data" / "real")
    ap.add_argument("--sets", nargs="+", default=["fountain_p11", "herzjesu_p8"])
    ap.add_argument("--saturate", nargs="*", default=["fountain_p11"])
    ap.add_argument("--downscale", nargs="+", default=["4", "3", "1"])
    ap.add_argument("--work", type=Path, default=ROOT / "work" / "photo_chain")
    args = ap.parse_args()
    work = args.work.resolve()
    photos = work / "photos"
    ckpt = work / "tiny_openclip.pt"
    if not ckpt.is_file():
        tiny_checkpoint(ckpt)
    folders = []
    for name in args.sets:
        dst = photos / name
        if not dst.is_dir():
            (dst / "images").mkdir(parents=True)
            for p in sorted((args.real / name / "images").glob("*.jpg")):
                (dst / "images" / p.name).symlink_to(p.resolve())
        folders.append(dst)
        if name in args.saturate:
            sat = photos / f"{name}_sat"
            if not sat.is_dir():
                saturate(args.real / name, sat)
            folders.append(sat)
    print("| set | r | " + " | ".join(STAGES) + " | exit |")
    print("|---" * (len(STAGES) + 3) + "|")
    ok = True
    for folder in folders:
        for r in args.downscale:
            sets = [
                "--work-dir", str(work / f"r{r}"),
                "--config", str(ROOT / "configs" / "paper.toml"),
                "--set", f"scene.downscale={r}",
                "--set", "reconstruct.iterations=30",
                "--set", "extract-features.encoder=openclip",
                "--set", "extract-features.clip_model=ptovs-tiny-test",
                "--set", f"extract-features.clip_checkpoint={ckpt}",
                "--set", "extract-features.segmenter=hier",
                "--set", "train-ae.epochs=2",
                "--set", "train-male.iterations=20",
            ]  # fmt: skip
            times, rc = [], 0
            for stage in STAGES:
                t0 = time.perf_counter()
                proc = subprocess.run(
                    [sys.executable, "-c", TINY, *sets, stage, "--data", str(folder)],
                    capture_output=True, text=True,
                )  # fmt: skip
                times.append(f"{time.perf_counter() - t0:.0f}")
                rc = proc.returncode
                if rc or "Traceback" in proc.stderr:
                    print(proc.stderr[-3000:], file=sys.stderr)
                    rc = rc or 1
                    break
            ok &= rc == 0
            times += ["–"] * (len(STAGES) - len(times))
            print(f"| {folder.name} | {r} | " + " | ".join(times) + f" | {rc} |",
                  flush=True)  # fmt: skip
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
