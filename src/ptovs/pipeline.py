"""What the batch drivers read: the stage order, the scene list, each stage's needs.

The Makefile (`make all`) and the Snakemake workflow (`workflow/Snakefile`) both
run every stage of every scene; they take the stages, in order, and the scenes
under a data folder from here, so the two can never disagree. The stage framework
(`ptovs.stage`) takes PIPELINE from here too.

Standard library only: the Makefile runs it with the system Python before the
virtual environment exists,

    PYTHONPATH=src python3 -m ptovs.pipeline stages
    PYTHONPATH=src python3 -m ptovs.pipeline scenes data
    PYTHONPATH=src python3 -m ptovs.pipeline check-scenes "tiny_s0 tiny_s1"
    PYTHONPATH=src python3 -m ptovs.pipeline resources

Both drivers put scene names into shell commands, so a scene name is one of
SCENE_NAME: a folder under the data folder named otherwise is refused (with the
folder's name and the fix), never run and never silently skipped.
"""

from __future__ import annotations

import math
import re
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

from ptovs.errors import InputError  # stdlib only, as this module

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

# What a scene may be named: the Makefile and the workflow put scene names into
# shell commands (and file paths), so no shell metacharacter, space, quote or "/"
# and no leading "-" (an option) or "." (hidden, "..") gets in. It admits every
# name in use: tiny_s0, bench_s1, fountain_p11, brandenburg_gate,
# notre_dame_front_facade. The workflow's `wildcard_constraints` is this pattern.
SCENE_NAME = r"[A-Za-z0-9][A-Za-z0-9._-]*"
_SCENE_NAME = re.compile(SCENE_NAME, re.ASCII)


class SceneNameError(InputError):
    """A scene name outside SCENE_NAME; the message names it and the fix."""


def is_scene_name(name: str) -> bool:
    """Whether `name` is an allowed scene name (the whole of it matches SCENE_NAME)."""
    return _SCENE_NAME.fullmatch(name) is not None


def check_scene_names(names: list[str], where: str, fix: str = "") -> list[str]:
    """`names` when every one is an allowed scene name; else SceneNameError naming
    each bad one, where it came from (`where`: a data folder, an option) and the fix
    (`fix`; default: rename the folders)."""
    bad = [n for n in names if not is_scene_name(n)]
    if bad:
        s = "s" if len(bad) > 1 else ""
        fix = fix or f"rename the folder{s}"
        raise SceneNameError(
            f"scene name{s} not allowed in {where}: {', '.join(map(repr, bad))}. "
            "A scene name holds only letters, digits, '.', '_' and '-', and begins "
            "with a letter or digit (make all and workflow/Snakefile put scene names "
            f"into shell commands); {fix}, e.g. "
            + ", ".join(f"{n!r} to {_suggest(n)!r}" for n in bad)
            + ". Nothing was run."
        )
    return names


def _suggest(name: str) -> str:
    """An allowed name close to `name` (for the message)."""
    return (
        re.sub(r"[^A-Za-z0-9._-]+", "_", name, flags=re.ASCII).lstrip("._-") or "scene"
    )


def scene_folders(data: Path | str) -> list[Path]:
    """The scene folders under a data folder, by name (none if it is missing):
    every folder but `label` and hidden ones. SceneNameError when a folder's name
    is not an allowed scene name (SCENE_NAME)."""
    data = Path(data)
    if not data.is_dir():
        return []
    folders = sorted(
        p for p in data.iterdir() if p.is_dir() and p.name not in NOT_SCENES
        and not p.name.startswith(".")
    )  # fmt: skip
    check_scene_names([p.name for p in folders], f"the data folder {data}")
    return folders


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
    usage = (
        "usage: python -m ptovs.pipeline stages | scenes DATA | check-scenes NAMES"
        " | resources"
    )
    if argv == ["stages"]:
        print(" ".join(PIPELINE))
    elif len(argv) == 2 and argv[0] in ("scenes", "check-scenes"):
        # scenes: the folders under DATA; check-scenes: a list given (make SCENES=...).
        # A name not allowed: the message on stderr, nothing on stdout, exit 3 (the
        # Makefile tells it from a traceback's 1)
        try:
            if argv[0] == "scenes":
                names = [p.name for p in scene_folders(argv[1])]
            else:
                names = check_scene_names(argv[1].split(), "SCENES", "give other names")
        except SceneNameError as exc:
            print(f"ptovs.pipeline: {exc}", file=sys.stderr)
            return 3
        print(" ".join(names))
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
