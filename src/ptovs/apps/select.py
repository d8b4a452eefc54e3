"""3-D selection to a standard Gaussian-splat PLY (docs/method.md §10.1).

    ptovs select --data data/bench_s0 "Rose Window" --out sel.ply [--rest rest.ply]

Every Gaussian's codes (levels × appearances) are decoded as `query` decodes
rendered codes (the same table, relevancy at temperature 10, background filter
and fusion over appearances; the [query] config section applies), the level with
the highest score is kept, and the Gaussians above the relative threshold
(min-max over the trained Gaussians, n > 0.7 for τ = 0.4) are selected. Gaussians
train-male never saw are never selected; `--min-opacity` drops faint ones and
`--min-visibility` those no train view shows with a blend weight that large;
`--smooth K` averages each Gaussian's score over its K nearest before the threshold.
The PLY is the one `ptovs export-ply` writes (appearance baked in).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import click

from ptovs.apps import close_inputs, trained_chain
from ptovs.errors import InputError
from ptovs.field.query import SelectOptions
from ptovs.options import chain_options
from ptovs.settings import RunContext

_DEFAULTS = SelectOptions()


def select_gaussians(chain, text: str, options=None):
    """(Selection, Querier, inputs) for one text on the chain's trained field;
    `options` a `ptovs.field.query.SelectOptions` (None: the defaults)."""
    from ptovs.field.query import Querier

    inputs = chain.inputs("query")
    querier = Querier(inputs, chain.config("query"), [text])
    return querier.select(text, options), querier, inputs


@click.command(name="select")
@click.argument("text")
@chain_options(variant="one", force=None)
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    required=True,
    help="PLY for the selected Gaussians (standard 3DGS layout).",
)
@click.option(
    "--rest",
    type=click.Path(path_type=Path),
    default=None,
    help="Also write the Gaussians not selected to this PLY.",
)
@click.option(
    "--min-opacity",
    type=click.FloatRange(0.0, 1.0),
    default=_DEFAULTS.min_opacity,
    show_default=True,
    help="Never select Gaussians less opaque than this.",
)
@click.option(
    "--min-visibility",
    type=click.FloatRange(0.0, 1.0),
    default=_DEFAULTS.min_visibility,
    show_default=True,
    help="Never select Gaussians whose largest blend weight (alpha x transmittance) "
    "in any train view is below this: hidden or faint ones no photo constrains "
    "(0: off).",
)
@click.option(
    "--smooth",
    type=click.IntRange(0, 256),
    default=_DEFAULTS.smooth,
    show_default=True,
    help="Average each Gaussian's score over its this many nearest Gaussians "
    "before thresholding, the 3-D counterpart of the 2-D mean filter (0: off).",
)
@click.option(
    "--image",
    default=None,
    help="Bake this image's appearance into the colours (default: neutral).",
)
@click.pass_obj
def command(
    obj: RunContext,
    text: str,
    scene_name: str | None,
    data: Path | None,
    out: Path,
    rest: Path | None,
    min_opacity: float,
    min_visibility: float,
    smooth: int,
    image: str | None,
    variant: str,
    sets: tuple[str, ...],
) -> None:
    """Select the Gaussians a text describes and write them as a 3DGS PLY.

    Decodes each Gaussian's language codes against TEXT with the query
    pipeline (relevancy, background filter, fusion over appearances, level
    choice, relative threshold) and writes the selection, and with --rest the
    remainder, as the standard PLY `ptovs export-ply` writes, so any 3DGS viewer
    or editor (e.g. SuperSplat) opens it. Also writes <out>.json with the
    count, level and score. Runs any missing stage of the chain first.
    """
    from ptovs.field.export import export_field_ply
    from ptovs.outputs import check_outputs, require_suffix, write_text_output

    record_path = out.with_suffix(".json")
    check_outputs({"--out": out, "--rest": rest,
                   f"the record beside --out ({record_path.name})": record_path},
                  suffix=".ply")  # fmt: skip
    require_suffix("--out", out, (".ply",))
    require_suffix("--rest", rest, (".ply",))
    chain, ref = trained_chain(obj, scene_name, data, variant, sets)
    t0 = time.perf_counter()
    options = SelectOptions(min_opacity, min_visibility, smooth)
    sel, querier, inputs = select_gaussians(chain, text, options)
    seconds = time.perf_counter() - t0
    try:
        n = int(sel.mask.sum())
        if n == 0:
            raise InputError(
                f"select: no Gaussian of {ref.name} is selected by {text!r} (highest "
                f"score {sel.score:.3f}); nothing written. Try another phrase, "
                "--min-opacity 0, or --set query.background_filter=off"
            )
        field = querier.field
        export_field_ply(
            inputs.reconstruct, out, image=image, index=sel.mask, field=field
        )
        if rest is not None:
            export_field_ply(
                inputs.reconstruct, rest, image=image, index=~sel.mask, field=field
            )
        record = {
            "scene": ref.name,
            "text": text,
            "variant": variant,
            "selected": n,
            "gaussians": int(len(sel.mask)),
            "level": querier.levels[sel.level],
            "score": round(sel.score, 5),
            "seconds": round(seconds, 3),
            "ply": str(out),
            "rest": str(rest) if rest else None,
        }
        write_text_output(record_path, json.dumps(record, indent=1))
    finally:
        close_inputs(inputs)
    click.echo(
        f"select {text!r}: {n} of {len(sel.mask)} Gaussians "
        f"({100 * n / len(sel.mask):.1f} %), level {record['level']}, "
        f"score {sel.score:.3f}, {seconds:.2f} s -> {out}"
        + (f" (rest: {rest})" if rest else "")
    )
