"""Structure from motion: a folder of unposed photos → a posed COLMAP scene.

    ptovs sfm --data photos/trevi          # photos/trevi/images/*.jpg or photos/trevi/*.jpg

The stage before the chain (`ptovs.sfm` has the method and its choices). Its key is
the photos' sha256 and the `[sfm]` options; the model is stored as an artifact,
`<work>/<scene>/sfm/<key[:12]>.h5`, and materialised as an ordinary scene folder
beside it, `<work>/<scene>/sfm/<key[:12]>/` (images/, sparse/, <scene>.tsv), that
every later stage reads. Any other command given such a photo folder runs this
stage first (cached); `ptovs status` only shows it.
"""

from __future__ import annotations

from pathlib import Path

import click

from ptovs.chain import RunContext
from ptovs.locate import pose_photos, scene_source
from ptovs.options import chain_options
from ptovs.registry import SFM


@click.command(name=SFM, help=__doc__)
@chain_options(variant=None, force="Run SfM again even if it is cached.")
@click.pass_obj
def command(
    obj: RunContext,
    scene_name: str | None,
    data: Path | None,
    sets: tuple[str, ...],
    force: bool,
) -> None:
    from ptovs.config import parse_sets
    from ptovs.options import split_sets

    name, folder, photos = scene_source(scene_name, data)
    if photos is None:
        raise click.UsageError(
            f"{folder} is already a posed scene (dense/ or sparse/ inside) or holds "
            "no photos: sfm takes a folder of unposed photos (DIR/images/* or DIR/*)"
        )
    items = split_sets(sets, (SFM,), default=SFM)[SFM]
    ctx = obj.with_command(SFM, [f"{SFM}.{i}" for i in items]).for_scene(name)
    ctx = ctx.with_overrides(parse_sets(items, SFM))
    key, state, out = pose_photos(ctx, name, photos, run=True, force=force or obj.force)
    click.echo(f"{SFM}: {out} (key {key[:12]}, {state})")
