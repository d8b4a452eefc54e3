"""The stage registry: which stages exist, what each declares, and the config
sections.

A stage module (`ptovs.stages.<name>`, listed in STAGE_MODULES) registers its
StageSpec when imported (`ptovs.stage.stage_command`); `get_stage` and
`all_stages` import the modules on demand, so nothing heavy loads before a command
needs it. Its `Inputs` fields are declared with `upstream("<stage>")` or
`scene_input()`.

Every config section has a dataclass: `[scene]` (SceneConfig), `[sfm]`
(`ptovs.sfm_match.SfmConfig`) and each stage's `Config`; `config_sections` lists
them with their keys (`ptovs.config` checks a config against them).
"""

from __future__ import annotations

import dataclasses
import importlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

from ptovs.errors import InputError
from ptovs.pipeline import PIPELINE  # the chain, in order (one list for every driver)

STAGE_MODULES: dict[str, str] = {
    name: "ptovs.stages." + name.replace("-", "_") for name in ("sfm", *PIPELINE)
}


def stages_between(first: str, last: str) -> tuple[str, ...]:
    """The stages of PIPELINE from `first` to `last`, both included."""
    return PIPELINE[PIPELINE.index(first) : PIPELINE.index(last) + 1]


EXTRACT_STAGES = stages_between("render-appearances", "uncertainty")  # ptovs extract
TRAIN_STAGES = stages_between("train-ae", "train-male")  # ptovs train
SCENE = "scene"  # pseudo-stage: the input data itself
SFM = "sfm"  # the stage before the chain: a folder of unposed photos → a posed scene
SCENE_VERSION = 1


@dataclass(frozen=True)
class SceneConfig:
    """How a scene folder is read (config section `[scene]`)."""

    downscale: int | str = "auto"
    """Image downscale factor r; "auto" = the smallest r that brings the photos'
    median long side to at most 1,000 px (r = 4 for 12 MP photos, 1 for small ones)."""
    split_file: str = "auto"
    """"auto" (the single *.tsv in the scene root), "all-train", or a path."""
    distortion: Literal["refuse", "ignore"] = "refuse"
    """Non-zero lens distortion: refuse (undistort first) or ignore (authors' code)."""


def upstream(stage: str, *, when: Callable[[Any], bool] | None = None) -> Any:
    """Declare an `Inputs` field filled with the named stage's artifact.

    `when(config)` makes the input conditional: where it returns False the stage
    neither needs nor is keyed by that upstream, and the field is None (e.g.
    train-ae without uncertainty weighting does not depend on `uncertainty`).
    """
    return field(metadata={"stage": stage, "when": when})


def scene_input() -> Any:
    """Declare an `Inputs` field filled with the loaded `ptovs.scene.Scene`."""
    return field(metadata={"stage": SCENE})


@dataclass(frozen=True)
class StageSpec:
    name: str
    version: int
    config_cls: type
    inputs_cls: type
    run: Callable[..., Any]
    kind: Literal["views", "single"]
    count: Callable[[Any, Any], int] | None = None
    after: Callable[[Any], None] | None = None
    """Runs on the finished (or cached) `ptovs.artifacts.Artifact`, e.g. to write
    PNG previews."""
    extra_key: Callable[[Any, Any], dict[str, str]] | None = None
    """(config, SceneRef) -> {name: digest} of what else the output depends on
    (files outside the scene fingerprint, e.g. the stand-in encoder's vocabulary)."""
    summary: Callable[[dict], str | None] | None = None
    """The artifact's metrics (its root `metrics_json`) -> the line `ptovs status`
    shows under a done stage (None: nothing to show)."""

    @property
    def inputs(self) -> dict[str, str]:
        """{Inputs field: upstream stage name}, conditional inputs included."""
        return {
            f.name: f.metadata["stage"] for f in dataclasses.fields(self.inputs_cls)
        }

    def needed_inputs(self, config: Any) -> dict[str, str]:
        """{Inputs field: upstream stage name} that this config depends on."""
        return {
            f.name: f.metadata["stage"]
            for f in dataclasses.fields(self.inputs_cls)
            if f.metadata.get("when") is None or f.metadata["when"](config)
        }


REGISTRY: dict[str, StageSpec] = {}


def all_stages() -> list[StageSpec]:
    """Every available stage, pipeline order first (imports the stage modules)."""
    for module in STAGE_MODULES.values():
        importlib.import_module(module)
    order = {name: i for i, name in enumerate(PIPELINE)}
    return sorted(
        REGISTRY.values(), key=lambda s: (order.get(s.name, len(order)), s.name)
    )


def get_stage(name: str) -> StageSpec:
    if name not in REGISTRY:
        if name in STAGE_MODULES:
            importlib.import_module(STAGE_MODULES[name])
    if name not in REGISTRY:
        raise InputError(f"unknown stage {name!r}; available: {sorted(REGISTRY)}")
    return REGISTRY[name]


def config_class(name: str) -> type:
    """The config dataclass of section `name`: [scene], [sfm] or a stage's."""
    if name == SCENE:
        return SceneConfig
    if name == SFM:
        from ptovs.sfm_match import SfmConfig  # on demand: it loads OpenCV

        return SfmConfig
    return get_stage(name).config_cls


def section_names() -> list[str]:
    """Every config section, in the order messages list them."""
    return list(dict.fromkeys([SCENE, *STAGE_MODULES, *REGISTRY]))


def config_keys(name: str) -> list[str]:
    return [f.name for f in dataclasses.fields(config_class(name))]


def config_sections() -> dict[str, list[str]]:
    """Every config section and its keys (imports every stage's module)."""
    return {name: config_keys(name) for name in section_names()}
