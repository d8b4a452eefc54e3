"""What a user does with a trained language field (docs/method.md §10).

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
    "view": "ptovs.apps.view",
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
        sets: SECTION.KEY=VALUE overrides; `query.*` ones set the decoding and
            relevancy knobs the applications share with `ptovs query`.
    """
    from ptovs.chain import run_stages
    from ptovs.options import variant_chain

    chain, ref = variant_chain(obj, scene_name, data, variant, sets, until="train-male")
    run_stages(chain, chain.closure("train-male"))
    return chain, ref


def close_inputs(inputs: Any) -> None:
    """Close the artifacts of a query stage's `Inputs` (the scene needs nothing)."""
    for art in (inputs.reconstruct, inputs.ae, inputs.male):
        art.close()
