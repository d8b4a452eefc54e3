"""The scene-fitted recipe (ptovs.fit): its evidence, its decisions, and how a
decision enters the chain (resolved before keying, printed, overridable)."""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import json
import logging
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import tomllib
import torch

from ptovs import fit
from ptovs.config import load_config
from ptovs.keys import flush_fingerprints, read_only
from ptovs.stage import Chain, RunContext, resolve_scene

ROOT = Path(__file__).resolve().parents[1]


def _colours(gains: np.ndarray, n_points: int = 400, seed: int = 0) -> np.ndarray:
    """[V, P, 3] colours of P surfaces seen by every photo under its log gains."""
    rng = np.random.default_rng(seed)
    base = rng.uniform(0.1, 0.7, (n_points, 3))
    return np.clip(base[None] * np.exp(gains)[:, None, :], 0, 1)


# ------------------------------------------------------------------ evidence --
def test_gains_recover_each_photos_exposure_and_the_spread():
    rng = np.random.default_rng(1)
    truth = rng.normal(0, 0.2, (24, 3))
    gains, idx, off = fit.photo_gains(_colours(truth))
    assert list(idx) == list(range(24))
    # gains are relative to the points' median colour: equal up to one offset,
    # a little smaller (the log's +0.02 and the clip at white)
    rel = gains - gains.mean(0)
    np.testing.assert_allclose(rel, truth - truth.mean(0), rtol=0.1, atol=0.02)
    assert 0.15 < fit._gain_spread(gains) < 0.25
    assert off < 0.05


def test_one_shared_appearance_reads_as_shared_even_with_occluders_and_noise():
    rng = np.random.default_rng(2)
    colours = _colours(np.zeros((16, 3)))
    colours = colours + rng.normal(0, 0.01, colours.shape)  # sensor noise
    hit = rng.random(colours.shape[:2]) < 0.2  # a fifth of the points occluded
    colours[hit] = rng.uniform(0, 1, (int(hit.sum()), 3))
    gains, _, off = fit.photo_gains(colours)
    spread = fit._gain_spread(gains)
    assert spread < fit.WILD_SPREAD / 2, spread
    assert 0.1 < off < 0.3  # the occluded observations are counted, not fitted
    ev = {"appearance_spread": spread, "views": 16, "short_side": 200}
    assert fit.decide("reconstruct", "wild", ev)[0] is False
    assert fit.decide("render-appearances", "n_appearances", ev)[0] == 1


def test_varying_light_reads_as_wild():
    truth = np.random.default_rng(3).normal(0, 0.15, (16, 1)).repeat(3, 1)
    gains, _, _ = fit.photo_gains(_colours(truth))
    ev = {"appearance_spread": fit._gain_spread(gains), "views": 16, "short_side": 9}
    assert ev["appearance_spread"] > fit.WILD_SPREAD
    value, why = fit.decide("reconstruct", "wild", ev)
    assert value is True and "appearance spread" in why and "16 photos" in why
    assert fit.decide("render-appearances", "n_appearances", ev)[0] == 4


@pytest.mark.parametrize(
    "colours",
    [
        np.full((0, 0, 3), np.nan),  # no photo, no point
        np.full((5, 100, 3), np.nan),  # nothing seen
        np.full((5, 100, 3), 0.5),  # a constant world
        np.zeros((5, 100, 3)),  # black photos
        np.ones((3, 10, 3)),  # too few points a photo for a gain
    ],
    ids=["empty", "unseen", "constant", "black", "too-few"],
)
def test_hard_cases_give_finite_evidence(colours):
    gains, idx, off = fit.photo_gains(colours)
    spread = fit._gain_spread(gains)
    assert np.isfinite(gains).all() and np.isfinite(spread) and np.isfinite(off)
    assert spread == 0.0 and len(gains) == len(idx)


def test_a_photo_seeing_few_points_gives_no_gain():
    colours = _colours(np.zeros((4, 3)), n_points=200)
    colours[3, fit.MIN_OBSERVATIONS - 1 :] = np.nan
    _, idx, _ = fit.photo_gains(colours)
    assert list(idx) == [0, 1, 2]


def _evidence(**over) -> dict:
    """photo_evidence's dict for 12 photos with a shared appearance, `over` set."""
    ev = {"photos": 12, "read": 12, "views": 12, "points": 4000,
          "appearance_spread": 0.01, "outliers": 0.0, "short_side": 72}  # fmt: skip
    return {**ev, **over}


def test_sam_grid_follows_the_image_size():
    """The grid reads the photos' size: one photo with a gain of twelve (no
    appearance spread to measure) does not stop it."""

    def grid(side: int) -> int:
        ev = _evidence(views=1, appearance_spread=0.0, short_side=side)
        return fit.decide("extract-features", "sam_points_per_side", ev)[0]

    assert grid(100) == 8 and grid(1024) == 16 and grid(4000) == 32
    with pytest.raises(KeyError):
        fit.decide("query", "threshold", _evidence())


def test_the_papers_values_are_the_stage_defaults_paper_toml_pins():
    paper = _flat(ROOT / "configs" / "paper.toml")
    for stage, fields in fit.FITTED.items():
        for field in fields:
            assert fit.paper_value(stage, field) == paper[stage][field], field
    assert fit.paper_value("reconstruct", "wild") is True
    assert fit.paper_value("render-appearances", "n_appearances") == 4


@pytest.mark.parametrize(
    "over, said",
    [
        ({"points": 0, "views": 0}, "no sparse points in the scene's model"),
        ({"views": 1}, "only 1 of 12 photos sees 30 or more of the 4000 sparse points"),
        ({"photos": 60, "read": 48, "views": 0, "points": 25},
         "only 0 of 48 photos see 30 or more of the 25 sparse points"),
    ],
    ids=["no-points", "one-photo", "too-few-points"],
)  # fmt: skip
def test_missing_evidence_keeps_the_papers_values_and_says_why(over, said):
    """No spread to measure is not "no appearance change": the paper's in-the-wild
    model and N = 4, the reason named, and the --set that chooses by hand."""
    ev = _evidence(appearance_spread=0.0, **over)  # what photo_gains gives then
    wild, why = fit.decide("reconstruct", "wild", ev)
    assert wild is True and why.startswith(said)
    assert fit.missing("reconstruct", "wild", ev) == said
    assert "kept the paper's value" in why and "--set reconstruct.wild=false" in why
    n, why = fit.decide("render-appearances", "n_appearances", ev)
    assert n == 4 and why.startswith(said)
    assert "--set render-appearances.n_appearances=1" in why
    grid, why = fit.decide("extract-features", "sam_points_per_side", ev)
    assert grid == 8 and "short side 72 px" in why  # the photos' size is known
    assert fit.missing("extract-features", "sam_points_per_side", ev) is None


def test_without_photos_every_decision_keeps_the_papers_value():
    ev = _evidence(photos=0, read=0, views=0, appearance_spread=0.0, short_side=0)
    for stage, fields in fit.FITTED.items():
        for field in fields:
            value, why = fit.decide(stage, field, ev)
            assert value == fit.paper_value(stage, field), field
            assert why.startswith("no train photos in the scene"), why
    assert fit.decide("extract-features", "sam_points_per_side", ev)[0] == 32


# ------------------------------------------- extract-features: which images --
def test_features_that_do_not_move_keep_the_photo_and_its_self_render_alone():
    rng = np.random.default_rng(4)
    own = rng.normal(size=(30, 16))
    still = [own + rng.normal(0, 1e-3, own.shape) for _ in range(3)]
    moved = [own + rng.normal(0, 1.0, own.shape) for _ in range(3)]
    calm = fit.images_decision([(own, still)])
    assert calm["images"] == "orig+self" and calm["ratio"] < 0.01
    assert calm["segments"] == 90
    busy = fit.images_decision([(own, moved)])
    assert busy["images"] == "all" and busy["ratio"] > fit.SENSITIVITY
    assert "distance between segments" in busy["why"]


def test_sensitivity_hard_cases():
    assert fit.images_decision([])["images"] == "all"  # nothing to probe: keep all
    empty = np.zeros((0, 8))
    assert fit.appearance_sensitivity([(empty, [empty])])["segments"] == 0
    one = np.ones((1, 8))  # a single segment: no contrast, no ratio
    s = fit.appearance_sensitivity([(one, [one * 2])])
    assert s["ratio"] == 0.0 and s["contrast"] == 0.0
    zeros = np.zeros((4, 8))  # zero rows: finite, not NaN
    s = fit.appearance_sensitivity([(zeros, [zeros])])
    assert all(np.isfinite(v) for v in s.values())
    a = np.eye(4)  # rows that do not align are not compared
    assert fit.appearance_sensitivity([(a, [np.eye(3)])])["segments"] == 0


# ------------------------------------------------------------- in the chain --
def _chain(tmp_path: Path, scene: Path, **sets: list[str]) -> Chain:
    ctx = RunContext(tmp_path / "work", load_config(ROOT / "configs" / "ci.toml"))
    return Chain(ctx, resolve_scene(ctx, None, scene), sets)


class _Keep(logging.Handler):
    """The messages logged to the logger it is added to (`warnings`: those at
    WARNING and above)."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.lines: list[str] = []
        self.warnings: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())
        if record.levelno >= logging.WARNING:
            self.warnings.append(record.getMessage())


@contextlib.contextmanager
def _kept() -> Iterator[_Keep]:
    """What ptovs.fit logs within (its own handler: a CLI run earlier in this
    process stops "ptovs" propagating)."""
    keep = _Keep()
    logger = logging.getLogger("ptovs.fit")
    logger.addHandler(keep)
    level, logger.level = logger.level, logging.INFO
    try:
        yield keep
    finally:
        logger.removeHandler(keep)
        logger.setLevel(level)


def test_auto_is_decided_before_the_key_and_keys_as_the_value(tmp_path, tiny_scene_dir):
    """tiny's photos change light (a synthetic world): "auto" gives the wild
    model and 4 appearances, with the same keys as those values given by hand."""
    auto = {
        "reconstruct": ['wild="auto"'],
        "render-appearances": ["n_appearances=auto"],
    }
    with _kept() as keep:
        chain = _chain(tmp_path, tiny_scene_dir, **auto)
        assert chain.config("reconstruct").wild is True
        assert chain.config("render-appearances").n_appearances == 4
    assert len(keep.lines) == 2 and not keep.warnings, keep.lines
    assert "reconstruct: wild = true (auto: appearance spread" in keep.lines[0]
    by_hand = _chain(
        tmp_path, tiny_scene_dir, reconstruct=["wild=true"],
        **{"render-appearances": ["n_appearances=4"]},
    )  # fmt: skip
    assert chain.key("render-appearances") == by_hand.key("render-appearances")
    # the evidence is kept by the scene's key: a second chain reads it back
    cache = tmp_path / "work" / "tiny_s0" / "fit.json"
    blob = json.loads(cache.read_text())
    assert blob["scene_key"] == chain.scene.key()
    assert blob["evidence"]["appearance_spread"] > fit.WILD_SPREAD


def test_a_shared_appearance_fits_plain_3dgs_and_one_appearance(
    tmp_path, tiny_scene_dir, monkeypatch
):
    shared = {"appearance_spread": 0.01, "views": 12, "short_side": 72}
    monkeypatch.setattr(fit, "cached_evidence", lambda ref: dict(shared))
    chain = _chain(
        tmp_path, tiny_scene_dir, reconstruct=["wild=auto"],
        **{"render-appearances": ["n_appearances=auto"],
           "extract-features": ["sam_points_per_side=auto"]},
    )  # fmt: skip
    assert chain.config("reconstruct").wild is False
    assert chain.config("render-appearances").n_appearances == 1
    assert chain.config("extract-features").sam_points_per_side == 8
    plain = _chain(
        tmp_path, tiny_scene_dir, reconstruct=["wild=false"],
        **{"render-appearances": ["n_appearances=1"]},
    )  # fmt: skip
    assert chain.key("render-appearances") == plain.key("render-appearances")


def test_a_value_given_is_never_fitted(tmp_path, tiny_scene_dir, monkeypatch):
    def boom(ref):
        raise AssertionError("evidence computed for a value given by hand")

    monkeypatch.setattr(fit, "cached_evidence", boom)
    chain = _chain(tmp_path, tiny_scene_dir, reconstruct=["wild=false"])
    assert chain.config("reconstruct").wild is False
    chain.key("train-male")  # nothing "auto" anywhere in the chain


def test_evidence_under_read_only_waits_for_the_checks(tmp_path, tiny_scene_dir):
    """Read-only (a command's checks, status) writes nothing; the evidence is
    written when the checks pass and dropped when they fail."""
    cache = tmp_path / "work" / "tiny_s0" / "fit.json"
    flush_fingerprints(write=False)  # nothing left pending by an earlier test
    chain = _chain(tmp_path, tiny_scene_dir, reconstruct=["wild=auto"])
    with read_only():
        assert chain.config("reconstruct").wild is True
    assert not cache.exists()
    flush_fingerprints(write=False)  # the checks failed
    assert not cache.exists()
    chain = _chain(tmp_path, tiny_scene_dir, reconstruct=["wild=auto"])
    with read_only():
        assert chain.config("reconstruct").wild is True
    assert not cache.exists()
    flush_fingerprints(write=True)  # the checks passed
    assert json.loads(cache.read_text())["scene_key"] == chain.scene.key()


def _drop_points(scene: Path, kept: int) -> None:
    """Keep only the first `kept` sparse points of the scene's COLMAP model."""
    import pycolmap

    sparse = scene / "dense" / "sparse"
    rec = pycolmap.Reconstruction(str(sparse))
    for pid in sorted(rec.point3D_ids())[kept:]:
        rec.delete_point3D(pid)
    rec.write(str(sparse))


@pytest.mark.parametrize(
    "kept, said",
    [(0, "no sparse points in the scene's model"),
     (25, "only 0 of 12 photos see 30 or more of the 25 sparse points")],
    ids=["no-points", "too-few-points"],
)  # fmt: skip
def test_a_scene_whose_points_say_nothing_keeps_the_papers_model(
    tmp_path, scene_copy, kept, said
):
    """tiny with its sparse points removed (or all but 25): the appearance cannot
    be measured, so "auto" keeps the wild model and 4 appearances, keyed as those
    values given by hand, with one warning each naming what was missing."""
    _drop_points(scene_copy, kept)
    auto = {
        "reconstruct": ["wild=auto"],
        "render-appearances": ["n_appearances=auto"],
    }
    with _kept() as keep:
        chain = _chain(tmp_path, scene_copy, **auto)
        assert chain.config("reconstruct").wild is True
        assert chain.config("render-appearances").n_appearances == 4
    assert len(keep.warnings) == 2, keep.lines
    assert keep.warnings[0].startswith(f"reconstruct: wild = true (auto: {said}")
    assert "kept the paper's value" in keep.warnings[0]
    assert "--set reconstruct.wild=false" in keep.warnings[0]
    assert keep.warnings[1].startswith(
        f"render-appearances: n_appearances = 4 (auto: {said}"
    )
    by_hand = _chain(
        tmp_path, scene_copy, reconstruct=["wild=true"],
        **{"render-appearances": ["n_appearances=4"]},
    )  # fmt: skip
    assert chain.key("render-appearances") == by_hand.key("render-appearances")
    blob = json.loads((tmp_path / "work" / "tiny_s0" / "fit.json").read_text())
    assert blob["evidence"]["points"] == kept and blob["evidence"]["views"] == 0
    assert blob["evidence"]["read"] == 12


def test_an_ordinary_run_caches_the_evidence_and_status_writes_none(
    tmp_path, tiny_scene_dir, monkeypatch
):
    """status reads the photos and writes nothing; a command whose checks fail
    writes nothing; one that runs leaves fit.json, and the next command reads it
    instead of the photos."""
    from click.testing import CliRunner

    from conftest import run_cli
    from ptovs.cli import main

    monkeypatch.setattr(fit, "_MEASURED", {}, raising=False)  # measured afresh here
    work = tmp_path / "work"
    auto = ("--config", str(ROOT / "configs" / "auto.toml"))
    data = ("--data", str(tiny_scene_dir))
    out = run_cli(work, *auto, "status", *data)
    assert "reconstruct: wild = true (auto:" in out
    assert not work.exists()  # not fit.json, not anything
    failed = CliRunner().invoke(main, [
        "--work-dir", str(work), *auto, "extract-features", *data,
        "--set", "encoder=openclip", "--set", f"clip_checkpoint={tmp_path / 'no.pt'}",
    ])  # fmt: skip
    assert failed.exit_code != 0 and "no.pt" in failed.output, failed.output
    assert not work.exists()
    run_cli(work, *auto, "reconstruct", *data, "--set", "iterations=30")
    cache = work / "tiny_s0" / "fit.json"
    blob = json.loads(cache.read_text())
    assert blob["version"] == fit.EVIDENCE_VERSION and blob["evidence"]["views"] == 12

    def unread(scene):
        raise AssertionError("the photos were read again")

    monkeypatch.setattr(fit, "photo_evidence", unread)
    monkeypatch.setattr(fit, "_MEASURED", {}, raising=False)  # a new process
    out = run_cli(work, *auto, "reconstruct", *data, "--set", "iterations=30")
    assert "reconstruct: wild = true (auto:" in out
    assert json.loads(cache.read_text()) == blob


def test_a_wrong_auto_is_refused_naming_the_key(tmp_path, tiny_scene_dir):
    from ptovs.errors import InputError

    chain = _chain(tmp_path, tiny_scene_dir, query=["threshold=auto"])
    with pytest.raises(InputError, match="query.threshold"):
        chain.config("query")


# ------------------------------------------------------------ the two files --
def _flat(path: Path) -> dict[str, dict]:
    with open(path, "rb") as f:
        return tomllib.load(f)


def test_auto_toml_turns_every_fitted_decision_on():
    auto = _flat(ROOT / "configs" / "auto.toml")
    for stage, fields in fit.FITTED.items():
        for field in fields:
            assert auto.get(stage, {}).get(field) == "auto", f"{stage}.{field}"
    assert auto["extract-features"]["images"] == "auto"
    assert auto["reconstruct"]["stop"] == "plateau"


def test_paper_toml_pins_every_fitted_value_and_keys_as_the_default(
    tmp_path, tiny_scene_dir
):
    """paper.toml names a fixed value for every decision auto.toml can take, and
    today's default is the paper's recipe but for its named departures (each view
    segmented once, from its photo: docs/method.md §4): with those set back, every
    stage keys the same; without, the stages from extract-features on differ."""
    paper, auto = (
        _flat(ROOT / "configs" / "paper.toml"),
        _flat(ROOT / "configs" / "auto.toml"),
    )
    for stage, items in auto.items():
        for field in items if stage != "scene" else ():  # [scene]: not fitted
            assert field in paper.get(stage, {}), f"{stage}.{field}"
            assert paper[stage][field] != "auto"

    def keys(config: Path, departures: dict | None = None) -> dict[str, str]:
        cfg = load_config(config)
        for stage, items in (departures or {}).items():
            cfg.setdefault(stage, {}).update(items)
        ctx = RunContext(tmp_path / "w", cfg)
        chain = Chain(ctx, resolve_scene(ctx, None, tiny_scene_dir))
        return {s: chain.key(s) for s in chain.closure("evaluate")}

    paper_keys = keys(ROOT / "configs" / "paper.toml")
    assert paper["extract-features"]["segment"] == "each"
    assert paper_keys == keys(
        ROOT / "configs" / "default.toml", {"extract-features": {"segment": "each"}}
    )
    default = keys(ROOT / "configs" / "default.toml")
    assert [s for s in paper_keys if paper_keys[s] != default[s]] == [
        "extract-features", "uncertainty", "train-ae", "train-male", "query", "evaluate",
    ]  # fmt: skip


# ---------------------------------------------------------- the plateau stop --
@dataclasses.dataclass(frozen=True)
class _Cfg:
    densify_until: int = 100
    iterations: int = 1000
    stop_rel: float = 0.01
    stop_patience: int = 2


def test_plateau_ends_after_patience_windows_without_progress():
    from ptovs.field.train import TrainState, _plateau_check, plateau_window

    assert plateau_window(10) == 50 and plateau_window(120) == 120
    assert plateau_window(5000) == 200
    state = TrainState(None, None, None, torch.zeros(3), None)
    losses = [1.0] * 50 + [0.5] * 50 + [0.499] * 50 + [0.498] * 50 + [0.1] * 50
    for k, loss in enumerate(losses):
        _plateau_check(_Cfg(), state, 101 + k, loss, n_views=10)
        if state.ended:
            break
    # windows end at 150 (1.0), 200 (0.5: the best), 250 and 300 (under 1 %
    # better): ends at 300
    assert state.ended == 300
    assert state.plateau[0] == pytest.approx(0.5)


def test_plateau_is_silent_before_densification_ends():
    from ptovs.field.train import TrainState, _plateau_check

    state = TrainState(None, None, None, torch.zeros(3), None)
    for step in range(1, 101):
        _plateau_check(_Cfg(), state, step, 1.0, n_views=10)
    assert state.ended == 0 and state.plateau_window == [0.0, 0.0]


def test_train_stops_on_the_plateau_and_a_resumed_run_ends_the_same(
    tiny_scene_dir, tmp_path
):
    """A short tiny fit whose loss cannot gain 50 % a window: it ends at
    until + 3 windows; resumed from its mid-run checkpoint it ends at the same
    step with the same parameters."""
    from ptovs.field.train import train
    from ptovs.stages.reconstruct import Config, _views_and_images

    ctx = RunContext(tmp_path / "work", load_config(None))
    scene = resolve_scene(ctx, None, tiny_scene_dir).load()
    _, images, cams = _views_and_images(scene)
    cfg = Config(
        iterations=600, densify_from=50, densify_until=100, mask_warmup=50,
        stop="plateau", stop_rel=0.5, stop_patience=2, checkpoint_every=175,
    )  # fmt: skip
    points = (scene.points_xyz, scene.points_rgb)
    saved: list[dict] = []
    # a copy, as a checkpoint on disk is (the optimiser's state moves on in place)
    whole = train(
        cfg, images, cams, points, save=lambda s: saved.append(copy.deepcopy(s))
    )
    # windows of 50 steps from step 100: the first sets the best, two more fail
    assert whole.ended == whole.step == 250
    assert whole.history["step"][-1] == 250
    mid = next(s for s in saved if s["step"] == 175)
    again = train(cfg, images, cams, points, load=lambda: mid)
    assert again.step == again.ended == 250
    for k, v in whole.model.params.items():
        torch.testing.assert_close(again.model.params[k], v, rtol=0, atol=0)
    # a run resumed after it ended trains no further
    done = train(cfg, images, cams, points, load=lambda: whole.to_dict())
    assert done.step == 250


# ------------------------------------------------------- the whole chain --
def _levels(work: Path) -> dict:
    from ptovs.artifacts import Artifact, read_json_dataset

    (path,) = (work / "tiny_s0" / "extract-features").glob("*.h5")
    with Artifact(path) as a:
        return read_json_dataset(a.root()["levels_json"])


def _wild(work: Path) -> bool:
    from ptovs.artifacts import Artifact

    (path,) = (work / "tiny_s0" / "reconstruct").glob("*.h5")
    with Artifact(path) as a:
        return json.loads(a.attrs["config_json"])["wild"]


def test_auto_toml_runs_the_whole_chain(tmp_path, tiny_scene_dir):
    """configs/auto.toml on tiny (changing light): the wild model, every image kept
    after the probe, the chain evaluated; each decision said once."""
    from conftest import run_cli

    work = tmp_path / "work"
    cfg = str(ROOT / "configs" / "auto.toml")
    out = run_cli(work, "--config", cfg, "evaluate", "--data", str(tiny_scene_dir))
    said = [ln.removeprefix("ptovs: ") for ln in out.splitlines()]
    assert _wild(work) is True
    levels = _levels(work)
    assert levels["images"] in ("all", "orig+self")
    assert levels["images_probe"]["segments"] > 0 and "why" in levels["images_probe"]
    assert sum("reconstruct: wild = true (auto:" in m for m in said) == 1
    assert sum(m.startswith("extract-features: images = ") for m in said) == 1
    assert list((work / "tiny_s0" / "evaluate").glob("*.h5"))


def test_a_shared_appearance_runs_plain_with_the_photo_and_its_self_render(
    tmp_path, tiny_scene_dir, monkeypatch
):
    """Where the photos share one appearance the fitted chain is plain 3DGS, one
    appearance (the self render) and two images a view, and it runs to the end."""
    from conftest import run_cli

    shared = {"appearance_spread": 0.01, "views": 12, "short_side": 72}
    monkeypatch.setattr(fit, "cached_evidence", lambda ref: dict(shared))
    work = tmp_path / "work"
    sets = ['--set=reconstruct.wild="auto"', "--set=render-appearances.n_appearances=auto",
            "--set=extract-features.images=auto"]  # fmt: skip
    run_cli(work, *sets, "evaluate", "--data", str(tiny_scene_dir))
    assert _wild(work) is False
    levels = _levels(work)
    assert levels["images"] == "orig+self" and levels["apps"] == ["orig", "self"]
    assert levels["images_probe"]["why"] == "no novel appearance rendered"
    assert list((work / "tiny_s0" / "evaluate").glob("*.h5"))
