"""What a user does with a trained language field (PAPER_SPEC.md §10).

`APP_MODULES` maps each application subcommand to its module; like the stages,
the CLI imports a module only when its command runs. Applications are not
stages: they write files for people and other tools (a PLY, a vote table, a
video), not artifacts; what they read they get from the artifact store, running
any missing stage of the chain first (each cached).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

APP_MODULES: dict[str, str] = {
    "select": "ptovs.apps.select",
    "style": "ptovs.apps.style",
    "roam": "ptovs.apps.roam",
    "table": "ptovs.apps.table",
}


def trained_chain(
    obj: Any,
    scene_name: str | None,
    data: Path | None,
    variant: str,
    sets: tuple[str, ...],
):
    """The chain of `variant` for a scene with train-male built (cached stages
    return at once), and the scene reference.

    Args:
        obj: the CLI's RunContext.
        sets: STAGE.KEY=VALUE overrides; `query.*` ones set the decoding and
            relevancy knobs the applications share with `ptovs query`.
    """
    from ptovs.cli import ALL_STAGES, _run_stages, _split_sets
    from ptovs.stage import Chain, resolve_scene
    from ptovs.variants import variant_sets

    ref = resolve_scene(obj, scene_name, data)
    split = _split_sets(sets, (*ALL_STAGES, "query"))
    chain = Chain(obj, ref, variant_sets(variant, split))
    _run_stages(chain, chain.closure("train-male"), set())
    return chain, ref


def close_inputs(inputs: Any) -> None:
    """Close the artifacts of a query stage's `Inputs` (the scene needs nothing)."""
    for art in (inputs.reconstruct, inputs.ae, inputs.male):
        art.close()


def variant_option(f):
    import click

    from ptovs.variants import VARIANTS

    f = click.option(
        "--set",
        "sets",
        multiple=True,
        metavar="STAGE.KEY=VALUE",
        help="Override a config value of any stage (repeatable), e.g. "
        "query.background_filter=off.",
    )(f)
    return click.option(
        "--variant",
        type=click.Choice(list(VARIANTS)),
        default="male",
        show_default=True,
        help="Which trained field to use (see `ptovs train --variant`).",
    )(f)
