"""The segment tools: truth levels (the instrument's perfect segmenter), the
hierarchical merging segmenter, the segment-quality measures, and query filters
that follow the image size."""

from __future__ import annotations

import numpy as np
import pytest

from ptovs.segment.quality import boundaries, boundary_f, covering
from ptovs.segment.truth import GROUND, SKY, TruthSegmenter, truth_ids, truth_levels


def _world() -> tuple[np.ndarray, np.ndarray]:
    """Part ids of a 40×60 image: sky above, ground below, part 0 in two pieces,
    part 1 between them; and an occluder over part 1's corner."""
    pid = np.full((40, 60), SKY, np.int32)
    pid[30:] = GROUND
    pid[10:30, 5:15] = 0
    pid[10:30, 45:55] = 0
    pid[5:30, 20:40] = 1
    tr = np.zeros(pid.shape, bool)
    tr[20:35, 35:44] = True
    return pid, tr


def _nested(fine: np.ndarray, coarse: np.ndarray) -> bool:
    pairs = np.unique(fine.ravel().astype(np.int64) * 10**6 + coarse.ravel())
    return len(np.unique(pairs // 10**6)) == len(np.unique(fine))


def test_truth_levels_pieces_parts_whole_and_occluders():
    pid, tr = _world()
    s, m, lv = (x.labels for x in truth_levels(pid, tr, ("s", "m", "l")))
    for lab in (s, m, lv):
        assert lab.dtype == np.int32 and lab.min() == 0
        assert np.array_equal(np.unique(lab), np.arange(lab.max() + 1))  # contiguous
        assert len(np.unique(lab[tr])) == 1  # the occluder is one segment
        assert not np.isin(lab[tr], lab[~tr]).any()  # and no other's
    # s: the two pieces of part 0 differ; m: one part; l: part 0 and 1 are one
    assert s[15, 10] != s[15, 50] and m[15, 10] == m[15, 50]
    assert m[15, 10] != m[15, 30] and lv[15, 10] == lv[15, 30]
    # sky and ground are their own at every level
    for lab in (s, m, lv):
        assert lab[0, 0] != lab[39, 0] and lab[0, 0] != lab[15, 10]
    assert s.max() + 1 == 6 and m.max() + 1 == 5 and lv.max() + 1 == 4
    # a render (no occluders): part 1 keeps its corner
    m2 = truth_levels(pid, None, ("m",))[0].labels
    assert m2[25, 37] == m2[10, 30]


def test_truth_ids_tell_ground_from_sky_and_refusals(tmp_path):
    pid = np.array([[-1, -1], [0, 2]], np.int16)
    depth = np.array([[np.inf, 5.0], [3.0, 2.0]])
    assert truth_ids(pid, depth).tolist() == [[SKY, GROUND], [0, 2]]
    with pytest.raises(ValueError, match="synthetic scene"):
        TruthSegmenter(tmp_path)
    with pytest.raises(ValueError, match="does not match"):
        truth_levels(np.zeros((3, 3)), np.zeros((2, 2), bool))


def test_covering_and_boundary_f_on_known_maps():
    pid, _ = _world()
    assert covering(pid, pid) == pytest.approx(1.0)
    assert boundary_f(pid, pid)[0] == pytest.approx(1.0)
    one = np.zeros_like(pid)
    # one segment for everything: each part's IoU is its share of the image
    n0, n1 = (pid == 0).sum(), (pid == 1).sum()
    want = (n0 * n0 / pid.size + n1 * n1 / pid.size) / (n0 + n1)
    assert covering(one, pid) == pytest.approx(want)
    f, p, r = boundary_f(one, pid)
    assert (f, p, r) == (0.0, 1.0, 0.0)
    # boundaries moved by more than the tolerance are missed; by less, found
    xx = np.mgrid[:40, :60][1]
    assert boundary_f(xx < 36, xx < 30, tol=1.0)[0] == 0.0
    assert boundary_f(xx < 31, xx < 30, tol=1.5)[0] == pytest.approx(1.0)
    assert np.isnan(covering(one, np.full_like(pid, -1)))
    assert boundaries(np.zeros((1, 1), int)).sum() == 0
    with pytest.raises(ValueError):
        covering(one[:-1], pid)


def _three_parts() -> tuple[np.ndarray, np.ndarray]:
    """Three flat parts side by side with sensor noise: A and B 17 CIELAB units
    apart (one material in two lights), C 68 from A; RGB and part ids."""
    h, w = 192, 256
    img = np.zeros((h, w, 3))
    pid = np.zeros((h, w), np.int32)
    img[:, :96], img[:, 96:176], img[:, 176:] = (
        (150, 100, 80),
        (170, 115, 85),
        (60, 90, 170),
    )
    pid[:, 96:176], pid[:, 176:] = 1, 2
    noise = np.random.default_rng(0).normal(0, 3, img.shape)
    return np.clip(img + noise, 0, 255).astype(np.uint8), pid


def test_hier_levels_nest_and_merge_by_region_colour():
    from ptovs.segment import get_segmenter

    img, pid = _three_parts()
    levels = get_segmenter("hier", levels=("s", "m", "l")).segment(img)
    assert [lv.labels.shape for lv in levels] == [pid.shape] * 3
    for lv in levels:
        assert np.array_equal(np.unique(lv.labels), np.arange(lv.n))
    assert levels[0].n >= levels[1].n >= levels[2].n
    assert _nested(levels[0].labels, levels[1].labels)
    assert _nested(levels[1].labels, levels[2].labels)
    s, m = levels[0].labels, levels[1].labels
    # s (cut at 8): the three parts apart, the noise merged away
    assert covering(s, pid) > 0.95
    assert len({s[50, 10], s[50, 120], s[50, 200]}) == 3
    # m (cut at 20): A and B are one region, C stays apart
    assert m[50, 10] == m[50, 120] != m[50, 200]
    # deterministic, and the same whatever the level order
    again = get_segmenter("hier", levels=("l", "s")).segment(img)
    assert np.array_equal(again[0].labels, levels[2].labels)
    assert np.array_equal(again[1].labels, levels[0].labels)


@pytest.mark.parametrize("shape", [(1, 1, 3), (2, 3, 3), (40, 1, 3), (64, 48, 3)])
def test_hier_hard_cases(shape):
    from ptovs.segment import get_segmenter

    seg = get_segmenter("hier", levels=("s", "m", "l"))
    const = np.full(shape, 77, np.uint8)
    for lv in seg.segment(const):
        assert lv.n == 1 and (lv.labels == 0).all()
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 256, shape, dtype=np.uint8)
    for lv in seg.segment(noise):
        assert lv.labels.shape == shape[:2] and lv.labels.min() == 0
    with pytest.raises(ValueError, match="uint8"):
        seg.segment(noise.astype(np.float32))


def test_filters_follow_the_image_and_reproduce_the_authors_at_340_px():
    import torch

    from ptovs.field.relevancy import QuerySettings, finish

    fixed = QuerySettings()
    scaled = QuerySettings(filter_ref=340.0)
    assert fixed.filter_sizes(100, 80) == (20, 7)
    assert scaled.filter_sizes(340, 514) == (20, 7)  # the authors' r = 2 photos
    assert scaled.filter_sizes(514, 340) == (20, 7)
    assert scaled.filter_sizes(170, 256) == (10, 3)
    assert scaled.filter_sizes(680, 1028) == (40, 13)
    assert scaled.filter_sizes(20, 30) == (1, 1)
    for h, w in [(120, 180), (700, 900)]:
        k, m = scaled.filter_sizes(h, w)
        assert k >= 1 and m >= 1 and m % 2 == 1
    off = QuerySettings(smooth_kernel=1, majority=1, filter_ref=340.0)
    assert off.filter_sizes(1000, 1000) == (1, 1)
    # at 340 px the scaled rule is the fixed rule, bit for bit
    g = torch.Generator().manual_seed(0)
    s = torch.rand(3, 2, 340, 514, generator=g)
    b = torch.rand(3, 2, 340, 514, generator=g) * 0.5
    r1, r2 = finish(s, b, fixed), finish(s, b, scaled)
    assert np.array_equal(r1.smoothed, r2.smoothed) and np.array_equal(r1.mask, r2.mask)
    # smaller: not the fixed rule's result
    s2, b2 = s[..., :170, :257], b[..., :170, :257]
    assert not np.array_equal(
        finish(s2, b2, fixed).smoothed, finish(s2, b2, scaled).smoothed
    )


def test_the_stage_builds_each_segmenter_and_refuses_truth_without_truth(tmp_path):
    from ptovs.errors import InputError
    from ptovs.segment.graph import GraphSegmenter
    from ptovs.segment.hier import HierSegmenter
    from ptovs.stages.extract_features import Config, build_segmenter

    assert isinstance(build_segmenter(Config()), HierSegmenter)  # the default
    assert isinstance(build_segmenter(Config(segmenter="graph")), GraphSegmenter)
    seg = build_segmenter(Config(hier_thresholds=(5.0, 9.0, 30.0)))
    assert seg.thresholds["s"] == 5.0 and seg.thresholds["l"] == 30.0
    with pytest.raises(ValueError, match="one value per level"):
        build_segmenter(Config(hier_thresholds=(5.0,)))
    with pytest.raises(InputError, match="synthetic scene"):
        build_segmenter(Config(segmenter="truth"), tmp_path)
