"""Stage framework: config resolution, chain keys, caching and the click command.

A stage module defines `NAME`, `VERSION`, a frozen `Config` dataclass, a frozen
`Inputs` dataclass whose fields are `upstream("<stage>")` artifacts or
`scene_input()`, and a pure `run(inputs, config)`:

- view stages yield `(view_name, {dataset: array})` (a `None` name writes
  whole-scene datasets); if `run` takes a `skip` keyword, views already stored by
  an interrupted run are passed in and must not be yielded again;
- single stages return `{dataset: array}`;
- either kind may take a `ckpt` keyword: a `ptovs.artifacts.Checkpoint` whose
  `load()` gives the state saved by an interrupted run (or None) and whose
  `save(state)` stores one atomically. Long training stages call `save` every N
  iterations, so a killed run resumes from its last checkpoint; the framework
  deletes the checkpoint once the artifact is complete (and on --force).

`stage_command(...)` registers the stage and returns its click command, which
adds `--scene`, `--data`, `--set` and `--force`, keys the whole chain before any
work, and streams `run` into a resumable artifact.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import logging
import os
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import click
from tqdm import tqdm

from ptovs.artifacts import (
    Artifact,
    Store,
    artifact_key,
    fingerprint_files,
    provenance,
    read_json_dataset,
    write_atomic,
)
from ptovs.config import (  # did_you_mean: also ptovs.stage's, for the CLI
    build_config,
    canonical_json,
    did_you_mean,
    merge,
    parse_sets,
)
from ptovs.errors import InputError, MissingInputError
from ptovs.pipeline import PIPELINE  # the chain, in order (one list for every driver)

log = logging.getLogger(__name__)

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
    after: Callable[[Artifact], None] | None = None
    """Runs on the finished (or cached) artifact, e.g. to write PNG previews."""
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
    import importlib

    for module in STAGE_MODULES.values():
        importlib.import_module(module)
    order = {name: i for i, name in enumerate(PIPELINE)}
    return sorted(
        REGISTRY.values(), key=lambda s: (order.get(s.name, len(order)), s.name)
    )


def get_stage(name: str) -> StageSpec:
    if name not in REGISTRY:
        import importlib

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
        from ptovs.sfm import SfmConfig

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


def check_config(config: Mapping[str, Any], origin: str = "the config") -> None:
    """Every section and key of a merged config (`--config` file plus the group's
    `--set` items), checked before anything runs: an unknown section or key, or a
    value of the wrong type, is an InputError with the nearest valid name."""
    sections = section_names()
    for name, section in config.items():
        if name not in sections:
            raise InputError(
                f"{origin}: unknown section [{name}]"
                + did_you_mean(name, sections, "[{}]")
                + f"; sections: {', '.join(sections)}"
            )
        if not isinstance(section, Mapping):
            raise InputError(
                f"{origin}: [{name}] must be a table of KEY = VALUE, got {section!r}"
            )
        keys = config_keys(name)
        for key in section:
            if key not in keys:
                raise InputError(
                    f"{origin}: [{name}] has no key {key!r}"
                    + did_you_mean(key, keys)
                    + f"; valid keys: {', '.join(sorted(keys))}"
                )
        build_config(config_class(name), section, name)  # the values' types


@dataclass
class RunContext:
    """What the `ptovs` group resolved: shared by every subcommand of one call."""

    work_dir: Path
    config: dict[str, Any] = field(default_factory=dict)
    force: bool = False

    @property
    def store(self) -> Store:
        return Store(self.work_dir)

    def section(self, name: str, sets: Iterable[str] = ()) -> dict[str, Any]:
        """Config section `name` with this command's `--set` items applied."""
        return merge(self.config.get(name, {}), parse_sets(sets, name).get(name, {}))


class SceneRef:
    """A scene folder plus its `[scene]` options; loads and fingerprints lazily."""

    def __init__(self, name: str, data: Path, config: SceneConfig, work_dir: Path):
        self.name = name
        self.data = Path(data)
        self.config = config
        self.work_dir = Path(work_dir)
        self._scene = None
        self._key: str | None = None

    def load(self) -> Any:
        if self._scene is None:
            from ptovs.scene import load_scene

            self._scene = load_scene(
                self.data,
                downscale=self.config.downscale,
                split_file=self.config.split_file,
                distortion=self.config.distortion,
                name=self.name,
            )
        return self._scene

    def key(self) -> str:
        """Content key of the scene: its files' sha256 plus the resolved options."""
        if self._key is None:
            scene = self.load()
            fingerprint = fingerprint_files(
                scene.fingerprint_files(), scene.root, self.cache_path
            )
            opts = dict(dataclasses.asdict(self.config), downscale=scene.downscale)
            if opts["split_file"] not in ("auto", "all-train"):
                opts["split_file"] = (
                    "explicit"  # the file's content is in the fingerprint
                )
            self._key = artifact_key(SCENE, SCENE_VERSION, opts, {"data": fingerprint})
        return self._key

    @property
    def cache_path(self) -> Path:
        return self.work_dir / self.name / ".fingerprints.json"


class Chain:
    """Keys, configs and artifacts of every stage for one scene, computed once."""

    def __init__(
        self,
        ctx: RunContext,
        scene: SceneRef,
        sets: Mapping[str, Iterable[str]] | None = None,
    ):
        self.ctx = ctx
        self.scene = scene
        self.sets = dict(sets or {})
        self._keys: dict[str, str] = {}
        self._configs: dict[str, Any] = {}

    def config(self, stage: str) -> Any:
        if stage not in self._configs:
            spec = get_stage(stage)
            section = self.ctx.section(stage, self.sets.get(stage, ()))
            self._configs[stage] = build_config(spec.config_cls, section, stage)
        return self._configs[stage]

    def upstream_keys(self, stage: str) -> dict[str, str]:
        spec = get_stage(stage)
        needed = spec.needed_inputs(self.config(stage))
        return {name: self.key(up) for name, up in needed.items()}

    def deps(self, stage: str) -> dict[str, str]:
        """What the stage's key covers besides its config: the upstream keys and
        the stage's extra digests (as "extra:<name>"); stored as the artifact's
        inputs."""
        spec = get_stage(stage)
        deps = self.upstream_keys(stage)
        if spec.extra_key is not None:
            extra = spec.extra_key(self.config(stage), self.scene)
            deps.update({f"extra:{k}": v for k, v in extra.items()})
        return deps

    def key(self, stage: str) -> str:
        if stage == SCENE:
            return self.scene.key()
        if stage not in self._keys:
            spec = get_stage(stage)
            self._keys[stage] = artifact_key(
                spec.name, spec.version, self.config(stage), self.deps(stage)
            )
        return self._keys[stage]

    def hint(self, stage: str) -> str:
        return f"ptovs {stage} --scene {self.scene.name} --data {self.scene.data}"

    def inputs(self, stage: str) -> Any:
        """The stage's `Inputs`, with every upstream artifact verified and opened."""
        spec = get_stage(stage)
        needed = spec.needed_inputs(self.config(stage))
        values: dict[str, Any] = dict.fromkeys(spec.inputs)  # None: not needed
        for name, up in needed.items():
            if up == SCENE:
                values[name] = self.scene.load()
                continue
            values[name] = self.inputs_of(up)
        return spec.inputs_cls(**values)

    def closure(self, stage: str) -> list[str]:
        """`stage` and every stage it needs under this chain's configs, in order."""
        need: set[str] = set()

        def visit(name: str) -> None:
            if name == SCENE or name in need:
                return
            need.add(name)
            spec = get_stage(name)
            for up in spec.needed_inputs(self.config(name)).values():
                visit(up)

        visit(stage)
        order = {name: i for i, name in enumerate(PIPELINE)}
        return sorted(need, key=lambda s: (order.get(s, len(order)), s))

    def inputs_of(self, stage: str) -> Artifact:
        """The verified artifact of `stage` for this chain, or a MissingInputError."""
        key = self.key(stage)
        art = self.ctx.store.lookup(self.scene.name, stage, key)
        if art is None:
            raise MissingInputError(
                f"no {stage} artifact for {self.scene.name} (key {key[:12]}) with "
                f"this config; run: {self.hint(stage)}" + self._other_configs(stage)
            )
        return art

    def _other_configs(self, stage: str) -> str:
        """What the stage's existing artifacts were made with, against this chain's
        config: the overrides to repeat (e.g. after `reconstruct --set ...`)."""
        others = self.ctx.store.others(self.scene.name, stage, self.key(stage))
        if not others:
            return ""
        want = json.loads(canonical_json(self.config(stage)))
        lines = []
        for art in others[:3]:
            diff = [f"{stage}.{k}={json.dumps(v)}" for k, v in sorted(art.config.items())
                    if want.get(k) != v]  # fmt: skip
            art.close()
            sets = " ".join(f"--set {d}" for d in diff)
            lines.append(
                f"  {art.path.name}: "
                + (
                    f"made with {sets}"
                    if diff
                    else "same config, other upstream inputs"
                )
            )
        for art in others[3:]:
            art.close()
        return (
            f". {len(others)} other {stage} artifact(s) exist; to use one, give its "
            "overrides before the command (ptovs --set ... <command>):\n"
            + "\n".join(lines)
        )

    def summary(self, stage: str) -> str | None:
        """The stage's own line for `ptovs status` (its headline figures, from the
        done artifact's metrics), or None: not done, no summary, no metrics."""
        spec = get_stage(stage)
        store, key = self.ctx.store, self.key(stage)
        if spec.summary is None or not store.exists(self.scene.name, stage, key):
            return None
        with Artifact(store.path(self.scene.name, stage, key), verify=False) as art:
            raw = art.root_item("metrics_json")
        return None if raw is None else spec.summary(read_json_dataset(raw))

    def state(self, stage: str) -> tuple[str, str]:
        """(state, detail) for `ptovs status`: done, corrupt, partial, missing or
        stale."""
        store, key = self.ctx.store, self.key(stage)
        if store.exists(self.scene.name, stage, key):
            return "done", str(store.path(self.scene.name, stage, key))
        path = store.path(self.scene.name, stage, key)
        if path.exists():  # there, but incomplete, unreadable or not what its name says
            return "corrupt", (
                f"{path.name} is damaged or holds another key (moved aside when "
                f"next read); run: {self.hint(stage)}"
            )
        n = store.partial_views(self.scene.name, stage, key)
        if n:
            return "partial", f"{n} views stored; rerun to resume"
        ckpt = store.checkpoint(self.scene.name, stage, key)
        if ckpt.exists():
            step = ckpt.step()
            at = "" if step is None else f" at iteration {step}"
            return "partial", f"checkpoint{at}; rerun to resume"
        others = store.others(self.scene.name, stage, key)
        if others:
            deps = self.deps(stage)
            config = json.loads(canonical_json(self.config(stage)))

            def differences(art: Artifact) -> tuple[list[str], bool]:
                changed = [k for k, v in deps.items() if art.inputs.get(k) != v]
                return changed, art.config != config

            # explain against the nearest older artifact (there may be variants)
            changed, config_differs = min(
                map(differences, others), key=lambda d: (len(d[0]) + d[1], d[1])
            )
            names = [k.removeprefix("extra:") for k in changed]
            why = (
                f"upstream changed ({', '.join(names)})"
                if changed and not config_differs
                else f"config and upstream changed ({', '.join(names)})"
                if changed
                else "config or version changed"
            )
            for art in others:
                art.close()
            return "stale", f"{why}; run: {self.hint(stage)}"
        return "missing", f"run: {self.hint(stage)}"


def execute(chain: Chain, stage: str, *, force: bool = False) -> Artifact:
    """Run one stage for the chain's scene, or return its cached artifact."""
    spec = get_stage(stage)
    store, scene = chain.ctx.store, chain.scene.name
    key = chain.key(stage)
    config = chain.config(stage)
    log.info("%s %s: config %s", stage, key[:12], canonical_json(config))
    with store.lock(scene, stage, key):
        cached = store.lookup(scene, stage, key)
        if cached is not None and not force:
            log.info(
                "cache hit: %s for %s (key %s), nothing to do", stage, scene, key[:12]
            )
            if spec.after is not None:
                spec.after(cached)
            return cached
        if cached is not None:
            cached.close()
            os.remove(cached.path)
            log.info("--force: recomputing %s for %s", stage, scene)
        inputs = chain.inputs(stage)
        attrs = dict(
            provenance(),
            version=spec.version,
            config_json=canonical_json(config),
            inputs_json=canonical_json(chain.deps(stage)),
            scene=scene,
        )
        writer = store.writer(scene, stage, key, attrs)
        ckpt = store.checkpoint(scene, stage, key)
        if force:
            writer.discard()
            ckpt.clear()
        kwargs: dict[str, Any] = {}
        if "ckpt" in inspect.signature(spec.run).parameters:
            kwargs["ckpt"] = ckpt
        t0 = time.perf_counter()
        if spec.kind == "views":
            done = writer.done_views()
            if done:
                log.info("resuming %s: %d views already stored", stage, len(done))
                if "skip" in inspect.signature(spec.run).parameters:
                    kwargs["skip"] = frozenset(done)
            total = spec.count(inputs, config) if spec.count else None
            bar = tqdm(
                total=total,
                initial=len(done),
                desc=f"{stage} {scene}",
                unit="view",
                disable=None,
                leave=False,
            )
            with bar:
                for name, datasets in spec.run(inputs, config, **kwargs):
                    if name is None:
                        writer.write_root(datasets)
                    elif name not in done:
                        writer.write_view(name, datasets)
                        bar.update(1)
        else:
            result = spec.run(inputs, config, **kwargs)
            writer.write_root(result)
        elapsed = time.perf_counter() - t0
        art = writer.finish(
            {"timings_json": canonical_json({"run_s": round(elapsed, 3)})}
        )
        ckpt.clear()
        log.info("wrote %s (%s, %.1f s)", art.path, stage, elapsed)
        if spec.after is not None:
            spec.after(art)
        return art


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


def run_stages(
    chain: Chain, stages: Iterable[str], force: Iterable[str] = (), check: bool = True
) -> None:
    """Run stages in order (cached ones return at once), one line per stage; first
    the preflight checks of those that will run (`ptovs.preflight`)."""
    stages = list(stages)
    if check:
        from ptovs.preflight import preflight

        preflight(chain, stages)
    redo_set = set(force)
    for stage in stages:
        redo = stage in redo_set or chain.ctx.force
        was = chain.state(stage)[0]
        t0 = time.perf_counter()
        art = execute(chain, stage, force=redo)
        what = "cached" if was == "done" and not redo else "done"
        click.echo(
            f"{stage:<20} {what:<7} {time.perf_counter() - t0:7.1f} s  {art.path}"
        )
        art.close()


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
    `--set` items (SECTION.KEY=VALUE; KEY=VALUE for `default`'s section). `until`
    (the last stage the command will run, default `default`) decides what a folder
    of unposed photos is checked for before SfM poses it."""
    from ptovs.variants import variant_sets

    split = split_sets(sets, (*PIPELINE, *REGISTRY, SCENE), default)
    last = until or default
    extract = "extract-features"
    needs = last in PIPELINE and PIPELINE.index(last) >= PIPELINE.index(extract)

    def before_sfm() -> None:  # what the features will need, before SfM's minutes
        if needs:
            from ptovs.preflight import check_extract_config

            section = ctx.section(extract, split.get(extract, ()))
            check_extract_config(build_config(get_stage(extract).config_cls,
                                              section, extract))  # fmt: skip

    ref = resolve_scene(ctx, scene_name, data, split.pop(SCENE), before_sfm)
    return Chain(ctx, ref, variant_sets(variant, split)), ref


def _scene_name(name: str, data: Path | None) -> tuple[str, Path | None]:
    """`--scene` is a name: it names the scene's folder under the work dir, so a
    path there would write outside it. A path to a folder given without --data is
    taken as --data (the scene named by the folder); anything else with a path
    separator, or "." / "..", is refused with the command to use."""
    if name and "/" not in name and "\\" not in name and name not in (".", ".."):
        return name, data
    path = Path(name).expanduser()
    if data is None and path.is_dir():
        resolved = path.resolve()
        log.info("--scene %s is a folder: taken as --data %s (scene %s)",
                 name, path, resolved.name)  # fmt: skip
        return resolved.name, path
    hint = Path(name).name or "myscene"
    raise InputError(
        f"--scene takes a name, not a path ({name!r}); give the folder as --data: "
        f"--data {name} [--scene {hint}]"
    )


def scene_part(path: Path) -> tuple[Path, str] | None:
    """(the scene folder, what `path` is in it) when `path` is a folder inside a
    scene rather than the scene: PhotoTourism's `dense/`, a scene's `images/` or
    `sparse/` (or a model `sparse/N`). Given as --data, such a folder would become a
    scene named "dense" or "images" that has lost its split and labels."""
    p = Path(path).resolve()
    if not p.is_dir():
        return None
    if p.name == "dense" and (p / "images").is_dir():
        return p.parent, "dense/ folder"
    if p.name in ("images", "sparse"):
        up = p.parent
        if up.name == "dense" and (up / "sparse").is_dir():
            return up.parent, f"dense/{p.name}/ folder"
        return up, f"{p.name}/ folder"  # the scene (or photo collection) holds it
    if p.parent.name == "sparse" and any(
        (p / f"cameras.{ext}").is_file() for ext in ("bin", "txt")
    ):
        up = p.parent.parent
        root = up.parent if up.name == "dense" else up
        return root, f"COLMAP model {p.relative_to(root)}/"
    return None


def scene_source(
    scene_name: str | None, data: Path | None
) -> tuple[str, Path, Path | None]:
    """(scene name, --data folder, its photo folder if it holds unposed photos)."""
    if scene_name is None and data is None:
        raise click.UsageError("give --scene NAME and/or --data FOLDER")
    if scene_name is not None:
        scene_name, data = _scene_name(scene_name, data)
    if data is None:
        data = Path(os.environ.get("PTOVS_DATA", "data")) / scene_name
    part = scene_part(Path(data))
    if part is not None:
        root, what = part
        shown = os.path.relpath(root) if not Path(data).is_absolute() else str(root)
        raise InputError(
            f"--data {data} is the {what} of the scene folder {shown}, not a scene: "
            f"pass --data {shown}" + (f" --scene {scene_name}" if scene_name else "")
        )
    if scene_name is None:
        scene_name = Path(data).resolve().name
    if not Path(data).is_dir():
        raise MissingInputError(
            f"scene folder {data} does not exist; pass --data pointing at a scene "
            "(PhotoTourism: <scene>/dense/images + dense/sparse; COLMAP: images/ + sparse/0), "
            "or make one with: ptovs synth-scene data --preset tiny"
        )
    from ptovs.sfm import photo_dir

    return scene_name, Path(data), photo_dir(Path(data))


def pose_photos(
    ctx: RunContext, scene_name: str, photos: Path, *, run: bool, force: bool = False
) -> tuple[str, str, Path]:
    """(key, state, posed scene folder) of the `sfm` stage for a photo folder:
    run (cached, under its lock) if `run`, else only looked up (`ptovs status`)."""
    from ptovs.sfm import SfmConfig, posed_scene, sfm_location, sfm_state

    config = build_config(SfmConfig, ctx.section(SFM), SFM)
    if not run:
        return sfm_state(photos, scene_name, ctx.work_dir, config)
    out = posed_scene(photos, scene_name, ctx.work_dir, config, force=force)
    return sfm_location(photos, scene_name, ctx.work_dir, config)[1], "done", out


def resolve_scene(
    ctx: RunContext,
    scene_name: str | None,
    data: Path | None,
    sets: Iterable[str] = (),
    before_sfm: Callable[[], None] | None = None,
) -> SceneRef:
    """The scene a command works on. A folder of unposed photos is posed first by
    the `sfm` stage (cached); `before_sfm` runs first when SfM has still to run
    (the command's preflight checks that need no scene)."""
    scene_name, data, photos = scene_source(scene_name, data)
    if photos is not None:  # unposed photos: SfM first (cached), then a COLMAP scene
        if before_sfm is not None:
            from ptovs.artifacts import read_only

            with read_only():  # the state lookup writes no cache
                state = pose_photos(ctx, scene_name, photos, run=False)[1]
            if state != "done":
                before_sfm()
        data = pose_photos(ctx, scene_name, photos, run=True)[2]
    section = ctx.section("scene", sets)
    config = build_config(SceneConfig, section, "scene")
    return SceneRef(scene_name, Path(data), config, ctx.work_dir)


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
            ctx = RunContext(obj.work_dir, merge(obj.config, {name: over}), obj.force)
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
