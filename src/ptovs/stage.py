"""A stage's command: `stage_command` registers a stage and builds its click command.

A stage module (`ptovs.stages.<name>`) defines `NAME`, `VERSION`, a frozen
`Config` dataclass, a frozen `Inputs` dataclass whose fields are
`upstream("<stage>")` artifacts or `scene_input()` (`ptovs.registry`), and a pure
`run(inputs, config)` (`ptovs.chain` says how it is called), then calls
`stage_command(...)`. The command adds `--scene`, `--data`, `--set` and `--force`,
keys the whole chain before any work, and streams `run` into a resumable artifact.

The chain API that scripts use (bench/) is importable from here too: `Chain`,
`RunContext`, `execute` (`ptovs.chain`) and `resolve_scene` (`ptovs.locate`).
"""

from __future__ import annotations

import dataclasses
import inspect
import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import click

from ptovs.artifacts import Artifact, write_atomic
from ptovs.chain import Chain, RunContext, execute, run_stages
from ptovs.locate import resolve_scene
from ptovs.options import chain_options, variant_chain
from ptovs.registry import REGISTRY, StageSpec

__all__ = [
    "DONE_HELP",
    "Chain",
    "CommandExtras",
    "RunContext",
    "execute",
    "resolve_scene",
    "stage_command",
    "write_done",
]


@dataclass(frozen=True)
class CommandExtras:
    """What a stage's command adds to the plain one (`query` and `evaluate`)."""

    options: tuple[Callable, ...] = ()
    """More click options and arguments, outermost first."""
    variant: Literal["one", "many"] | None = None
    """--variant: one recipe, several side by side, or none (the paper's)."""
    overrides: Callable[[dict[str, Any]], dict[str, Any]] | None = None
    """The extra options' values → values of the stage's own config section."""
    upstream: bool = False
    """Run any missing upstream stage first (else a missing input is an error)."""
    force_also: tuple[str, ...] = ()
    """Upstream stages --force recomputes too."""
    report: Callable[..., None] | None = None
    """(ctx, scene ref, {variant: artifact}, **extra options) → None, after the run;
    default: print the artifact's path."""
    force_help: str = "Recompute even if the artifact exists."


DONE_HELP = (
    "When the stage has succeeded, write this small JSON file (atomically) with the "
    "artifact's key and path: the target the batch workflow (workflow/Snakefile) waits on."
)


def write_done(
    path: Path, stage: str, scene: str, arts: Mapping[str, Artifact]
) -> None:
    """The done-file of a finished stage: which artifact (key, path) each variant
    has, so a batch driver's target names the cached result, not a guessed path."""
    record = {
        "stage": stage,
        "scene": scene,
        "artifacts": {v: {"key": a.key, "path": str(a.path)} for v, a in arts.items()},
    }
    write_atomic(path, json.dumps(record, indent=1) + "\n")


def stage_command(
    name: str,
    version: int,
    config_cls: type,
    inputs_cls: type,
    run: Callable[..., Any],
    *,
    kind: Literal["views", "single"] = "views",
    count: Callable[[Any, Any], int] | None = None,
    after: Callable[[Artifact], None] | None = None,
    extra_key: Callable[[Any, Any], dict[str, str]] | None = None,
    summary: Callable[[dict], str | None] | None = None,
    help: str | None = None,
    extras: CommandExtras = CommandExtras(),
) -> click.Command:
    """Register a stage and build its click command (every stage's, one way)."""
    REGISTRY[name] = StageSpec(
        name,
        version,
        config_cls,
        inputs_cls,
        run,
        kind,
        count,
        after,
        extra_key,
        summary,
    )
    fields = "\n".join(
        f"  {f.name} = {f.default!r}" for f in dataclasses.fields(config_cls)
    )
    doc = (help or (inspect.getmodule(run).__doc__ or name)).strip()
    doc += f"\n\n\b\nConfig keys ([{name}] in --config, or --set KEY=VALUE):\n{fields}"

    @click.pass_obj
    def command(
        obj: RunContext,
        scene_name: str | None,
        data: Path | None,
        sets: tuple[str, ...],
        force: bool,
        done: Path | None,
        **extra: Any,
    ) -> None:
        variants = extra.pop("variants", None) or (extra.pop("variant", "male"),)
        if extra.get("out") is not None:  # an output folder: checked before any work
            from ptovs.outputs import check_output_dir

            check_output_dir("--out", extra["out"])
        ctx = obj
        if extras.overrides is not None:
            over = extras.overrides(extra)
            ctx = obj.with_overrides({name: over})  # also over a recorded config
        redo = {name, *extras.force_also} if force else set()
        arts: dict[str, Artifact] = {}
        try:
            for variant in variants:
                chain, ref = variant_chain(
                    ctx, scene_name, data, variant, sets, default=name
                )
                from ptovs.preflight import preflight

                preflight(chain, chain.closure(name) if extras.upstream else [name])
                if extras.upstream:
                    before = [s for s in chain.closure(name) if s != name]
                    run_stages(chain, before, redo, check=False)
                arts[variant] = execute(chain, name, force=name in redo or obj.force)
            if extras.report is None:
                click.echo(f"{name}: {arts[variants[0]].path}")
            else:
                extras.report(ctx, ref, arts, **extra)
            if done is not None:
                write_done(done, name, ref.name, arts)
        finally:
            for art in arts.values():
                art.close()

    for option in (
        *extras.options,
        click.option(
            "--done",
            type=click.Path(path_type=Path, dir_okay=False),
            default=None,
            help=DONE_HELP,
        ),  # fmt: skip
        chain_options(variant=extras.variant, force=extras.force_help),
    )[::-1]:
        command = option(command)
    return click.command(name=name, help=doc)(command)
