"""extract-features' economies on `tiny`: one segmentation per view
(`segment = "once"`) and no crops the encoder cannot read (`min_crop_px`)."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import RECON, copy_work
from ptovs.features import SegmentFeatures, view_apps
from ptovs.segment import NO_SEGMENT, Level
from ptovs.segment import cut as segcut
from ptovs.stages import extract_features as ef


@pytest.fixture(scope="module")
def work(tmp_path_factory, extracted_work):
    return copy_work(extracted_work[0], tmp_path_factory.mktemp("econ") / "work")


def _extract(work, data, *items: str) -> dict[str, dict[str, np.ndarray]]:
    """extract-features with `items` set (its upstream cached): view -> datasets."""
    from ptovs.chain import Chain, RunContext, execute
    from ptovs.locate import resolve_scene

    ctx = RunContext(work, {})
    sets = {
        "reconstruct": [r.removeprefix("--set=reconstruct.") for r in RECON],
        "extract-features": list(items),
    }
    chain = Chain(ctx, resolve_scene(ctx, None, data), sets)
    for stage in chain.closure("render-appearances"):
        execute(chain, stage).close()
    art = execute(chain, "extract-features")
    try:
        return {
            n: {k: np.asarray(v[k]) for k in v} for n in art.names() for v in [art[n]]
        }
    finally:
        art.close()


class _Counting:
    """Wraps a segmenter: counts `segment` calls and records what truth selected."""

    def __init__(self, inner):
        self.inner, self.name, self.levels = inner, inner.name, inner.levels
        self.calls, self.selected = 0, []
        if hasattr(inner, "select"):
            self.select = self._select

    def _select(self, stem, photo):
        self.selected.append(photo)
        self.inner.select(stem, photo)

    def segment(self, image):
        self.calls += 1
        return self.inner.segment(image)


@pytest.fixture
def counting(monkeypatch):
    made = []
    real = ef.build_segmenter

    def build(config, scene_root=None):
        made.append(_Counting(real(config, scene_root)))
        return made[-1]

    monkeypatch.setattr(ef, "build_segmenter", build)
    return made


def test_segment_once_reuses_the_views_segments(work, tiny_scene_dir, counting):
    each = _extract(work, tiny_scene_dir, "segment=each")  # every image its own
    for source in ("self", "orig"):
        once = _extract(work, tiny_scene_dir, "segment=once", f"segment_from={source}")
        (seg,) = counting[-1:]
        assert seg.calls == len(once)  # one segmenter call per view, not five
        for name, view in once.items():
            apps = view_apps(view)
            assert apps == ["orig", "nov1", "nov2", "nov3", "self"]
            for app in apps:
                SegmentFeatures.from_view(view, app).validate(f"{name} {app}")
                # every image carries the segments of the one it was cut from
                assert np.array_equal(view[f"seg_{app}"], each[name][f"seg_{source}"])
                assert np.array_equal(view[f"nseg_{app}"], each[name][f"nseg_{source}"])
            # ... and is cropped and encoded with its own pixels
            assert np.array_equal(view[f"feat_{source}"], each[name][f"feat_{source}"])
            assert not np.array_equal(view["feat_orig"], view["feat_self"])


def test_segment_once_with_truth_segments(work, tiny_scene_dir, counting):
    """Truth segments of the source image: the photo's with its occluders, the
    self render's without, whatever image they crop."""
    each = _extract(work, tiny_scene_dir, "segmenter=truth", "segment=each")
    assert counting[-1].selected.count(True) == len(each)  # the photos only
    for source, photo in (("self", False), ("orig", True)):
        once = _extract(
            work, tiny_scene_dir, "segmenter=truth", "segment=once",
            f"segment_from={source}",
        )  # fmt: skip
        assert counting[-1].selected == [photo] * len(once)
        for name, view in once.items():
            for app in view_apps(view):
                assert np.array_equal(view[f"seg_{app}"], each[name][f"seg_{source}"])


def _level(labels) -> Level:
    return Level(np.asarray(labels, np.int32))


def test_min_crop_px_drops_exactly_the_small_segments():
    lab = np.full((20, 30), 0, np.int32)
    lab[2:5, 3:6] = 1  # 3 x 3
    lab[10:19, 20:24] = 2  # 9 tall, 4 wide: longer side 9
    lab[0, 29] = NO_SEGMENT
    lab[15, 2] = 3  # one pixel
    lab[6, 8:18] = 4  # one row of 10
    level = _level(lab)
    assert segcut.crop_sides(level).tolist() == [30, 3, 9, 1, 10]
    (out,) = segcut.drop_small_segments([level], 9)
    assert out.n == 3  # 0, 2 and 4 kept, in their order
    gone = np.isin(lab, [1, 3])
    assert (out.labels[gone] == NO_SEGMENT).all()
    assert (out.labels[lab == NO_SEGMENT] == NO_SEGMENT).all()
    for old, new in ((0, 0), (2, 1), (4, 2)):
        assert (out.labels[lab == old] == new).all()
    f = SegmentFeatures.from_levels([out], [np.eye(3)], 3)
    f.validate()
    # every segment small: the level is empty, and still valid
    (none,) = segcut.drop_small_segments([level], 31)
    assert none.n == 0 and (none.labels == NO_SEGMENT).all()
    SegmentFeatures.from_levels([none], [np.zeros((0, 3))], 3).validate()
    # 0 (and any size all segments reach) changes nothing
    assert segcut.drop_small_segments([level], 0)[0] is level
    assert segcut.drop_small_segments([level], 1)[0] is level


def test_min_crop_px_measures_the_cropped_mask():
    """SAM's levels crop a whole mask (painted over in the labels): its box counts."""
    lab = np.zeros((16, 16), np.int32)
    lab[0:2, 0:2] = 1  # visible as 2 x 2 ...
    whole = np.zeros((16, 16), bool)
    whole[0:12, 0:12] = True  # ... but its mask's box is 12 x 12
    small = lab == 0
    small[:] = False
    small[14:16, 14:16] = True
    lab[14:16, 14:16] = 2
    masks = [lab == 0, whole, small]
    level = Level(lab, masks)
    assert segcut.crop_sides(level).tolist() == [16, 12, 2]
    (out,) = segcut.drop_small_segments([level], 4)
    assert out.n == 2 and len(out.masks) == 2 and out.masks[1] is whole
    assert (out.labels[14:, 14:] == NO_SEGMENT).all()


def test_min_crop_px_in_the_stage(work, tiny_scene_dir):
    base = _extract(work, tiny_scene_dir)
    cut = _extract(work, tiny_scene_dir, "min_crop_px=16")
    dropped = 0
    for name, view in cut.items():
        for app in view_apps(view):
            f = SegmentFeatures.from_view(view, app)
            f.validate(f"{name} {app}")
            b = SegmentFeatures.from_view(base[name], app)
            dropped += int(b.counts.sum() - f.counts.sum())
            for lv in range(f.levels):
                level = _level(f.local(lv))
                if level.n:
                    assert segcut.crop_sides(level).min() >= 16
                # a kept segment is the one it was, its pixels unchanged
                kept = f.seg[lv] >= 0
                assert np.array_equal(f.dense(lv)[0][kept], b.dense(lv)[0][kept])
    assert dropped > 0
