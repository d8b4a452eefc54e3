"""The chain and its execution: one scene's stages keyed, cached and run.

A `Chain` receives a scene's resolved settings (`ptovs.settings`) and computes
every stage's config from them and its content key (stage name, VERSION, config
and the upstream keys; the scene's key covers its files) once, before any work.
`execute` runs one stage into a resumable artifact, or returns the cached one;
`run_stages` runs several in order after their preflight checks.

A stage's `run` (`ptovs.stage` says what a stage module defines) is called as:

- view stages yield `(view_name, {dataset: array})` (a `None` name writes
  whole-scene datasets); if `run` takes a `skip` keyword, views already stored by
  an interrupted run are passed in and must not be yielded again;
- single stages return `{dataset: array}`;
- either kind may take a `ckpt` keyword: a `ptovs.checkpoint.Checkpoint` whose
  `load()` gives the state saved by an interrupted run (or None) and whose
  `save(state)` stores one atomically. Long training stages call `save` every N
  iterations, so a killed run resumes from its last checkpoint; the chain deletes
  the checkpoint once the artifact is complete (and on --force);
- a view stage may take a `notes` keyword: the partial artifact's
  `ptovs.artifacts.Notes`, where a decision made once for the whole artifact
  (`put` before the first view it governs) is kept for a resumed run (`get`);
- a stage that raises `ptovs.errors.UselessOutputError` has its partial artifact
  (views, notes, checkpoint) deleted, so the rerun after the fix starts clean.
"""

from __future__ import annotations

import dataclasses
import inspect
import json
import logging
import os
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import click
from tqdm import tqdm

from ptovs.artifacts import Artifact, ArtifactWriter, provenance, read_json_dataset
from ptovs.config import canonical_json
from ptovs.errors import MissingInputError, UselessOutputError
from ptovs.keys import artifact_key, fingerprint_files, model_file_deps
from ptovs.pipeline import PIPELINE
from ptovs.progress import Ticker
from ptovs.registry import SCENE, SCENE_VERSION, SceneConfig, get_stage
from ptovs.settings import RunContext, Settings

log = logging.getLogger(__name__)


class SceneRef:
    """A scene folder plus its `[scene]` options; loads and fingerprints lazily.

    `data` is the posed scene that is read; `source` is the folder the user gave as
    --data (a folder of unposed photos that SfM posed into `data`, else `data`):
    the commands this module advises name it."""

    def __init__(
        self,
        name: str,
        data: Path,
        config: SceneConfig,
        work_dir: Path,
        source: Path | None = None,
    ):
        self.name = name
        self.data = Path(data)
        self.source = Path(data if source is None else source)
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
        settings: Settings | RunContext,
        scene: SceneRef,
        sets: Mapping[str, Iterable[str]] | None = None,
    ):
        """`settings`: the scene's (`ptovs.settings.resolve_settings`; a script's
        `RunContext` is resolved here). `sets`: a recipe's KEY=VALUE items per
        stage (`ptovs.variants`), applied before the settings' own --set items."""
        if isinstance(settings, RunContext):
            settings = settings.for_scene(scene.name)
        self.settings = settings
        self.scene = scene
        self.sets = dict(sets or {})
        self._keys: dict[str, str] = {}
        self._configs: dict[str, Any] = {}
        self._deps: dict[str, dict[str, str]] = {}

    @property
    def ctx(self) -> Settings:
        """The chain's settings (the name scripts use: `chain.ctx.store`)."""
        return self.settings

    def config(self, stage: str) -> Any:
        """The stage's config, "auto" values decided (`Settings.stage_config`)."""
        if stage not in self._configs:
            recipe = self.sets.get(stage, ())
            self._configs[stage] = self.settings.stage_config(stage, recipe, self.scene)
        return self._configs[stage]

    def upstream_keys(self, stage: str) -> dict[str, str]:
        spec = get_stage(stage)
        needed = spec.needed_inputs(self.config(stage))
        return {name: self.key(up) for name, up in needed.items()}

    def deps(self, stage: str) -> dict[str, str]:
        """What the stage's key covers besides its config: the upstream keys, the
        stage's extra digests (as "extra:<name>") and the content of the model
        files its config names (as "file:<field>", `ptovs.keys.MODEL_FILES`);
        stored as the artifact's inputs. Computed once: the inputs recorded are
        those the key was made of."""
        if stage not in self._deps:
            spec = get_stage(stage)
            config = self.config(stage)
            deps = self.upstream_keys(stage)
            if spec.extra_key is not None:
                extra = spec.extra_key(config, self.scene)
                deps.update({f"extra:{k}": v for k, v in extra.items()})
            deps.update(model_file_deps(stage, config, self.settings.work_dir))
            self._deps[stage] = deps
        return dict(self._deps[stage])

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
        """The command that makes `stage`, with the folder the user gave as --data."""
        return (
            f"ptovs {self.settings.advice}{stage} --scene {self.scene.name} "
            f"--data {self.scene.source}"
        )

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
        art = self.settings.store.lookup(self.scene.name, stage, key)
        if art is None:
            raise MissingInputError(
                f"no {stage} artifact for {self.scene.name} (key {key[:12]}) with "
                f"this config; run: {self.hint(stage)}" + self._other_configs(stage)
            )
        return art

    def _other_configs(self, stage: str) -> str:
        """What the stage's existing artifacts were made with, against this chain's
        config: the overrides to repeat (e.g. after `reconstruct --set ...`)."""
        others = self.settings.store.others(self.scene.name, stage, self.key(stage))
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
        store, key = self.settings.store, self.key(stage)
        if spec.summary is None or not store.exists(self.scene.name, stage, key):
            return None
        with Artifact(store.path(self.scene.name, stage, key), verify=False) as art:
            raw = art.root_item("metrics_json")
        return None if raw is None else spec.summary(read_json_dataset(raw))

    def state(self, stage: str) -> tuple[str, str]:
        """(state, detail) for `ptovs status`: done, corrupt, partial, missing or
        stale."""
        store, key = self.settings.store, self.key(stage)
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
            files = [k.removeprefix("file:") for k in changed if k[:5] == "file:"]
            names = [k.removeprefix("extra:") for k in changed if k[:5] != "file:"]
            why = (
                f"upstream changed ({', '.join(names)})"
                if names and not config_differs
                else f"config and upstream changed ({', '.join(names)})"
                if names
                else "config or version changed"
                if config_differs or not files
                else ""
            )
            if files:  # a checkpoint replaced at the same path
                what = f"model file changed ({', '.join(files)})"
                why = f"{what}, {why}" if why else what
            for art in others:
                art.close()
            return "stale", f"{why}; run: {self.hint(stage)}"
        return "missing", f"run: {self.hint(stage)}"


def execute(chain: Chain, stage: str, *, force: bool = False) -> Artifact:
    """Run one stage for the chain's scene, or return its cached artifact."""
    spec = get_stage(stage)
    store, scene = chain.settings.store, chain.scene.name
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
        params = inspect.signature(spec.run).parameters
        if "ckpt" in params:
            kwargs["ckpt"] = ckpt
        if "notes" in params:
            kwargs["notes"] = writer.notes
        t0 = time.perf_counter()
        try:
            if spec.kind == "views":
                _run_views(spec, inputs, config, kwargs, writer, f"{stage} {scene}")
            else:
                result = spec.run(inputs, config, **kwargs)
                writer.write_root(result)
        except UselessOutputError:
            writer.remove()  # the rerun after the fix starts clean
            ckpt.clear()
            log.info("removed the partial %s artifact (key %s)", stage, key[:12])
            raise
        elapsed = time.perf_counter() - t0
        art = writer.finish(
            {"timings_json": canonical_json({"run_s": round(elapsed, 3)})}
        )
        ckpt.clear()
        log.info("wrote %s (%s, %.1f s)", art.path, stage, elapsed)
        if spec.after is not None:
            spec.after(art)
        return art


def _run_views(
    spec: Any,
    inputs: Any,
    config: Any,
    kwargs: dict[str, Any],
    writer: ArtifactWriter,
    desc: str,
) -> None:
    """Stream a view stage's `run` into `writer`, skipping the views stored by an
    interrupted run; a bar on a terminal, else a progress line every EVERY_S s
    (`Ticker`: even while one view takes minutes)."""
    done = writer.done_views()
    if done:
        log.info("resuming %s: %d views already stored", spec.name, len(done))
        if "skip" in inspect.signature(spec.run).parameters:
            kwargs = dict(kwargs, skip=frozenset(done))
    total = spec.count(inputs, config) if spec.count else None
    bar = tqdm(
        total=total,
        initial=len(done),
        desc=desc,
        unit="view",
        disable=None,
        leave=False,
    )
    # the ticker logs exactly when tqdm draws nothing (stderr not a terminal)
    with bar, Ticker(desc, total, initial=len(done), enabled=bar.disable) as tick:
        for name, datasets in spec.run(inputs, config, **kwargs):
            if name is None:
                writer.write_root(datasets)
            elif name not in done:
                writer.write_view(name, datasets)
                bar.update(1)
                tick.update(1)


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
        redo = stage in redo_set or chain.settings.force
        was = chain.state(stage)[0]
        t0 = time.perf_counter()
        art = execute(chain, stage, force=redo)
        what = "cached" if was == "done" and not redo else "done"
        click.echo(
            f"{stage:<20} {what:<7} {time.perf_counter() - t0:7.1f} s  {art.path}"
        )
        art.close()
