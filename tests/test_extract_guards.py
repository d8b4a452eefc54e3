"""extract-features decides once per artifact and stops when it finds nothing:
the precision "auto" chose is stored before the first view and reused by a
resumed run; views without any segment are counted, and a segmenter that finds
nothing in most views stops the stage and leaves no partial artifact behind."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from ptovs.artifacts import read_json_dataset
from ptovs.chain import Chain, RunContext, execute
from ptovs.cli import main
from ptovs.errors import InputError, UselessOutputError
from ptovs.locate import resolve_scene
from ptovs.scene import load_scene
from ptovs.segment import NO_SEGMENT, Level
from ptovs.stages import extract_features as ef

STAGE = "extract-features"


class _Halves:
    """Two segments (left / right half) at every level; none for the views in
    `empty`; raises KeyboardInterrupt (a kill) on the view `die_at`."""

    name = "halves"

    def __init__(self, levels, empty=(), die_at=None):
        self.levels = tuple(levels)
        self.empty, self.die_at = set(empty), die_at
        self.stem = None
        self.calls: list[str] = []

    def select(self, stem, photo):  # called by extract-features before `segment`
        self.stem = stem

    def segment(self, image):
        self.calls.append(self.stem)
        if self.stem == self.die_at:
            raise KeyboardInterrupt
        h, w = image.shape[:2]
        lab = np.full((h, w), NO_SEGMENT, np.int32)
        if self.stem not in self.empty:
            lab[:, : w // 2] = 0
            lab[:, w // 2 :] = 1
        return [Level(lab.copy()) for _ in self.levels]


class _Precise:
    """An OpenCLIP-like encoder with precision "auto": the first check in the
    process keeps bf16, any later one fp32. Each row says the precision it was
    encoded at (first component 1 for bf16, second for fp32)."""

    name = "fake"
    dim = 4
    size = 8
    checks = 0  # over every instance: a resumed run builds a new encoder

    def __init__(self):
        self.precision_wanted, self.precision = "auto", "fp32"
        self.used: list[str] = []

    def check_precision(self, crops):
        type(self).checks += 1
        kept = "bf16" if type(self).checks == 1 else "fp32"
        return {"precision": kept, "checked": "bf16", "crops": int(len(crops))}

    def encode_images(self, crops):
        self.used.append(self.precision)
        rows = np.zeros((len(crops), self.dim), np.float32)
        rows[:, 0 if self.precision == "bf16" else 1] = 1.0
        return rows


@pytest.fixture
def fakes(monkeypatch):
    """Patch extract-features' builders; returns the lists of what was built."""
    made: dict[str, list] = {"seg": [], "enc": []}
    options: dict = {"empty": (), "die_at": None}
    _Precise.checks = 0

    def segmenter(config, scene_root=None):
        made["seg"].append(_Halves(config.levels, **options))
        return made["seg"][-1]

    def encoder(config, synthetic, scene_root=None):
        made["enc"].append(_Precise())
        return made["enc"][-1]

    monkeypatch.setattr(ef, "build_segmenter", segmenter)
    monkeypatch.setattr(ef, "build_encoder", encoder)
    return made, options


def _chain(tmp_path, data, *items: str) -> Chain:
    ctx = RunContext(tmp_path / "work", {})
    sets = {STAGE: ["images=orig", *items]}
    return Chain(ctx, resolve_scene(ctx, None, data), sets)


def _parts(chain: Chain):
    store, key = chain.ctx.store, chain.key(STAGE)
    return store.path(chain.scene.name, STAGE, key).with_suffix(".parts")


def test_precision_is_chosen_once_and_reused_on_resume(tmp_path, tiny_scene_dir, fakes):
    made, options = fakes
    chain = _chain(tmp_path, tiny_scene_dir)
    views = chain.scene.load().train_views()
    options["die_at"] = views[1].stem  # killed in the second view
    with pytest.raises(KeyboardInterrupt):
        execute(chain, STAGE)
    parts = _parts(chain)
    assert len(list(parts.glob("*.h5"))) == 1  # the first view was stored
    notes = json.loads((parts / "notes.json").read_text())
    assert notes["notes"]["precision"]["precision"] == "bf16"
    assert _Precise.checks == 1

    options["die_at"] = None  # resumed, as on another machine: would choose fp32
    art = execute(chain, STAGE)
    try:
        assert _Precise.checks == 1  # not checked again
        resumed = made["enc"][-1]
        assert resumed.precision == "bf16"
        assert set(resumed.used) == {"bf16"}
        assert art.names() == sorted(v.name for v in views)
        for name in art.names():
            feat = art[name]["feat_orig"]
            assert len(feat) == 2 * 3  # two halves at each of s/m/l
            np.testing.assert_array_equal(feat[:, 0], 1.0)  # all encoded in bf16
        meta = read_json_dataset(art.root()["levels_json"])
        assert meta["precision"] == {"precision": "bf16", "checked": "bf16",
                                     "crops": 2}  # fmt: skip
        assert (meta["empty_views"], meta["views"]) == (0, len(views))
        # the decision is kept with the artifact, and the parts are gone
        assert json.loads(art.attrs["notes_json"])["precision"]["precision"] == "bf16"
    finally:
        art.close()
    assert not parts.exists()


def test_force_forgets_the_stored_precision(tmp_path, tiny_scene_dir, fakes):
    chain = _chain(tmp_path, tiny_scene_dir)
    execute(chain, STAGE).close()
    art = execute(chain, STAGE, force=True)  # a new artifact decides afresh
    try:
        meta = read_json_dataset(art.root()["levels_json"])
        assert _Precise.checks == 2 and meta["precision"]["precision"] == "fp32"
    finally:
        art.close()


def test_a_few_empty_views_are_counted_not_fatal(
    tmp_path, tiny_scene_dir, fakes, caplog
):
    made, options = fakes
    chain = _chain(tmp_path, tiny_scene_dir)
    views = chain.scene.load().train_views()
    options["empty"] = {views[2].stem, views[7].stem}
    with caplog.at_level("WARNING", logger="ptovs"):
        art = execute(chain, STAGE)
    try:
        meta = read_json_dataset(art.root()["levels_json"])
        assert meta["empty_views"] == 2 and meta["views"] == len(views) == 12
        assert meta["empty_view_names"] == sorted([views[2].name, views[7].name])
        assert np.all(art[views[2].name]["seg_orig"] == NO_SEGMENT)
        assert art[views[2].name]["feat_orig"].shape == (0, 4)
    finally:
        art.close()
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert sum(views[2].name in w for w in warned) == 2  # its own line + the summary
    assert any("2 of 12 views have no segment" in w for w in warned)


def test_empty_views_are_counted_across_a_resume(tmp_path, tiny_scene_dir, fakes):
    made, options = fakes
    chain = _chain(tmp_path, tiny_scene_dir)
    views = chain.scene.load().train_views()
    options.update(empty={views[0].stem}, die_at=views[3].stem)
    with pytest.raises(KeyboardInterrupt):
        execute(chain, STAGE)
    options["die_at"] = None
    art = execute(chain, STAGE)
    try:
        meta = read_json_dataset(art.root()["levels_json"])
        assert meta["empty_views"] == 1 and meta["empty_view_names"] == [views[0].name]
    finally:
        art.close()


def test_a_segmenter_that_finds_nothing_stops_and_leaves_nothing(
    tmp_path, tiny_scene_dir, fakes, caplog
):
    made, options = fakes
    chain = _chain(tmp_path, tiny_scene_dir, "segmenter=sam2",
                   "sam_checkpoint=random.pt")  # fmt: skip
    views = chain.scene.load().train_views()
    options["empty"] = {v.stem for v in views}
    with caplog.at_level("WARNING", logger="ptovs"):
        with pytest.raises(UselessOutputError) as err:
            execute(chain, STAGE)
    msg = str(err.value)
    assert isinstance(err.value, InputError) and "\n" not in msg  # the CLI's one line
    assert "in 3 of 3 views" in msg  # stopped after the first three
    size = f"images too small ({views[2].width}x{views[2].height} px"
    for cause in ("sam_checkpoint = 'random.pt'", "sam_points_per_side = 32",
                  "sam_crop_n_layers", size):  # fmt: skip
        assert cause in msg
    # the precision sample's view 0, then the first three views and no more
    assert made["seg"][-1].calls == [v.stem for v in (views[0], *views[:3])]
    warned = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert sum("no segment at any level" in w for w in warned) == 3
    parts = _parts(chain)
    assert not parts.exists()  # no stored views, no notes: a rerun starts clean
    store = chain.ctx.store
    assert not store.exists(chain.scene.name, STAGE, chain.key(STAGE))


def test_the_cli_prints_the_stop_in_one_line(tmp_path, tiny_scene_dir, fakes):
    made, options = fakes
    options["empty"] = {v.stem for v in load_scene(tiny_scene_dir).train_views()}
    work = tmp_path / "work"
    res = CliRunner().invoke(main, ["--work-dir", str(work), STAGE, "--data",
                                    str(tiny_scene_dir), "--set", "images=orig"])  # fmt: skip
    assert res.exit_code == 1, res.output
    (line,) = [x for x in res.output.splitlines() if x.startswith("Error:")]
    assert "segmenter 'hier' found no segment at any level in 3 of 3" in line
    assert "hier_thresholds" in line and "hier_min_size = 300" in line
    assert not list((work / tiny_scene_dir.name / STAGE).glob("*.parts"))


@pytest.mark.parametrize(
    ("empty", "finished", "total", "stop"),
    [
        (2, 2, 12, False),  # too early to tell
        (3, 3, 12, True),  # each of the first three
        (2, 3, 12, False),
        (3, 5, 12, True),  # more than half from five on
        (2, 5, 12, False),
        (5, 10, 12, False),  # half is not most
        (2, 2, 2, True),  # a small scene: at its end
        (1, 2, 2, False),
        (2, 4, 4, False),
    ],
)
def test_the_stop_rule(empty, finished, total, stop):
    assert ef.too_many_empty(empty, finished, total) is stop


def test_notes_belong_to_their_key_and_go_with_the_parts(tmp_path):
    from ptovs.artifacts import Notes, Store

    store, key = Store(tmp_path), "a" * 64
    writer = store.writer("s", "x", key, {})
    assert writer.notes.get("precision") is None
    writer.notes.put("precision", {"precision": "bf16"})
    writer.notes.put("empty_views", ["v1"])
    resumed = store.writer("s", "x", key, {})  # what a resumed run opens
    assert resumed.notes.all() == {"precision": {"precision": "bf16"},
                                   "empty_views": ["v1"]}  # fmt: skip
    assert Notes(writer.parts, "b" * 64).all() == {}  # another key's: ignored
    writer.write_view("v", {"x": np.zeros(2, np.float32)})
    assert store.partial_views("s", "x", key) == 1  # notes are not a view
    writer.discard()  # --force
    assert writer.notes.all() == {} and writer.parts.is_dir()
    writer.notes.put("precision", {"precision": "fp32"})
    writer.remove()
    assert not writer.parts.exists()
