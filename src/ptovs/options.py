"""The command line's shared options and what they resolve to.

Every command over the chain takes --scene and --data (`scene_options`), and
most take --set, --variant and --force too (`chain_options`). `split_sets` reads
`--set` items the same way for every command, and `variant_chain` turns a
command's options into the chain of a recipe (`ptovs.variants`) for its scene.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Literal

import click

from ptovs.chain import Chain, SceneRef
from ptovs.config import did_you_mean
from ptovs.locate import scene_ref, scene_source
from ptovs.pipeline import PIPELINE
from ptovs.registry import REGISTRY, SCENE
from ptovs.settings import RunContext, Settings, resolve_settings


def scene_options(f: Callable) -> Callable:
    f = click.option(
        "--data",
        type=click.Path(path_type=Path),
        default=None,
        help="Scene folder (default: data/<scene>, or $PTOVS_DATA/<scene>).",
    )(f)
    f = click.option(
        "--scene",
        "scene_name",
        default=None,
        help="Scene name (default: the --data folder's name).",
    )(f)
    return f


SET_HELP = (
    "Override a config value (repeatable): STAGE.KEY=VALUE, STAGE any stage of the "
    "chain or scene; on a stage's own command KEY=VALUE sets that stage's keys."
)


def split_sets(
    sets: Iterable[str], sections: Iterable[str], default: str | None = None
) -> dict[str, list[str]]:
    """`--set` items → {section: ["key=value", ...]}, one grammar for every command.

    An item is `STAGE.KEY=VALUE` (STAGE a stage or `scene`); on a stage's own
    command `KEY=VALUE` means that stage (`default`). A section outside `sections`
    is an error naming the choices, never silently ignored.
    """
    allowed = list(dict.fromkeys(sections))
    out: dict[str, list[str]] = {name: [] for name in allowed}
    for item in sets:
        key, eq, value = item.partition("=")
        section, dot, rest = key.partition(".")
        if not dot:
            section, rest = default or "", key
        if not eq or not rest.strip() or section not in out:
            near = did_you_mean(section, allowed) if dot else ""
            raise click.UsageError(
                f"--set {item!r}: "
                + (f"no stage {section!r}{near}; " if near else "")
                + "write STAGE.KEY=VALUE with STAGE one of "
                f"{', '.join(allowed)} (e.g. --set extract-features.segmenter=graph)"
                + (f", or KEY=VALUE for [{default}]" if default else "")
            )
        out[section].append(f"{rest.strip()}={value}")
    return out


def chain_options(
    *,
    variant: Literal["one", "many"] | None = "one",
    force: str | None = "Recompute even if cached.",
):
    """The options every command over the chain shares: --scene, --data, --set,
    --variant (one, repeatable, or none: `variant`) and --force (its help text, or
    none: the applications write no artifact)."""

    def wrap(f: Callable) -> Callable:
        if force is not None:
            f = click.option("--force", is_flag=True, help=force)(f)
        f = click.option(
            "--set", "sets", multiple=True, metavar="STAGE.KEY=VALUE", help=SET_HELP
        )(f)
        if variant is not None:
            from ptovs.variants import VARIANTS

            many = variant == "many"
            f = click.option(
                "--variant",
                "variants" if many else "variant",
                multiple=many,
                type=click.Choice(list(VARIANTS)),
                default=None if many else "male",
                show_default=not many,
                help="Which recipe: male (the paper's MALE-GS, with the authors' "
                "code's AE weighting); paper (the paper's text exactly); lift (no "
                "optimiser: each Gaussian's weighted mean feature); langsplat "
                "(LangSplat's: one appearance, originals only, no uncertainty, on "
                "plain-3DGS geometry); langsplat-wild (that recipe on the "
                "in-the-wild geometry); a Table 3 ablation or an iteration budget "
                "(ptovs.variants)." + (" Repeatable: side by side." if many else ""),
            )(f)
        return scene_options(f)

    return wrap


def variant_chain(
    ctx: RunContext,
    scene_name: str | None,
    data: Path | None,
    variant: str,
    sets: Iterable[str],
    default: str | None = None,
    until: str | None = None,
) -> tuple[Chain, SceneRef]:
    """The chain of a recipe (`ptovs.variants`) for a scene, with the command's
    `--set` items (SECTION.KEY=VALUE; KEY=VALUE for `default`'s section). The
    scene's settings are resolved once, here (`ptovs.settings.resolve_settings`),
    and passed down. `until` (the last stage the command will run, default
    `default`) decides what a folder of unposed photos is checked for before SfM
    poses it."""
    from ptovs.variants import variant_sets

    split = split_sets(sets, (*PIPELINE, *REGISTRY, SCENE), default)
    # the command's own --set items are part of the settings the scene records
    click_ctx = click.get_current_context(silent=True)
    name = (click_ctx.info_name if click_ctx else None) or default or "ptovs"
    ctx = ctx.with_command(
        name, [f"{sec}.{item}" for sec, items in split.items() for item in items]
    )
    last = until or default
    extract = "extract-features"
    needs = last in PIPELINE and PIPELINE.index(last) >= PIPELINE.index(extract)

    def before_sfm(settings: Settings) -> None:  # before SfM's minutes
        if needs:  # what the features will need
            from ptovs.preflight import check_extract_config

            check_extract_config(settings.build(extract))

    scene, folder, photos = scene_source(scene_name, data)
    settings = resolve_settings(ctx, scene, split)
    ref = scene_ref(settings, scene, folder, photos, before_sfm)
    return Chain(settings, ref, variant_sets(variant)), ref
