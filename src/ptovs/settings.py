"""A scene's settings, resolved once, top down.

A stage's config comes from these places, merged in this order (a later one wins
key by key):

1. the stage's defaults (its config dataclass);
2. the scene's recorded last run (`ptovs.scene_config`: the `--config` texts and
   `--set` items it ran with) when the command has no `--config` and the scene
   has a record; otherwise the `--config` files, in the order given;
3. the group's `--set` items (`ptovs --set SECTION.KEY=VALUE <command>`);
4. the command's own options that set config values (`RunContext.with_overrides`:
   a stage's `--size`, say);
5. a recipe's items (`ptovs.variants`), then the command's own `--set` items;
6. the fitted values: a field of `ptovs.fit.FITTED` still "auto" is decided from
   the scene's photos (`ptovs.fit.resolve`); a value set by hand is never touched.

`RunContext` holds what the `ptovs` group was given. `resolve_settings` merges
2-4 once per scene (and records them for the scene's next command) and returns a
frozen `Settings` that carries the command's own `--set` items too. Everything
below receives that object: `ptovs.locate` reads `[scene]` and `[sfm]` from it,
`ptovs.chain.Chain` asks it for each stage's config (`Settings.stage_config`, 1, 5
and 6, once per stage and only for the stages a command keys: "auto" reads the
scene's photos), and nothing below asks the group again.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from ptovs.artifacts import Store
from ptovs.config import build_config, merge, parse_sets


@dataclass
class RunContext:
    """What the `ptovs` group resolved: shared by every subcommand of one call."""

    work_dir: Path
    config: dict[str, Any] = field(default_factory=dict)
    force: bool = False
    given: Any = None
    """The group's --config file and --set items (`ptovs.scene_config.GivenConfig`):
    a scene's config is recorded from them, or, without --config, the recorded
    one is used (`resolve_settings`). None (scripts): `config` is used as it is."""
    overrides: dict[str, Any] = field(default_factory=dict)
    """A command's own options over the config (`with_overrides`): they stay on
    top of a scene's recorded config too."""
    advice: str = ""
    """The group's options to repeat in the commands this context advises
    (`Chain.hint`): `--config A --set X=1 `, or "" where none were given."""
    _scenes: dict[str, dict[str, Any]] = field(default_factory=dict, repr=False)
    """Each scene's merged config (steps 2-4), once per scene (`resolve_settings`)."""
    _commands: dict[tuple, RunContext] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if self.given is not None and not self.advice:
            origin = (
                self.given.origin() if (self.given.files or self.given.sets) else ""
            )
            self.advice = f"{origin} " if origin else ""

    @property
    def store(self) -> Store:
        return Store(self.work_dir)

    def with_overrides(self, over: dict[str, Any]) -> RunContext:
        """This context with a command's own config values on top."""
        return RunContext(self.work_dir, merge(self.config, over), self.force,
                          self.given, merge(self.overrides, over),
                          self.advice)  # fmt: skip

    def with_command(self, name: str, items: Iterable[str]) -> RunContext:
        """This context for command `name` with its own --set items
        (SECTION.KEY=VALUE): they are recorded with the scene's settings
        (`ptovs.scene_config`). The same context for the same command and items."""
        if self.given is None:
            return self
        key = (name, tuple(items))
        if key not in self._commands:
            self._commands[key] = RunContext(
                self.work_dir, self.config, self.force,
                self.given.with_command(name, key[1]), self.overrides, self.advice,
            )  # fmt: skip
        return self._commands[key]

    def for_scene(
        self, scene: str, sets: Mapping[str, Iterable[str]] | None = None
    ) -> Settings:
        """The settings of one scene: `resolve_settings(self, scene, sets)`."""
        return resolve_settings(self, scene, sets)


@dataclass(frozen=True)
class Settings:
    """One scene's settings for one command, resolved (`resolve_settings`).

    `config` is the merged config of steps 2-4 (section → {key: value}); `sets`
    holds the command's own --set items per section ("KEY=VALUE", step 5)."""

    scene: str
    work_dir: Path
    config: Mapping[str, Any]
    sets: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    force: bool = False
    advice: str = ""
    """The group's options to repeat in advice (`RunContext.advice`)."""

    @property
    def store(self) -> Store:
        return Store(self.work_dir)

    def section(self, name: str, recipe: Iterable[str] = ()) -> dict[str, Any]:
        """Config section `name`: the merged config, then `recipe`'s KEY=VALUE
        items, then the command's own --set items (which win)."""
        items = [*recipe, *self.sets.get(name, ())]
        return merge(self.config.get(name, {}), parse_sets(items, name).get(name, {}))

    def build(self, name: str, recipe: Iterable[str] = ()) -> Any:
        """Section `name` as its config dataclass ([scene], [sfm] or a stage's:
        `ptovs.registry.config_class`): the defaults under `section(name, recipe)`."""
        from ptovs.registry import config_class

        return build_config(config_class(name), self.section(name, recipe), name)

    def stage_config(self, stage: str, recipe: Iterable[str], scene: Any) -> Any:
        """The config of `stage` for the scene `scene` (a `ptovs.chain.SceneRef`):
        `build(stage, recipe)` with every "auto" decided from the scene's photos
        (`ptovs.fit.resolve`: the decided value is what the key, the artifact and
        the log carry)."""
        from ptovs import fit

        return fit.resolve(stage, self.build(stage, recipe), scene)

    def with_overrides(self, over: dict[str, Any]) -> Settings:
        """These settings with a command's own config values on top."""
        return replace(self, config=merge(self.config, over))


def resolve_settings(
    ctx: RunContext, scene: str, sets: Mapping[str, Iterable[str]] | None = None
) -> Settings:
    """The settings of `scene` for the command of `ctx`, merged in the module's
    order: steps 2-4 once per scene (`ptovs.scene_config.scene_config` chooses
    between the recorded run and the --config files, says which in one line, and
    records the command's settings once its checks pass), with the command's own
    --set items (`sets`: section → ["KEY=VALUE", ...]) kept for step 5. A script's
    context (no `given`) uses its `config` as it is. Resolving again gives equal
    settings and records nothing more."""
    if ctx.given is None:
        config = ctx.config
    else:
        if scene not in ctx._scenes:
            from ptovs.scene_config import scene_config

            ctx._scenes[scene] = scene_config(ctx.work_dir, scene, ctx.given,
                                              ctx.config, ctx.overrides)  # fmt: skip
        config = ctx._scenes[scene]
    own = {name: tuple(items) for name, items in (sets or {}).items() if items}
    return Settings(scene, ctx.work_dir, config, own, ctx.force, ctx.advice)


__all__ = ["RunContext", "Settings", "resolve_settings"]
