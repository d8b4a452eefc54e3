"""What the batch drivers read: the stage order, the scene list, each stage's needs.

The Makefile (`make all`) and the Snakemake workflow (`workflow/Snakefile`) both
run every stage of every scene; they take the stages, in order, and the scenes
under a data folder from here, so the two can never disagree. The stage framework
(`ptovs.registry`, `ptovs.chain`) take PIPELINE from here too.

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


# The photo files a scene's stages read (ptovs.sfm takes them from here).
IMAGE_EXTS = frozenset(
    {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp", ".webp", ".jp2"}
)


def scene_photos(folder: Path | str) -> int:
    """How many photos a scene folder holds: in dense/images (a posed scene), in
    images/ or in the folder itself (a collection of photos), the first that has
    any; 0 when none does. The batch drivers size a job's memory and time with it."""
    folder = Path(folder)
    for cand in (folder / "dense" / "images", folder / "images", folder):
        try:
            n = sum(
                1
                for p in cand.iterdir()
                if p.suffix.lower() in IMAGE_EXTS and p.is_file()
            )
        except OSError:
            continue
        if n:
            return n
    return 0


# The collection the resource table is measured on: a Brandenburg-sized scene (the
# smallest of the seven PT-OVS scenes), `ptovs synth-scene --preset landmark`.
REF_PHOTOS = 763
FLOOR_MB = 512  # no stage's process peaks lower (torch alone is ~300 MB)


@dataclass(frozen=True)
class Resources:
    """What one stage of one scene asks a cluster for (`workflow/Snakefile`).

    `peak_mb` is the stage's peak RSS measured on a collection of REF_PHOTOS
    photos of a real photo size (docs/findings.md, "A landmark-sized collection on
    one machine"). A stage whose memory must grow with the photos says so in
    `mb_per_photo` (the measured growth a photo); for a scene of n photos the
    peak is taken as peak_mb + mb_per_photo * (n - REF_PHOTOS), never below
    FLOOR_MB, and the job asks for half as much again (`mem_mb_for`). `minutes` is
    the time limit at REF_PHOTOS, with room; it grows in proportion past them (up
    to 763 photos no stage's time grew faster than its photos; past them the
    Gaussians grow too, which the room covers). `threads` is what the stage uses
    well on a cluster node; on one machine the workflow shares the cores among the
    scenes as `make all` does. `device` names the stage's config key that can put
    it on a GPU ("" = CPU only): when the config sets it to cuda, the job goes to
    the GPU partition."""

    threads: int
    peak_mb: int
    minutes: int
    device: str = ""
    mb_per_photo: float = 0.0

    def peak_mb_for(self, photos: int) -> float:
        """The expected peak RSS (MB) for a scene of `photos` photos."""
        return max(FLOOR_MB, self.peak_mb + self.mb_per_photo * (photos - REF_PHOTOS))

    def mem_mb_for(self, photos: int) -> int:
        """The memory request (MB) for a scene of `photos` photos: 1.5x its peak,
        in steps of 256 MB."""
        return 256 * math.ceil(1.5 * self.peak_mb_for(photos) / 256)

    def minutes_for(self, photos: int) -> int:
        """The time limit (minutes) for a scene of `photos` photos."""
        return max(self.minutes, math.ceil(self.minutes * photos / REF_PHOTOS))

    @property
    def mem_mb(self) -> int:
        """The memory request at REF_PHOTOS photos."""
        return self.mem_mb_for(REF_PHOTOS)


# peak_mb: the largest peak RSS measured for the stage's process (MB) on the
# `landmark` preset's seed 0 (640-760 px photos) at 763 photos with the default
# config, one process a stage (bench/growth.py, 2026-11-26/27; train-male after its
# memory fixes); where a `bench` run (80 small photos) peaked higher (uncertainty),
# that figure. mb_per_photo, for the stages whose memory grows: reconstruct
# holds its photos and trains a Gaussian per SfM point, 2.9 MB a photo (measured:
# 3.1, 5.1 and 11.3 GB at 100, 763 and 2,934 photos); train-ae holds its segments'
# features, 1.1 MB a photo between 100 and 763 photos; train-male's lift sums 24.6 KB
# a Gaussian (3 levels x 4 slots x 512 floats) until it reaches cache_mb (then it
# makes more passes instead), and the Gaussians follow the photos (55 a photo at
# 763, 52 at 2,934): 1.3 MB a photo; render-appearances renders those Gaussians,
# 0.25 MB a photo (808 and 1,289 MB at 763 and 2,934 photos). minutes: at least 3x
# the 763-photo wall time on our 2 cores (a cluster core may be slower). threads:
# measured on 16 cores at the landmark photo size (bench/threads.py, 2026-11-27):
# reconstruct ran 1.97x faster at 8 threads than at 2 (2.56x at 16); every other stage
# gained at most 1.29x at 8 or 16 threads, and extract-features, uncertainty and
# train-ae ran slower (0.77-0.93x), so they ask for 2. query was not measured at that
# size (1.43x from 1 to 2 threads on small photos) and asks for 2.
RESOURCES: dict[str, Resources] = {
    "reconstruct": Resources(threads=8, peak_mb=5112, minutes=60, mb_per_photo=2.9),
    "render-appearances": Resources(
        threads=2, peak_mb=808, minutes=20, mb_per_photo=0.25
    ),
    "extract-features": Resources(threads=2, peak_mb=571, minutes=60, device="device"),
    "uncertainty": Resources(threads=2, peak_mb=715, minutes=30),
    "train-ae": Resources(threads=2, peak_mb=1257, minutes=30, mb_per_photo=1.1),
    "train-male": Resources(threads=2, peak_mb=4335, minutes=45, mb_per_photo=1.6),
    "query": Resources(threads=2, peak_mb=1141, minutes=20, device="device"),
    "evaluate": Resources(threads=1, peak_mb=424, minutes=10),
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
