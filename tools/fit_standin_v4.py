"""Refit the invariance projection of stand-in version 4 (issue 41).

    python tools/fit_standin_v4.py [--out src/ptovs/encoders/standin_v4.npz]

Renders the parts of the bank worlds (seeds 900-911, preset small, version 3's
worlds; never a calibration or judged seed) under 12 azimuths x 7 lights, reduces
each crop to version 2's statistics, fits Fisher's discriminant over (world, part)
classes and writes its mean, directions and scale. About ten minutes on 2 cores.
The package verifies the file by its SHA-256 (`synthetic_v4.PROJECTION_SHA256`):
after a refit, put the printed digest there. Floats differ between CPU models, so
a refit elsewhere may differ in the last bits.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import sys
from pathlib import Path

import numpy as np

from ptovs.encoders import synthetic_v4 as v4

ROOT = Path(__file__).resolve().parent.parent


def write(raw: np.ndarray, cls: np.ndarray, out: Path) -> str:
    mu, V, scale, ev = v4.fisher(raw, cls, v4.K)
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
    ap.add_argument("--out", type=Path,
                    default=ROOT / "src" / "ptovs" / "encoders" / v4.PROJECTION_FILE)  # fmt: skip
    args = ap.parse_args(argv)
    raw, cls = v4.bank_statistics(
        v4.BANK_SEEDS, lambda s, n: print(f"bank world {s}: {n} crops", flush=True)
    )
    digest = write(raw, cls, args.out)
    print(f"wrote {args.out} ({len(raw)} crops); sha256 {digest}")


if __name__ == "__main__":
    sys.exit(main())
