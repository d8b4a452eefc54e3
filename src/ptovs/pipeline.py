"""What the batch drivers read: the stage order, the scene list, each stage's needs.

The Makefile (`make all`) and the Snakemake workflow (`workflow/Snakefile`) both
run every stage of every scene; they take the stages, in order, and the scenes
under a data folder from here, so the two can never disagree. The stage framework
(`ptovs.stage`) takes PIPELINE from here too.

Standard library only: the Makefile runs it with the system Python before the
virtual environment exists,

    PYTHONPATH=src python3 -m ptovs.pipeline stages
    PYTHONPATH=src python3 -m ptovs.pipeline scenes data
    PYTHONPATH=src python3 -m ptovs.pipeline resources
"""

from __future__ import annotations

import math
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

# The chain, in dependency order: every stage group, the CLI's chain commands, the
# Makefile's STAGES and the workflow's rules are derived from it. Stage NAME lives
# in module ptovs.stages.<name with _ for ->.
PIPELINE = (
    "reconstruct",
    "render-appearances",
    "extract-features",
    "uncertainty",
    "train-ae",
    "train-male",
    "query",
    "evaluate",
)

NOT_SCENES = ("label",)  # the PT-OVS layout's label folder sits beside the scenes


def scene_folders(data: Path | str) -> list[Path]:
    """The scene folders under a data folder, by name (none if it is missing)."""
    data = Path(data)
    if not data.is_dir():
        return []
    return sorted(
        p for p in data.iterdir() if p.is_dir() and p.name not in NOT_SCENES
        and not p.name.startswith(".")
    )  # fmt: skip


@dataclass(frozen=True)
class Resources:
    """What one stage of one scene asks a cluster for (`workflow/Snakefile`).

    `peak_mb` is the largest peak RSS measured for the stage (docs/benchmarks.md,
    "Many scenes, many machines"); the job asks for half as much again. `threads`
    is what the stage uses well on a cluster node; on one machine the workflow
    shares the cores among the scenes as `make all` does. `minutes` is the time
    limit for a `bench`-sized scene on one such job, with room; a PT-OVS scene
    needs the profile's override (the same section shows how much). `device` names
    the stage's config key that can put it on a GPU ("" = CPU only): when the
    config sets it to cuda, the job goes to the GPU partition."""

    threads: int
    peak_mb: int
    minutes: int
    device: str = ""

    @property
    def mem_mb(self) -> int:
        return 256 * math.ceil(1.5 * self.peak_mb / 256)


# peak_mb: the largest peak RSS measured for the stage's process (MB): the `bench`
# preset (80 photos of 320x240, ~25k Gaussians) through the workflow's benchmark
# files on 2026-11-26 (bench/cluster.py --parts stages), the tiny scenes' jobs in
# sacct (query), and earlier bench and `scale` (3,000 photos) runs in
# docs/benchmarks.md (reconstruct, render-appearances, extract-features,
# uncertainty, train-ae). train-male is the default recipe (the lift); the
# optimising variants peaked at 4.8 GB on bench.
RESOURCES: dict[str, Resources] = {
    "reconstruct": Resources(threads=8, peak_mb=1526, minutes=60),
    "render-appearances": Resources(threads=4, peak_mb=516, minutes=20),
    "extract-features": Resources(threads=4, peak_mb=571, minutes=30, device="device"),
    "uncertainty": Resources(threads=4, peak_mb=715, minutes=20),
    "train-ae": Resources(threads=4, peak_mb=562, minutes=30),
    "train-male": Resources(threads=8, peak_mb=3484, minutes=30),
    "query": Resources(threads=4, peak_mb=760, minutes=20, device="device"),
    "evaluate": Resources(threads=1, peak_mb=356, minutes=10),
}


def rule_name(stage: str) -> str:
    """A stage's rule in the workflow (Snakemake rule names are identifiers)."""
    return stage.replace("-", "_")


def main(argv: list[str]) -> int:
    usage = "usage: python -m ptovs.pipeline stages | scenes DATA | resources"
    if argv == ["stages"]:
        print(" ".join(PIPELINE))
    elif len(argv) == 2 and argv[0] == "scenes":
        print(" ".join(p.name for p in scene_folders(argv[1])))
    elif argv == ["resources"]:
        for stage in PIPELINE:
            r = RESOURCES[stage]
            print(
                stage, *(f"{k}={v}" for k, v in asdict(r).items()), f"mem_mb={r.mem_mb}"
            )
    else:
        print(usage, file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
