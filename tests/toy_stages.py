"""Two small stages on the real framework, for testing keys, caching and resume.

Run as a script, it is the `ptovs` CLI with these stages added (used by the tests
that kill or race real processes).
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from ptovs.artifacts import Artifact
from ptovs.registry import scene_input, upstream
from ptovs.stage import stage_command


def _note(what: str) -> None:
    path = os.environ.get("TOY_LOG")
    if path:
        with open(path, "a") as fh:
            fh.write(what + "\n")


@dataclass(frozen=True)
class ViewsConfig:
    gain: float = 1.0
    sleep: float = 0.0


@dataclass(frozen=True)
class ViewsInputs:
    scene: object = scene_input()


def run_views(inputs: ViewsInputs, config: ViewsConfig, skip=frozenset()) -> Iterator:
    scene = inputs.scene
    for view in scene.train_views():
        if view.name in skip:
            continue
        _note(f"views:{view.name}")
        time.sleep(config.sleep)
        img = scene.load_image(view)
        yield (
            view.name,
            {
                "mean": (img.mean(axis=2) * config.gain).astype(np.float32),
                "label": np.full((4, 4), 7, np.int16),
            },
        )
    yield None, {"gain": np.float64(config.gain)}


views_command = stage_command(
    "toy-views",
    1,
    ViewsConfig,
    ViewsInputs,
    run_views,
    count=lambda inputs, config: len(inputs.scene.train_views()),
    help="Toy per-view stage.",
)


@dataclass(frozen=True)
class SumConfig:
    scale: float = 1.0


@dataclass(frozen=True)
class SumInputs:
    views: Artifact = upstream("toy-views")


def run_sum(inputs: SumInputs, config: SumConfig) -> dict:
    _note("sum")
    total = sum(float(inputs.views[n]["mean"].sum()) for n in inputs.views.names())
    return {"total": np.float64(total * config.scale)}


sum_command = stage_command(
    "toy-sum",
    1,
    SumConfig,
    SumInputs,
    run_sum,
    kind="single",
    help="Toy whole-scene stage.",
)


def main() -> None:
    from ptovs.cli import main as cli

    cli.add_command(views_command)
    cli.add_command(sum_command)
    cli()


if __name__ == "__main__":
    main()
