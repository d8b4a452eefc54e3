"""Refit the invariance projection of stand-in version 4 or 5 (issue 41).

    python tools/fit_standin_v4.py [--version 4|5] [--out PATH]

Renders the parts of the bank worlds (seeds 900-911, preset small, version 3's
worlds; never a calibration or judged seed) under 12 azimuths x 7 lights, reduces
each crop to version 2's statistics (with version 5's options for `--version 5`),
fits Fisher's discriminant over (world, part) classes and writes its mean,
directions and scale (default: the package's own file of that version). About
ten minutes on 2 cores. The package verifies the file by its SHA-256
(`PROJECTION_SHA256` of `synthetic_v4` / `synthetic_v5`): after a refit, put the
printed digest there. Floats differ between CPU models, so a refit elsewhere may
differ in the last bits.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import sys
from pathlib import Path

import numpy as np

from ptovs.encoders import synthetic_v4 as v4
from ptovs.encoders import synthetic_v5 as v5

ROOT = Path(__file__).resolve().parent.parent
STATS = {4: None, 5: v5.STATS}
FILES = {4: v4.PROJECTION_FILE, 5: v5.PROJECTION_FILE}


def write(
    raw: np.ndarray, cls: np.ndarray, out: Path, stats: dict | None = None
) -> str:
    mu, V, scale, ev = v4.fisher(raw, cls, v4.K, stats=stats)
    buf = io.BytesIO()
    np.savez(buf, mean=mu, directions=V, scale=np.array(scale), eigenvalues=ev,
             bank_seeds=np.array(v4.BANK_SEEDS), n_crops=np.array(len(raw)))  # fmt: skip
    blob = buf.getvalue()
    tmp = out.with_suffix(".tmp")
    tmp.write_bytes(blob)
    tmp.replace(out)
    return hashlib.sha256(blob).hexdigest()


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--version", type=int, default=4, choices=(4, 5))
    ap.add_argument("--out", type=Path, default=None,
                    help="where to write (default: the package's file)")  # fmt: skip
    args = ap.parse_args(argv)
    out = args.out or ROOT / "src" / "ptovs" / "encoders" / FILES[args.version]
    stats = STATS[args.version]
    raw, cls = v4.bank_statistics(
        v4.BANK_SEEDS,
        lambda s, n: print(f"bank world {s}: {n} crops", flush=True),
        stats,
    )
    digest = write(raw, cls, out, stats)
    print(f"wrote {out} ({len(raw)} crops); sha256 {digest}")


if __name__ == "__main__":
    sys.exit(main())
