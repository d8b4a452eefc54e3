"""A scene's settings are resolved once, top down (`ptovs.settings`).

One place shows the order, a later source winning key by key: the scene's
recorded run (or, with --config, the files in order) < the group's --set items <
the command's own options < a recipe < the command's own --set items < the
fitted values (which fill only an "auto"). Resolving again gives equal settings,
records nothing more, and keys the chain the same.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from ptovs import fit
from ptovs.chain import Chain
from ptovs.keys import flush_fingerprints, forget_checked_writes
from ptovs.locate import resolve_scene
from ptovs.scene_config import GivenConfig, record_path
from ptovs.settings import RunContext, Settings, resolve_settings

KEYS = ("lr", "epochs", "patience", "batch_size", "seed", "tau_u")


@pytest.fixture(autouse=True)
def _no_pending_writes():
    flush_fingerprints(write=False)
    yield
    flush_fingerprints(write=False)
    forget_checked_writes()


def _toml(path: Path, **values: object) -> Path:
    path.write_text("[train-ae]\n" + "".join(f"{k} = {v}\n" for k, v in values.items()))
    return path


def _context(work: Path, files=(), sets=()) -> RunContext:
    given = GivenConfig.read(files, sets)
    return RunContext(work, given.config(), given=given)


def _record(work: Path, scene: str, file: Path) -> None:
    """A command ran `scene` with --config `file` and its checks passed."""
    resolve_settings(_context(work, [file]).with_command("train", ()), scene)
    flush_fingerprints()  # the recorded settings are written
    assert record_path(work, scene).is_file()


def _layers(ctx: RunContext, scene: str) -> Settings:
    """Every source above the recorded run / files, each over one key more."""
    ctx = ctx.with_overrides({"train-ae": {"patience": 9, "batch_size": 32}})
    own = {"train-ae": ["seed=3"]}
    return resolve_settings(ctx.with_command("train", ["train-ae.seed=3"]), scene, own)


def test_the_order_without_config_starts_from_the_recorded_run(tmp_path):
    work = tmp_path / "work"
    recorded = dict(lr=0.1, epochs=10, patience=7, batch_size=8, seed=1, tau_u=0.5)
    _record(work, "s", _toml(tmp_path / "r.toml", **recorded))
    settings = _layers(_context(work, sets=["train-ae.epochs=20"]), "s")
    section = settings.section("train-ae", ["batch_size=16", "seed=2"])  # a recipe
    assert {k: section[k] for k in KEYS} == dict(
        lr=0.1,  # the recorded run
        tau_u=0.5,  # the recorded run
        epochs=20,  # the group's --set over the recorded run
        patience=9,  # the command's option over both
        batch_size=16,  # the recipe over the command's option
        seed=3,  # the command's own --set over the recipe
    )


def test_config_files_replace_the_recorded_run(tmp_path):
    work = tmp_path / "work"
    _record(work, "s", _toml(tmp_path / "r.toml", lr=0.1, tau_u=0.5))
    a = _toml(tmp_path / "a.toml", lr=0.2, epochs=4)
    b = _toml(tmp_path / "b.toml", epochs=5)
    settings = _layers(_context(work, [a, b], ["train-ae.epochs=20"]), "s")
    section = settings.section("train-ae")
    assert "tau_u" not in section  # the recorded run is not read under --config
    assert section["lr"] == 0.2  # the files in order, the later winning
    assert (section["epochs"], section["patience"], section["seed"]) == (20, 9, 3)


def test_fitted_values_come_last_and_fill_only_auto(monkeypatch):
    asked = []

    def evidence(scene):
        asked.append(scene)
        return {"photos": 9, "points": 500, "views": 9, "appearance_spread": 0.2}

    monkeypatch.setattr(fit, "cached_evidence", evidence)
    settings = Settings("s", Path("work"), {"reconstruct": {"wild": "auto"}})
    assert settings.stage_config("reconstruct", (), "ref").wild is True  # decided
    assert asked == ["ref"]
    by_hand = Settings("s", Path("work"), {}, {"reconstruct": ("wild=false",)})
    assert by_hand.stage_config("reconstruct", ["wild=auto"], "ref").wild is False
    assert asked == ["ref"]  # a value set by hand is never fitted


def test_resolving_twice_gives_equal_settings_and_keys(
    tmp_path, tiny_scene_dir, monkeypatch
):
    import ptovs.scene_config

    work = tmp_path / "work"
    config = _toml(tmp_path / "c.toml", epochs=3)
    scene = tiny_scene_dir.name
    cmd = _context(work, [config], ["train-ae.lr=0.01"]).with_command("train", ())
    merged = []
    scene_config = ptovs.scene_config.scene_config
    monkeypatch.setattr(ptovs.scene_config, "scene_config",
                        lambda *a: merged.append(a) or scene_config(*a))  # fmt: skip
    first = resolve_settings(cmd, scene, {"train-ae": ["seed=3"]})
    again = resolve_settings(cmd, scene, {"train-ae": ["seed=3"]})
    assert first == again and len(merged) == 1  # merged and recorded once
    other = _context(work, [config], ["train-ae.lr=0.01"]).with_command("train", ())
    assert resolve_settings(other, scene, {"train-ae": ["seed=3"]}) == first

    ref = resolve_scene(first, None, tiny_scene_dir)
    keys = [Chain(s, ref).key("train-ae") for s in (first, again)]
    # a script's context holding the same merged config keys the same chain
    script = RunContext(work, {"train-ae": first.section("train-ae")})
    assert keys == [keys[0], Chain(script, ref).key("train-ae")]
