"""The per-scene and mean table over every scene under a data folder (Table 1 style).

    ptovs table --data data [--variant male --variant langsplat] [--out work/table.md]

For each scene folder under --data (the PT-OVS `label` folder is not a scene)
and each variant, reads that chain's `evaluate` artifact from the store if it
exists; it runs nothing. A scene without one is marked "failed" when its
`<work>/<scene>/FAILED` marker exists (the Makefile's batch target writes it
when a stage fails, with the log's tail) and "–" (not run) otherwise; the mean
column is over the scenes with numbers and starred when some are missing.
--data may also be one scene folder (posed, or a folder of photos): the table
then has that scene's column only.
"""

from __future__ import annotations

import json
from pathlib import Path

import click

from ptovs.pipeline import check_scene_names, scene_folders
from ptovs.settings import RunContext
from ptovs.variants import VARIANTS

FAILED_MARKER = "FAILED"


def is_scene(folder: Path) -> bool:
    """Whether `folder` is itself a scene rather than a folder of scenes: a posed
    scene (`dense/` or `sparse/` in it), or photos (in it or in `images/`) beside
    no posed scene."""
    from ptovs.sfm import is_posed, photo_dir

    if is_posed(folder):
        return True
    if photo_dir(folder) is None:
        return False
    return not any(is_posed(p) for p in folder.iterdir() if p.is_dir())


def table_scenes(data: Path) -> list[Path]:
    """The scene folders the table covers: `data` itself when it is a scene, else
    those under it (`scene_folders`)."""
    if is_scene(data):
        folder = data if data.name not in ("", "..") else data.resolve()
        check_scene_names([folder.name], f"--data {data}")
        return [folder]
    return scene_folders(data)


def collect(
    obj: RunContext, folders: list[Path], variants: tuple[str, ...]
) -> tuple[dict, dict]:
    """({variant: {scene: summary or None}}, {scene: failure text}) over the scene
    folders `table_scenes` found."""
    from ptovs.chain import Chain
    from ptovs.errors import InputError, MissingInputError
    from ptovs.locate import resolve_scene
    from ptovs.metrics import read_metrics
    from ptovs.variants import variant_sets

    rows: dict[str, dict] = {v: {} for v in variants}
    failures: dict[str, str] = {}
    for folder in folders:
        name = folder.name
        marker = obj.work_dir / name / FAILED_MARKER
        if marker.is_file():
            lines = marker.read_text().strip().splitlines()
            failures[name] = lines[-1] if lines else "failed"
        try:
            ref = resolve_scene(obj, name, folder)
        except (InputError, MissingInputError, OSError, ValueError) as exc:
            failures.setdefault(name, str(exc).splitlines()[0])
            ref = None
        for variant in variants:
            summary, art = None, None
            if ref is not None:
                try:
                    key = Chain(obj, ref, variant_sets(variant, {})).key("evaluate")
                    art = obj.store.lookup(name, "evaluate", key)
                except (InputError, MissingInputError, OSError, ValueError) as exc:
                    failures.setdefault(name, str(exc).splitlines()[0])
            if art is not None:
                try:
                    summary, _ = read_metrics(art)
                finally:
                    art.close()
            if summary is not None or name in failures:
                rows[variant][name] = summary  # None shows as "failed"
    return rows, failures


@click.command(name="table")
@click.option("--data", type=click.Path(path_type=Path, file_okay=False), required=True,
              help="Folder of scene folders (e.g. the seven PT-OVS scenes), or one scene.")  # fmt: skip
@click.option("--variant", "variants", multiple=True, default=("male",),
              type=click.Choice(list(VARIANTS)), show_default=True,
              help="Variant rows (repeatable).")  # fmt: skip
@click.option("--out", type=click.Path(path_type=Path), default=None,
              help="Also write the table here (Markdown) and <out>.json.")  # fmt: skip
@click.option("--strict", is_flag=True,
              help="Exit with status 1 when a scene has no numbers.")  # fmt: skip
@click.pass_obj
def command(obj: RunContext, data: Path, variants: tuple[str, ...], out: Path | None,
            strict: bool) -> None:  # fmt: skip
    """Print mIoU / mPA / mP per scene and their mean, one row per variant.

    Reads the evaluate artifacts the pipeline wrote for every scene under
    --data (or for --data itself when it is one scene); runs nothing (use
    `make -j3 all DATA=...` or `ptovs evaluate`).
    """
    from ptovs.artifacts import write_atomic
    from ptovs.metrics import markdown_table

    if not data.is_dir():
        raise click.BadParameter(f"{data} is not a folder", param_hint="--data")
    if out is not None:
        from ptovs.outputs import check_outputs

        check_outputs({"--out": out, f"the record beside --out "
                       f"({out.with_suffix('.json').name})": out.with_suffix(".json")},
                      suffix=".md")  # fmt: skip
    folders = table_scenes(data)
    if not folders:
        raise click.ClickException(f"no scene folders under {data}")
    rows, failures = collect(obj, folders, variants)
    scenes = [f.name for f in folders]
    table = markdown_table(rows, scenes)
    if failures:
        table += (
            "\n"
            + "\n".join(f"- {s}: failed ({why})" for s, why in failures.items())
            + "\n"
        )
    click.echo(table)
    if out is not None:
        write_atomic(out, table)
        write_atomic(out.with_suffix(".json"),
                     json.dumps({"results": rows, "failed": failures}, indent=1))  # fmt: skip
        click.echo(f"table: {out}")
    missing = [s for s in scenes if any(r.get(s) is None for r in rows.values())]
    if strict and missing:
        raise SystemExit(1)
