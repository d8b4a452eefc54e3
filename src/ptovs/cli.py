"""The `ptovs` command line: a click group; each stage imports itself when called."""

from __future__ import annotations

import importlib
import logging
import os
import re
import sys
from pathlib import Path

import click

from ptovs import __version__
from ptovs.chain import run_stages
from ptovs.errors import InputError, MissingInputError
from ptovs.locate import resolve_scene
from ptovs.options import chain_options, scene_options, variant_chain
from ptovs.registry import EXTRACT_STAGES, STAGE_MODULES, TRAIN_STAGES
from ptovs.settings import RunContext, resolve_settings

log = logging.getLogger("ptovs")


def _openmp_defaults() -> None:
    """OpenMP threads spin ~30 µs when a parallel region ends, then sleep
    (GOMP_SPINCOUNT=3000; libgomp's default spins ~3 ms). Spinning that long took
    the cores a shared machine's other work needed; sleeping at once
    (OMP_WAIT_POLICY=PASSIVE) made each of a training step's
    thousands of small tensor operations wait for a wake-up: 216-228 ms a bench
    step alone against 158 ms here (docs/findings.md, reconstruct's speed).
    Runs before torch loads its OpenMP runtime; a user's own setting wins."""
    if "OMP_WAIT_POLICY" not in os.environ and "GOMP_SPINCOUNT" not in os.environ:
        os.environ["GOMP_SPINCOUNT"] = "3000"


_openmp_defaults()


# the group's options that take a value (to find where the subcommand starts)
_GROUP_VALUED = ("--work-dir", "--config", "--set", "--threads")
_GROUP_FLAGS = ("--verbose", "--quiet", "--deterministic", "--nondeterministic")


def hoist_global_flags(args: list[str]) -> list[str]:
    """-v/-q/--threads N/--(non)deterministic given after the subcommand, moved
    before it, so that they work on either side (no subcommand has options of those
    names). Tokens after `--` stay where they are."""
    args = list(args)
    i = 0
    while i < len(args) and args[i].startswith("-") and args[i] != "--":
        i += 2 if args[i] in _GROUP_VALUED else 1
    if i >= len(args) or args[i] == "--":
        return args
    head, sub, rest = args[:i], args[i], args[i + 1 :]
    moved, kept, j = [], [], 0
    while j < len(rest):
        tok = rest[j]
        if tok == "--":
            kept += rest[j:]
            break
        if tok in _GROUP_FLAGS or re.fullmatch(r"-(v+|q+)", tok):
            moved.append(tok)
        elif tok == "--threads" and j + 1 < len(rest):
            moved += [tok, rest[j + 1]]
            j += 1
        elif tok.startswith("--threads="):
            moved.append(tok)
        else:
            kept.append(tok)
        j += 1
    return [*head, *moved, sub, *kept]


class LazyGroup(click.Group):
    """Lists stage and application commands without importing their modules."""

    def parse_args(self, ctx: click.Context, args: list[str]) -> list[str]:
        return super().parse_args(ctx, hoist_global_flags(args))

    def list_commands(self, ctx: click.Context) -> list[str]:
        from ptovs.apps import APP_MODULES

        return sorted(
            set(super().list_commands(ctx)) | set(STAGE_MODULES) | set(APP_MODULES)
        )

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        cmd = super().get_command(ctx, name)
        if cmd is not None:
            return cmd
        from ptovs.apps import APP_MODULES

        module = STAGE_MODULES.get(name) or APP_MODULES.get(name)
        if module is not None:
            return importlib.import_module(module).command
        return None

    def resolve_command(self, ctx: click.Context, args: list[str]) -> tuple:
        """A misspelt command is told the nearest one, stage and application
        commands included (click's own suggestion sees only those imported)."""
        try:
            return super().resolve_command(ctx, args)
        except click.UsageError:
            name = args[0] if args else ""
            if (
                name
                and not name.startswith("-")
                and name not in self.list_commands(ctx)
            ):
                from ptovs.config import did_you_mean

                hint = did_you_mean(name, self.list_commands(ctx))
                if hint:
                    raise click.UsageError(
                        f"No such command {name!r}{hint}", ctx
                    ) from None
            raise

    def invoke(self, ctx: click.Context) -> object:
        """Errors a user can cause become one-line messages (exit 1); `-vv` shows
        the traceback as well. A command that fails leaves the scene's recorded
        settings as they were (`ptovs.keys.undo_checked_writes`); one interrupted
        keeps them, so its rerun resumes with them."""
        from ptovs.keys import forget_checked_writes, undo_checked_writes

        try:
            out = super().invoke(ctx)
        except (KeyboardInterrupt, click.exceptions.Abort):
            forget_checked_writes()
            raise
        except (InputError, MissingInputError, OSError, MemoryError) as exc:
            undo_checked_writes()
            if _TRACEBACKS:
                log.debug("traceback", exc_info=True)
            raise click.ClickException(_user_message(exc)) from None
        except click.exceptions.Exit as exc:
            if exc.exit_code:
                undo_checked_writes()
            forget_checked_writes()
            raise
        except BaseException:
            undo_checked_writes()
            raise
        forget_checked_writes()
        return out


def _user_message(exc: BaseException) -> str:
    """The one line the CLI prints for an error a user can cause."""
    if isinstance(exc, InputError | MissingInputError):  # before OSError: a subclass
        return str(exc)
    if isinstance(exc, OSError):  # permission, full disk, a folder in the way, ...
        from ptovs.outputs import describe_os_error

        return describe_os_error(exc)
    return (
        "out of memory; lower the sizes given (--size, --images, scene.downscale) "
        "or free memory (run with -vv for the traceback)"
    )


_TRACEBACKS = False  # set by -vv: errors mapped to messages also log their traceback


def _setup_logging(verbose: int, quiet: int) -> None:
    global _TRACEBACKS
    _TRACEBACKS = verbose >= 2
    level = logging.INFO - 10 * verbose + 10 * quiet
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("ptovs: %(message)s"))
    root = logging.getLogger("ptovs")
    root.handlers[:] = [handler]
    root.setLevel(max(logging.DEBUG, min(level, logging.ERROR)))
    root.propagate = False
    try:
        import pycolmap

        pycolmap.logging.minloglevel = 2  # else ~220 glog lines per run
    except (ImportError, AttributeError):  # pragma: no cover
        pass


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="ptovs")
@click.option(
    "--work-dir",
    type=click.Path(path_type=Path),
    default=None,
    help="Where artifacts go: <work>/<scene>/<stage>/<key>.h5 "
    "(default: $PTOVS_WORK_DIR or ./work).",
)
@click.option(
    "--config",
    "config_files",
    type=click.Path(path_type=Path),
    multiple=True,
    help="TOML file with one [section] per stage plus [scene]; repeatable, later "
    "files winning key by key (--config configs/auto.toml --config "
    "configs/photos-cpu.toml). A command's settings (its files and every --set) are "
    "recorded for the scene once it runs stages (<work>/<scene>/config.json): later "
    "commands on that scene without --config use them, and say so.",
)
@click.option(
    "--set",
    "sets",
    multiple=True,
    metavar="SECTION.KEY=VALUE",
    help="Override a config value, e.g. --set scene.downscale=1 (repeatable).",
)
@click.option("--force", is_flag=True, help="Recompute the stage even if it is cached.")
@click.option(
    "--threads",
    type=click.IntRange(1, 4096),
    envvar="PTOVS_THREADS",
    default=None,
    help="CPU threads for torch and the rasterizer (default: torch's, one per core; "
    "$PTOVS_THREADS). The same bits at any count (see --deterministic). Idle "
    "threads spin briefly, then sleep (GOMP_SPINCOUNT=3000 unless it or "
    "OMP_WAIT_POLICY is set), so the default degrades gracefully beside other "
    "work (docs/findings.md).",
)
@click.option(
    "--deterministic/--nondeterministic",
    envvar="PTOVS_DETERMINISTIC",
    default=True,
    show_default=True,
    help="Training (reconstruct, render-appearances, train-male) runs torch's own "
    "operations on one thread and only the compiled rasterizer on all --threads, so "
    "a field is the same bit for bit at any thread count. --nondeterministic gives "
    "torch every thread too: reconstruct 2.7x faster at 16 threads, 1.26-1.45x at 2 "
    '(docs/results.md, "Threads"), the field then reproducible per thread count '
    "only. Recorded in every artifact's provenance.",
)
@click.option("-v", "--verbose", count=True, help="More log output (-vv for debug).")
@click.option("-q", "--quiet", count=True, help="Less log output.")
@click.pass_context
def main(
    ctx: click.Context,
    work_dir: Path | None,
    config_files: tuple[Path, ...],
    sets: tuple[str, ...],
    force: bool,
    threads: int | None,
    deterministic: bool,
    verbose: int,
    quiet: int,
) -> None:
    """Open-vocabulary 3D understanding of landmarks from photo collections.

    Every stage is a subcommand that reads and writes content-keyed HDF5
    artifacts under --work-dir; rerunning with the same inputs does no work,
    and an interrupted stage resumes where it stopped.

    \b
    Quick start on the synthetic demo scene:
      ptovs synth-scene data --preset tiny
      ptovs status --data data/tiny_s0

    --out, in every command, is where its result goes: the file itself when the
    command writes one file (export-ply, select, roam, table), else a folder
    (query, evaluate, style, export-features, view). A folder where a file is
    asked for, or a file name where a folder is, is refused before any work.
    -v/-q/--threads/--(non)deterministic work before or after the subcommand.
    """
    _setup_logging(verbose, quiet)
    if threads is not None:
        import torch

        torch.set_num_threads(threads)
    from ptovs.raster import set_deterministic

    set_deterministic(deterministic)
    from ptovs.keys import flush_fingerprints, forget_checked_writes
    from ptovs.scene_config import GivenConfig

    flush_fingerprints(write=False)  # nothing left pending by an earlier call
    forget_checked_writes()
    try:
        given = GivenConfig.read(config_files, sets)
        config = given.config()
        if config:
            from ptovs.config import check_config

            check_config(config, "--config/--set")
    except (InputError, MissingInputError) as exc:
        raise click.ClickException(str(exc)) from None
    except OSError as exc:  # e.g. a --config that cannot be read
        raise click.ClickException(_user_message(exc)) from None
    if work_dir is None:
        work_dir = Path(os.environ.get("PTOVS_WORK_DIR", "work"))
    ctx.obj = RunContext(work_dir=work_dir, config=config, force=force, given=given)


def _standin_option(version: int) -> int:
    if version in (1, 5):
        return version
    raise click.BadParameter(
        f"stand-in version {version} is not available (only 1 and 5 are); "
        "use --standin 1 or --standin 5",
        param_hint="--standin",
    )


@main.command("synth-scene")
@click.argument("out", type=click.Path(path_type=Path))
@click.option(
    "--preset",
    type=click.Choice(
        ["tiny", "demo", "small", "small-3x", "bench", "landmark", "scale"]
    ),
    default="tiny",
    show_default=True,
    help="Scene size: tiny (CI, ~12 views), small (the accuracy benchmark, ~48 "
    "views), small-3x (small's scenes at 3x the side, 528-768 px), bench (~80 "
    "views), landmark (763 views of 640-760 px, a "
    "Brandenburg-sized collection), scale (~3,000 small views).",
)
@click.option(
    "--photos",
    type=click.IntRange(1),
    default=None,
    help="Keep N of the preset's train photos (its labelled and test views, then "
    "the others in order): the same world at another size. landmark also takes "
    "more, up to 2,934 (Notre-Dame's count): more photos of the same world. Name: "
    "<preset>_s<seed>_pN.",
)
@click.option(
    "--seed",
    type=click.IntRange(0),
    default=0,
    show_default=True,
    help="A new seed is a new landmark, cameras and appearances.",
)
@click.option(
    "--name", default=None, help="Scene folder name (default <preset>_s<seed>)."
)
@click.option(
    "--standin",
    type=int,
    default=1,
    show_default=True,
    callback=lambda ctx, param, v: _standin_option(v),
    help="The stand-in for CLIP the scene is written for: 1 (the original) or 5 "
    "(calibrated against CLIP's published failure profile); docs/standin.md.",
)
def synth_scene(
    out: Path,
    preset: str,
    photos: int | None,
    seed: int,
    name: str | None,
    standin: int,
) -> None:
    """Generate a synthetic landmark photo collection in PT-OVS layout under OUT.

    Writes OUT/<name>/dense/{images,sparse}, OUT/<name>/<preset>.tsv,
    OUT/label/<name>/*.json (ISAT) and OUT/<name>/synthetic/ (vocabulary for
    the stand-in encoder, exact ground truth). Deterministic per seed.
    """
    import time

    from ptovs.synthetic import generate_scene
    from ptovs.synthetic.generate import PhotoCountError

    t0 = time.perf_counter()
    try:
        scene_dir = generate_scene(out, preset=preset, seed=seed, name=name,
                                   standin=standin, photos=photos)  # fmt: skip
    except PhotoCountError as exc:
        raise click.BadParameter(str(exc), param_hint="--photos") from None
    click.echo(f"wrote {scene_dir} ({time.perf_counter() - t0:.1f} s)")


@main.command("status")
@scene_options
@click.pass_obj
def status(obj: RunContext, scene_name: str | None, data: Path | None) -> None:
    """Show each stage of the chain for a scene: key and state.

    States: done; partial (an interrupted run, resumable); missing; stale (an
    artifact exists under an older key because an upstream or the config changed).
    A folder of unposed photos first shows its `sfm` stage; status never runs it.
    It reads only: nothing is written, not even the photos' fingerprint cache.
    """
    from ptovs.keys import read_only

    with read_only():
        _status(obj, scene_name, data)


def _status(obj: RunContext, scene_name: str | None, data: Path | None) -> None:
    from ptovs.chain import Chain
    from ptovs.locate import pose_photos, scene_source
    from ptovs.registry import SFM, all_stages

    click.echo(f"work dir: {Path(obj.work_dir).resolve()}")

    name, folder, photos = scene_source(scene_name, data)
    # without --config, the config recorded for the scene
    settings = resolve_settings(obj, name)
    sfm_line = None
    if photos is not None:
        key, state, posed = pose_photos(settings, name, photos, run=False)
        if state != "done":
            click.echo(f"scene {name}: {photos} (unposed photos)")
            click.echo(
                f"  {SFM:<20} {key[:12]}  {state:<8} run: ptovs {settings.advice}sfm "
                f"--data {folder}"
            )
            return
        sfm_line = f"  {SFM:<20} {key[:12]}  done     {photos}"
        scene_name, data = name, posed  # the posed scene the sfm stage left
    ref = resolve_scene(settings, scene_name, data)
    if sfm_line:
        ref.source = folder  # the advice names the photo folder given, not the copy
    scene = ref.load()
    chain = Chain(settings, ref)
    click.echo(f"scene {ref.name}: {ref.data}")
    n_train, n_test = len(scene.train_views()), len(scene.test_views())
    n_lab = sum(v.has_label for v in scene.views)
    click.echo(
        f"  {len(scene.views)} views ({n_train} train, {n_test} test, "
        f"{n_lab} labelled), {len(scene.points_xyz)} points, "
        f"downscale r={scene.downscale}"
    )
    given = obj.given
    if given is not None and not given.files:  # the recorded settings it keys with
        from ptovs.scene_config import history_lines

        for line in history_lines(settings.work_dir, ref.name):
            click.echo(f"  {line}")
    if sfm_line:
        click.echo(sfm_line)
    click.echo(f"  {'scene':<20} {ref.key()[:12]}  input")
    stages = all_stages()
    if not stages:
        click.echo("  (no pipeline stages are implemented yet)")
    for spec in stages:
        state, detail = chain.state(spec.name)
        click.echo(
            f"  {spec.name:<20} {chain.key(spec.name)[:12]}  {state:<8} {detail}"
        )
        line = chain.summary(spec.name) if state == "done" else None
        if line:
            click.echo(f"  {'':<20} {line}")


@main.command("export-ply")
@scene_options
@click.option(
    "--out",
    "out",
    type=click.Path(path_type=Path),
    required=True,
    help="PLY file to write (standard 3DGS layout).",
)
@click.option(
    "--image",
    default=None,
    help="Bake the appearance of this image (name or stem) into the colours; "
    "default: the neutral appearance (mean of the train embeddings).",
)
@click.pass_obj
def export_ply(
    obj: RunContext,
    scene_name: str | None,
    data: Path | None,
    out: Path,
    image: str | None,
) -> None:
    """Export the reconstructed Gaussians as a standard 3DGS PLY.

    Reads the scene's reconstruct artifact (run `ptovs reconstruct` first) and
    writes x y z, normals, f_dc_*, f_rest_*, opacity logits, log-scales and
    rotations, with the ΔSH of one image's appearance (or a neutral one) baked
    into the SH, so any 3DGS viewer shows it.
    """
    from ptovs.chain import Chain
    from ptovs.field.export import export_field_ply
    from ptovs.outputs import check_outputs, require_suffix

    check_outputs({"--out": out}, suffix=".ply")
    require_suffix("--out", out, (".ply",))
    ref = resolve_scene(obj, scene_name, data)
    chain = Chain(obj, ref)
    art = chain.inputs_of("reconstruct")
    try:
        n = export_field_ply(art, out, image=image)
    finally:
        art.close()
    click.echo(f"export-ply: {n} Gaussians -> {out}")


@main.command("extract")
@chain_options(variant=None, force="Recompute all three stages.")
@click.pass_obj
def extract(
    obj: RunContext,
    scene_name: str | None,
    data: Path | None,
    sets: tuple[str, ...],
    force: bool,
) -> None:
    """Run render-appearances, extract-features and uncertainty for one scene.

    The three preprocessing stages of the paper in order, each cached and
    resumable on its own: a second `ptovs extract` does nothing, and a killed one
    resumes in the stage (and at the view) where it stopped. Needs reconstruct.
    """
    chain, _ = variant_chain(obj, scene_name, data, "male", sets, until="uncertainty")
    run_stages(chain, EXTRACT_STAGES, EXTRACT_STAGES if force else ())


@main.command("train")
@chain_options(variant="one", force="Retrain train-ae and train-male.")
@click.pass_obj
def train(
    obj: RunContext,
    scene_name: str | None,
    data: Path | None,
    variant: str,
    sets: tuple[str, ...],
    force: bool,
) -> None:
    """Train the language field of one scene: train-ae, then train-male.

    Each stage is cached and resumable on its own: a second `ptovs train` does
    nothing, and a killed one resumes from its last checkpoint. Any stage the
    variant needs that has not run yet (reconstruct, extract-features, ...) runs
    first, so `--variant langsplat` builds its plain-3DGS geometry itself.
    """
    chain, _ = variant_chain(obj, scene_name, data, variant, sets, until="train-male")
    run_stages(chain, chain.closure("train-male"), TRAIN_STAGES if force else ())


@main.command("export-features")
@scene_options
@click.option(
    "--out",
    type=click.Path(path_type=Path),
    required=True,
    help="Folder to write <id>_f.npy / <id>_s.npy (and _ma_<k> for renders) into.",
)
@click.pass_obj
def export_features(
    obj: RunContext, scene_name: str | None, data: Path | None, out: Path
) -> None:
    """Export extract-features as a LangSplat feature folder.

    Writes, per train view, `<id>_f.npy` (float32 [n, 512]) and `<id>_s.npy`
    (int32 [4, H, W] over LangSplat's levels default/s/m/l, -1 = no segment) for
    the original, and `<id>_f_ma_<k>.npy` / `<id>_s_ma_<k>.npy` for the renders
    (k = 0.. novel, the last = self), the layout the authors' code reads.
    """
    from ptovs.artifacts import read_json_dataset
    from ptovs.chain import Chain
    from ptovs.features import SegmentFeatures, langsplat_suffix, write_langsplat
    from ptovs.outputs import check_output_dir

    check_output_dir("--out", out)
    ref = resolve_scene(obj, scene_name, data)
    art = Chain(obj, ref).inputs_of("extract-features")
    try:
        meta = read_json_dataset(art.root()["levels_json"])
        levels = tuple(meta["levels"])
        novel = [a for a in meta["apps"] if a not in ("orig", "self")]
        n = 0
        for name in art.names():
            view = art[name]
            for app in meta["apps"]:
                f = SegmentFeatures.from_view(view, app)
                write_langsplat(
                    out, Path(name).stem, f, levels, langsplat_suffix(app, novel)
                )
                n += 1
    finally:
        art.close()
    click.echo(f"export-features: {n} images -> {out}")
