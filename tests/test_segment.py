"""Segmenters (graph, SAM), mask filtering, and the OpenCLIP encoder backend."""

from __future__ import annotations

import inspect
import sys
from collections import Counter

import numpy as np
import pytest
import torch

from conftest import (
    add_disks,
    assert_points_match,
    assert_same_masks,
    langsplat_paint_anns,
    one_output,
    reference_batched_nms,
)
from ptovs.compat import available
from ptovs.encoders import get_encoder
from ptovs.segment import NO_SEGMENT, get_segmenter
from ptovs.segment.masks import box_iou, box_nms, mask_nms, mask_nms_reference, paint

HAS_SAM = available("segment_anything")
HAS_CLIP = available("open_clip")
NO_SAM = "extra [sam] not installed (pip install torchvision==0.28.0 -e '.[sam]')"
NO_CLIP = "extra [clip] not installed (pip install torchvision==0.28.0 -e '.[clip]')"


def _blocks(h=96, w=128) -> np.ndarray:
    """An image of flat coloured blocks with mild noise."""
    rng = np.random.default_rng(0)
    img = np.zeros((h, w, 3), np.float32)
    img[:, : w // 2] = (200, 40, 40)
    img[:, w // 2 :] = (40, 40, 200)
    img[h // 2 :, w // 4 : 3 * w // 4] = (40, 200, 40)
    img += rng.normal(0, 3, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


# ---------------------------------------------------------------- graph --


def test_graph_levels_cover_and_coarsen():
    seg = get_segmenter("graph")
    img = (np.random.default_rng(1).random((120, 160, 3)) * 255).astype(np.uint8)
    img = np.repeat(np.repeat(img[::8, ::8], 8, 0), 8, 1)  # blocky texture
    levels = seg.segment(img)
    assert len(levels) == 3
    ns = []
    for lv in levels:
        assert lv.labels.shape == (120, 160) and lv.labels.dtype == np.int32
        assert lv.labels.min() == 0  # every pixel covered
        assert np.array_equal(np.unique(lv.labels), np.arange(lv.n))
        ns.append(lv.n)
    assert ns[0] >= ns[1] >= ns[2] and ns[0] > ns[2]
    flat = seg.segment(_blocks())[2].labels  # whole level on three flat blocks
    h, w = flat.shape
    for block in (
        flat[: h // 2, : w // 4],
        flat[: h // 2, -w // 4 :],
        flat[-h // 4 :, w // 3 : 2 * w // 3],
    ):
        assert np.bincount(block.ravel()).max() > 0.9 * block.size  # one segment each
    with pytest.raises(ValueError):
        seg.segment(np.zeros((10, 10, 3), np.float32))
    with pytest.raises(ValueError, match="levels"):
        get_segmenter("graph", levels=("s", "xl"))


# ---------------------------------------------------------------- masks --


def _random_masks(rng, m, h=24, w=20):
    masks = np.zeros((m, h, w), bool)
    for i in range(m):
        y0, x0 = rng.integers(0, h - 4), rng.integers(0, w - 4)
        y1, x1 = rng.integers(y0 + 1, h + 1), rng.integers(x0 + 1, w + 1)
        masks[i, y0:y1, x0:x1] = True
    # nested and duplicated masks exercise the inner and IoU rules
    masks[1] = masks[0]
    masks[2] = False
    masks[2, 2:20, 2:18] = True
    masks[3] = False
    masks[3, 5:8, 5:8] = True
    return torch.from_numpy(masks)


@pytest.mark.parametrize("seed", range(8))
def test_mask_nms_matches_reference(seed):
    rng = np.random.default_rng(seed)
    masks = _random_masks(rng, 14)
    scores = torch.from_numpy(rng.random(14)).float()
    got = mask_nms(masks, scores)
    want = mask_nms_reference(masks, scores)
    assert got.tolist() == want.tolist()
    assert len(got) < 14  # something was filtered


def test_mask_nms_rules_and_edges():
    big = torch.zeros(1, 20, 20, dtype=torch.bool)
    big[0, :, :] = True
    small = torch.zeros(1, 20, 20, dtype=torch.bool)
    small[0, :4, :4] = True  # fully inside `big`, covers 4 % of it
    masks = torch.cat([big, small])
    # the inner mask goes, whichever scores higher
    assert mask_nms(masks, torch.tensor([0.9, 0.8])).tolist() == [0]
    assert mask_nms(masks, torch.tensor([0.8, 0.9])).tolist() == [0]
    # nothing above the score threshold: the top 3 survive that rule
    low = torch.tensor([0.1, 0.2])
    assert sorted(mask_nms(torch.cat([small, ~small]), low).tolist()) == [0, 1]
    assert mask_nms(torch.zeros(0, 5, 5, dtype=torch.bool), torch.zeros(0)).numel() == 0


def test_box_nms_greedy():
    boxes = torch.tensor(
        [[0, 0, 10, 10], [1, 1, 11, 11], [20, 20, 30, 30], [0, 0, 10, 10.5]]
    )
    scores = torch.tensor([0.9, 0.8, 0.7, 0.95])
    assert box_nms(boxes, scores, 0.5).tolist() == [3, 2]
    assert box_iou(boxes[:1], boxes[:1]).item() == pytest.approx(1.0)
    assert box_nms(torch.zeros(0, 4), torch.zeros(0), 0.5).numel() == 0


def test_reuse_freed_memory_keeps_freed_tensors_pages():
    """Inside `reuse_freed_memory` freed 64 MB tensors' pages serve the next ones
    (no page faults once the heap has grown); outside, glibc unmaps each and the
    kernel faults in fresh zeroed pages every time; on exit that default is back."""
    import resource

    from ptovs.segment.generator import _glibc, reuse_freed_memory

    if _glibc() is None:
        pytest.skip("not glibc, or malloc tuned through the environment")

    def faults(n: int = 3) -> int:
        start = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        for _ in range(n):
            t = torch.ones(16 << 20)  # 64 MB, above glibc's largest mmap threshold
            del t
        return resource.getrusage(resource.RUSAGE_SELF).ru_minflt - start

    outside = faults()
    with reuse_freed_memory():
        faults(4)  # the heap grows to a few such tensors (aligned allocations)
        inside = faults()
    assert inside < 3 * 16384 / 10  # 16384 pages a tensor: freed pages serve again
    # glibc's default unmaps each such tensor, unless this process's earlier
    # allocations already raised its thresholds (other tests ran here first)
    if outside > 3 * 10_000:
        # on exit the default is back: tensors fault again, more than inside's bound
        # (how many of the three depends on glibc's trimming: 1 or 2 seen in a suite)
        assert faults() >= 3 * 16384 / 10


def test_paint_later_masks_win_and_ids_are_dense():
    a = np.zeros((4, 4), bool)
    a[:2] = True
    b = np.zeros((4, 4), bool)
    b[:3] = True  # covers a entirely: a disappears
    c = np.zeros((4, 4), bool)
    c[3, 3] = True
    labels, kept = paint([a, b, c], (4, 4))
    assert kept == [1, 2]
    assert labels[0, 0] == 0 and labels[3, 3] == 1 and labels[3, 0] == NO_SEGMENT


# ------------------------------------------------------------------ SAM --


@pytest.mark.skipif(not HAS_SAM, reason=NO_SAM)
@pytest.mark.parametrize(
    "order, radii", [("index", (4.0, 9.0, 16.0)), ("area", (9.0, 16.0, 4.0))]
)
def test_sam_generator_levels_with_disk_predictions(monkeypatch, order, radii):
    """The generator loop on a predictor that answers each point with three disks:
    by index, output k is level k; by area (SAM 2.1's default), the smallest
    disk is s and the largest l whatever output slot each comes in."""
    from ptovs.segment.sam import SamSegmenter, tiny_sam

    seg = SamSegmenter(
        model=tiny_sam(),
        points_per_side=4,
        crop_n_layers=1,
        min_mask_region_area=4,
        level_order=order,
    )

    def predict_torch(points, labels, multimask_output=True, return_logits=True):
        h, w = seg.predictor.original_size
        scale = seg.predictor.transform.target_length / max(h, w)
        p = points[:, 0, :] / scale  # back to crop pixels
        yy, xx = torch.meshgrid(
            torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij"
        )
        d = torch.sqrt(
            (xx[None] - p[:, 0, None, None]) ** 2
            + (yy[None] - p[:, 1, None, None]) ** 2
        )
        logits = torch.stack([(r - d) * 4 for r in radii], 1)
        iou = torch.full((len(p), 3), 0.95)
        return logits, iou, None

    monkeypatch.setattr(seg.predictor, "predict_torch", predict_torch)
    img = _blocks(64, 64)
    levels = seg.segment(img)
    assert len(levels) == 3
    areas = []
    for lv in levels:
        assert lv.labels.shape == (64, 64) and lv.n > 0
        assert np.array_equal(np.unique(lv.labels[lv.labels >= 0]), np.arange(lv.n))
        assert len(lv.masks) == lv.n
        for k in range(lv.n):  # each visible id lies inside its crop mask
            assert lv.masks[k][lv.labels == k].all()
        areas.append(np.mean([m.sum() for m in lv.masks]))
    assert areas[0] < areas[1] < areas[2]  # subpart < part < whole
    want = sorted(radii) if order == "area" else radii
    smaller = 0.0
    for lv, r in zip(levels, want, strict=True):  # each level holds its own disks
        area = np.array([m.sum() for m in lv.masks])
        assert (area <= 1.05 * np.pi * r**2).all()  # clipped at the image's edge
        assert (area > 1.1 * np.pi * smaller**2).all()
        smaller = r


def test_order_by_area_sorts_each_prompt_and_keeps_pairs():
    from ptovs.segment.generator import order_by_area

    g = torch.Generator().manual_seed(0)
    logits = (
        torch.randn(5, 3, 6, 7, generator=g)
        + torch.tensor([0.5, -0.5, 0.0])[None, :, None, None]
    )
    iou = torch.rand(5, 3, generator=g)
    got, got_iou = order_by_area(logits, iou, 0.0)
    area = (got > 0).sum((-2, -1))
    assert (area[:, :-1] <= area[:, 1:]).all()
    for n in range(5):  # a permutation of the prompt's own outputs, iou alike
        for k in range(3):
            j = [torch.equal(got[n, k], logits[n, i]) for i in range(3)].index(True)
            assert got_iou[n, k] == iou[n, j]
    same = torch.stack([logits[0, 0] - 9, logits[0, 0], logits[0, 0] + 9])[None]
    out, _ = order_by_area(same, iou[:1], 0.0)
    assert out is same  # already in order: returned as is


@pytest.mark.skipif(not HAS_SAM, reason=NO_SAM)
def test_sam_tiny_random_model_runs(tmp_path):
    from ptovs.segment.sam import SamSegmenter, load_sam, tiny_sam

    model = tiny_sam()
    seg = SamSegmenter(
        model=model,
        points_per_side=4,
        crop_n_layers=0,
        pred_iou_thresh=-1e9,
        stability_score_thresh=0.0,
    )
    levels = seg.segment(_blocks(48, 64))
    assert [lv.labels.shape for lv in levels] == [(48, 64)] * 3
    for lv in levels:  # random weights: whatever comes out is consistent
        assert lv.labels.min() >= NO_SEGMENT and (
            lv.masks is None or len(lv.masks) == lv.n
        )
    with pytest.raises(FileNotFoundError, match="sam_checkpoint"):
        load_sam(tmp_path / "missing.pth")
    with pytest.raises(ValueError, match="sam_checkpoint"):
        get_segmenter("sam")


@pytest.fixture
def one_thread():
    """torch on one thread: the tiny SAM's ops are too small to share, and two
    threads waiting on each other on a busy machine made the test 20x slower."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.mark.skipif(not HAS_SAM, reason=NO_SAM)
@pytest.mark.parametrize("order", ["index", "area"])
def test_sam_generator_equals_segment_anythings(monkeypatch, order, one_thread):
    """Per level, our candidates are segment-anything's own
    `SamAutomaticMaskGenerator` run with that level's output (or all three for
    "default"), mask for mask and in order, on seeded random weights with crops,
    several batches and the small-region clean-up; and the painted levels are
    LangSplat's `masks_update` + `mask2segmap` of upstream's masks. Thresholds 0
    (upstream: filters off), so random weights give masks."""
    from ptovs.compat import import_backend
    from ptovs.segment.sam import SamSegmenter, tiny_sam

    amg_mod = import_backend("segment_anything.automatic_mask_generator")
    monkeypatch.setattr(amg_mod, "batched_nms", reference_batched_nms)
    model = tiny_sam(seed=1)
    radii = (5.0, 12.0, 25.0) if order == "index" else (12.0, 25.0, 5.0)

    def disks(predictor):
        def to_pixels(p):  # SAM's input frame (longest side 256) → crop pixels
            (h, w), (ih, iw) = predictor.original_size, predictor.input_size
            return p * torch.tensor([w / iw, h / ih])

        return add_disks(predictor.predict_torch, radii, to_pixels)

    opts = dict(
        points_per_side=4,
        points_per_batch=6,
        pred_iou_thresh=0.0,
        stability_score_thresh=0.0,
        crop_n_layers=1,
        min_mask_region_area=20,
    )
    levels = ("default", "s", "m", "l")
    seg = SamSegmenter(model=model, levels=levels, level_order=order, **opts)
    monkeypatch.setattr(seg.predictor, "predict_torch", disks(seg.predictor))
    img = _blocks(96, 128)
    ours = seg.candidates(img)
    painted = seg.segment(img)
    total = 0
    for level, lv in zip(levels, painted, strict=True):
        gen = amg_mod.SamAutomaticMaskGenerator(model, **opts)
        predict = one_output(
            disks(gen.predictor),
            (0, 1, 2) if level == "default" else (("s", "m", "l").index(level),),
            by_area=order == "area",
            threshold=model.mask_threshold,
        )
        monkeypatch.setattr(gen.predictor, "predict_torch", predict)
        anns = gen.generate(img)
        assert_same_masks(ours[level], anns)
        total += len(anns)
        labels, visible = langsplat_paint_anns(anns, img.shape[:2])
        assert np.array_equal(lv.labels, labels)
        assert len(lv.masks) == len(visible)
        assert all(np.array_equal(a, b) for a, b in zip(lv.masks, visible, strict=True))
    assert total > 20 and len(ours["default"]["masks"]) > len(ours["s"]["masks"])


# ------------------------------------ production settings against upstream --

UPSTREAM_OPTIONS = (
    "pred_iou_thresh",
    "stability_score_thresh",
    "stability_score_offset",
    "box_nms_thresh",
    "crop_n_layers",
    "crop_overlap_ratio",
    "crop_n_points_downscale_factor",
    "crop_nms_thresh",
    "min_mask_region_area",
)
"""`MaskGenerator`'s options that upstream's automatic mask generators share."""

FILTERS = (
    "predicted IoU",
    "stability",
    "crop edge",
    "box NMS",
    "crop NMS",
    "clean-up NMS",
)
"""The generator's steps that drop masks, in the order they run."""

NMS_SITES = {
    "box NMS": ("_process_crop", "_crop_masks"),
    "crop NMS": ("_generate_masks", "candidates"),
    "clean-up NMS": ("postprocess_small_regions", "_postprocess_small_regions"),
}
"""Each box NMS: the upstream generator's method that runs it, and ours."""


def production_options() -> dict:
    """The generator settings extract-features runs SAM and SAM 2.1 with (all
    but the prompt grid): `MaskGenerator`'s defaults, and the config's
    `sam_crop_n_layers`."""
    from ptovs.segment.generator import MaskGenerator
    from ptovs.stages.extract_features import Config

    params = inspect.signature(MaskGenerator.__init__).parameters
    opts = {name: params[name].default for name in UPSTREAM_OPTIONS}
    opts["crop_n_layers"] = Config().sam_crop_n_layers
    return opts


def shaped_outputs(
    predict, to_pixels, n: int, iou_thresh: float, stability_thresh: float
):
    """Upstream's batched predict (SAM's `predict_torch`, sam2's `_predict`)
    answering so that, at production settings, every one of `FILTERS` keeps some
    masks and drops others (random weights alone give predicted IoUs and
    stabilities that drop them all).

    For the prompt in cell (i, j) of the crop's n x n grid, output k, added to
    the model's logits (`to_pixels` as for `add_disks`):
    - a cone (1/4 logit a pixel) of radius 6 or 24 px around the prompt (outputs
      0 and 1), or of 32 px around the centre of the prompt's 2 x 2 block of
      cells (output 2, the whole: four prompts give one mask, box NMS keeps one);
      a mask of the whole image and one of a corner crop then coincide (crop
      NMS), and many reach an inner crop edge (the crop-edge filter);
    - ripples of +-0.5 logit on the crop's top 40 rows, which leave holes and
      islands there for the clean-up: a mask found in two crops can come out
      changed from one and unchanged from the other, and the clean-up's NMS,
      which prefers unchanged masks, then keeps another than crop NMS, which
      prefers the smaller crop;
    - on output 2 of cells with i + j odd, a 5 x 5 px island at the block's
      centre mirrored through the crop's: box NMS keeps that mask beside the
      block's plain one, and once the clean-up removes the island, its NMS drops
      the duplicate;
    - a predicted IoU of `iou_thresh` - 0.1, `iou_thresh` itself (dropped: the
      filter keeps IoU > threshold), + 0.1 or + 0.2, by (i + j + k) mod 4 (box
      NMS ranks by it);
    - logits x 1 where (i + 2j + k) mod 4 is 1, else x 40: the stability offset
      (1 logit) is then 4 px or 0.1 px of a cone, a stability of about
      ((r - 4) / (r + 4))^2, below 0.85, or about 1; but output 0 where
      (i + 2j) mod 4 is 1 is a 10 x 10 px square at the prompt, its first
      100 x `stability_thresh` pixels (row by row) at 2 logits and the rest at 0,
      in -5: a stability of exactly the threshold (kept: the filter keeps
      stability >= threshold).
    Patched into ours and upstream's alike: it tests the generator, not SAM.
    """

    def wrapped(points, labels, *args, **kwargs):
        logits, iou, low = predict(points, labels, *args, **kwargs)
        h, w = logits.shape[-2:]
        size = torch.tensor([w, h])
        xy = to_pixels(points[:, 0, :].float())  # [N, 2] crop pixels
        cell = (xy / size * n).floor()
        block = (cell // 2 * 2 + 1) / n * size  # centre of the 2 x 2 block
        i, j = cell.long().unbind(1)
        centres = torch.stack([xy, xy, block], 1)  # [N, 3, 2]
        yy, xx = torch.meshgrid(
            torch.arange(h) + 0.5, torch.arange(w) + 0.5, indexing="ij"
        )
        d = torch.hypot(
            xx - centres[..., 0, None, None], yy - centres[..., 1, None, None]
        )
        cones = (torch.tensor([6.0, 24.0, 32.0])[:, None, None] - d) * 0.25
        ripple = 0.5 * torch.sin(1.3 * xx) * torch.sin(1.7 * yy) * (yy < 40)
        far = size - block  # [N, 2]
        island = ((xx - far[:, 0, None, None]).abs() < 2.5) & (
            (yy - far[:, 1, None, None]).abs() < 2.5
        )
        island &= ((i + j) % 2 == 1)[:, None, None]
        cones[:, 2] = torch.where(island, 2.0, cones[:, 2])
        k = torch.arange(3)
        gain = torch.where(((i + 2 * j)[:, None] + k) % 4 == 1, 1.0, 40.0)
        logits = (logits + cones.to(logits.dtype) + ripple) * gain[..., None, None]
        rows = torch.arange(h)[:, None] - xy[:, 1, None, None].floor() + 5
        cols = torch.arange(w) - xy[:, 0, None, None].floor() + 5
        inside = (rows >= 0) & (rows < 10) & (cols >= 0) & (cols < 10)
        core = rows * 10 + cols < round(100 * stability_thresh)
        square = torch.where(inside, torch.where(core, 2.0, 0.0), -5.0)
        exact = ((i + 2 * j) % 4 == 1)[:, None, None]
        logits[:, 0] = torch.where(exact, square.to(logits.dtype), logits[:, 0])
        ious = [iou_thresh - 0.1, iou_thresh, iou_thresh + 0.1, iou_thresh + 0.2]
        iou = torch.tensor(ious, dtype=iou.dtype)[((i + j)[:, None] + k) % 4]
        return logits, iou, low

    return wrapped


def count_filters(monkeypatch, module):
    """Count the masks that enter and that pass each of `FILTERS` in upstream's
    generator `module` (segment_anything's or sam2's automatic_mask_generator,
    its NMS `reference_batched_nms`), and the masks its clean-up changes.

    Returns:
        the counter ({(filter, "in" or "kept"): n, "changed": n}) and a wrapper
        for upstream's predict that counts the masks entering the first filter.
    """
    counts: Counter = Counter()
    sites = {theirs: name for name, (theirs, _) in NMS_SITES.items()}
    stability, near, regions = (
        module.calculate_stability_score,
        module.is_box_near_crop_edge,
        module.remove_small_regions,
    )

    def calculate_stability_score(masks, *args):
        counts["predicted IoU", "kept"] += len(masks)
        counts["stability", "in"] += len(masks)
        return stability(masks, *args)

    def is_box_near_crop_edge(boxes, *args):
        out = near(boxes, *args)
        counts["stability", "kept"] += len(boxes)
        counts["crop edge", "in"] += len(boxes)
        counts["crop edge", "kept"] += int((~out).sum())
        return out

    def batched_nms(boxes, *args, **kwargs):
        keep = reference_batched_nms(boxes, *args, **kwargs)
        name = sites[sys._getframe(1).f_code.co_name]
        counts[name, "in"] += len(boxes)
        counts[name, "kept"] += len(keep)
        return keep

    def remove_small_regions(mask, *args, **kwargs):
        out, changed = regions(mask, *args, **kwargs)
        counts["changed"] += changed
        return out, changed

    for fn in (
        calculate_stability_score,
        is_box_near_crop_edge,
        batched_nms,
        remove_small_regions,
    ):
        monkeypatch.setattr(module, fn.__name__, fn)

    def counted(predict):
        def wrapped(*args, **kwargs):
            out = predict(*args, **kwargs)
            counts["predicted IoU", "in"] += out[1].numel()
            return out

        return wrapped

    return counts, counted


def assert_every_filter_worked(counts: Counter) -> None:
    """Each of `FILTERS` kept some masks and dropped others; the clean-up changed
    some masks."""
    for name in FILTERS:
        assert 0 < counts[name, "kept"] < counts[name, "in"], (name, dict(counts))
    assert counts["changed"] > 0, dict(counts)


def same_masks(ours: dict, theirs: dict) -> bool:
    """Whether our candidates ({level: ...}) are upstream's annotations
    ({level: [ann, ...]}), as `assert_same_masks` decides."""
    try:
        for level, anns in theirs.items():
            assert_same_masks(ours[level], anns)
    except AssertionError:
        return False
    return True


def assert_controls_fail(monkeypatch, seg, img: np.ndarray, theirs: dict) -> None:
    """Negative controls: one step of ours changed at a time, our candidates of
    `img` are no longer upstream's `theirs` (the comparison can fail).

    Switched off: the predicted-IoU, stability and crop-edge filters, crop NMS,
    the clean-up's NMS, the crop layer, the clean-up. Moved: the IoU threshold
    down by 1e-6 (masks predicted at the threshold pass), the stability
    threshold up by 1e-6 (masks at the threshold go) and box NMS's down by 0.3.
    Box NMS switched off changes nothing here: crop NMS then removes the same
    masks, at the same threshold and in the order box NMS leaves them (sorted by
    predicted IoU either way); only a chain across crops would tell (a corner
    crop's mask removing one of the whole image's that would have removed
    another), and these outputs form none.
    """
    from ptovs.segment import generator

    def attrs(**changes):
        return lambda m: [m.setattr(seg, k, v) for k, v in changes.items()]

    def nms_off(ours_site):
        def no_nms_there(boxes, scores, iou_thr):
            site = sys._getframe(1).f_code.co_name
            return box_nms(boxes, scores, 1.0 if site == ours_site else iou_thr)

        return lambda m: m.setattr(generator, "box_nms", no_nms_there)

    def never_near(boxes, *args):
        return torch.zeros(len(boxes), dtype=torch.bool)

    controls = {
        "predicted IoU off": attrs(pred_iou_thresh=0.0),
        "predicted IoU threshold - 1e-6": attrs(
            pred_iou_thresh=seg.pred_iou_thresh - 1e-6
        ),
        "stability off": attrs(stability_score_thresh=0.0),
        "stability threshold + 1e-6": attrs(
            stability_score_thresh=seg.stability_score_thresh + 1e-6
        ),
        "crop edge off": lambda m: m.setattr(
            seg.amg, "is_box_near_crop_edge", never_near
        ),
        "box NMS threshold - 0.3": attrs(box_nms_thresh=seg.box_nms_thresh - 0.3),
        "crop NMS off": nms_off(NMS_SITES["crop NMS"][1]),
        "clean-up NMS off": nms_off(NMS_SITES["clean-up NMS"][1]),
        "no crop layer": attrs(crop_n_layers=0),
        "no clean-up": attrs(min_mask_region_area=0),
    }
    still_equal = []
    for name, apply in controls.items():
        with monkeypatch.context() as m:
            apply(m)
            if same_masks(seg.candidates(img), theirs):
                still_equal.append(name)
    assert not still_equal, f"ours still equals upstream's with {still_equal}"


@pytest.mark.skipif(not HAS_SAM, reason=NO_SAM)
def test_sam_generator_equals_segment_anythings_at_production_settings(
    monkeypatch, one_thread
):
    """At the settings extract-features runs (`production_options`, read from the
    code: predicted IoU > 0.7, stability >= 0.85, one crop layer, box and crop NMS
    0.7, holes and islands under 100 px), levels by index as for SAM: per level,
    our candidates are `SamAutomaticMaskGenerator`'s (NMS: torchvision's
    `batched_nms` as `reference_batched_nms`), mask for mask and in order, and the
    painted levels LangSplat's. The predictor's outputs are shaped
    (`shaped_outputs`) so that each filter keeps some masks and drops others,
    counted in upstream's run; and each negative control (`assert_controls_fail`:
    a step of ours off or its threshold moved) breaks the equality."""
    from ptovs.compat import import_backend
    from ptovs.segment.sam import SamSegmenter, tiny_sam

    amg_mod = import_backend("segment_anything.automatic_mask_generator")
    counts, counted = count_filters(monkeypatch, amg_mod)
    opts = production_options()
    grid = dict(points_per_side=4, points_per_batch=6)
    model = tiny_sam(seed=1)

    def shaped(predictor):
        def to_pixels(p):  # SAM's input frame (longest side 256) -> crop pixels
            (h, w), (ih, iw) = predictor.original_size, predictor.input_size
            return p * torch.tensor([w / iw, h / ih])

        predict = predictor.predict_torch
        thresholds = opts["pred_iou_thresh"], opts["stability_score_thresh"]
        return shaped_outputs(predict, to_pixels, 4, *thresholds)

    levels = ("default", "s", "m", "l")
    # as extract-features builds it: every other option at its default
    seg = SamSegmenter(
        model=model, levels=levels, crop_n_layers=opts["crop_n_layers"], **grid
    )
    assert seg.level_order == "index"
    monkeypatch.setattr(seg.predictor, "predict_torch", shaped(seg.predictor))
    img = _blocks(96, 128)
    ours = seg.candidates(img)
    painted = seg.segment(img)
    theirs = {}
    for level, lv in zip(levels, painted, strict=True):
        gen = amg_mod.SamAutomaticMaskGenerator(model, **grid, **opts)
        outputs = (0, 1, 2) if level == "default" else ("sml".index(level),)
        predict = one_output(shaped(gen.predictor), outputs, False, 0.0)
        monkeypatch.setattr(gen.predictor, "predict_torch", counted(predict))
        anns = theirs[level] = gen.generate(img)
        assert_same_masks(ours[level], anns)
        labels, visible = langsplat_paint_anns(anns, img.shape[:2])
        assert np.array_equal(lv.labels, labels)
        assert len(lv.masks) == len(visible)
    assert all(theirs.values())
    assert_every_filter_worked(counts)
    assert_controls_fail(monkeypatch, seg, img, theirs)


@pytest.mark.skipif(not HAS_SAM, reason=NO_SAM)
def test_sam_finding_nothing_gives_empty_levels():
    """LangSplat's thresholds on random weights keep no mask: every level is all
    NO_SEGMENT with n == 0 (how extract-features counts an empty view)."""
    from ptovs.segment.sam import SamSegmenter, tiny_sam

    seg = SamSegmenter(model=tiny_sam(seed=1), points_per_side=4, crop_n_layers=0)
    levels = seg.segment(_blocks(48, 64))
    assert [lv.n for lv in levels] == [0, 0, 0]
    assert all((lv.labels == NO_SEGMENT).all() and lv.masks == [] for lv in levels)


@pytest.mark.skipif(not HAS_SAM, reason=NO_SAM)
def test_sam_adapter_equals_sam_predictor():
    """Our batched point path answers as segment-anything's own
    `SamPredictor.predict`, point by point, on the same random weights."""
    from ptovs.compat import import_backend
    from ptovs.segment.sam import SamPoints, tiny_sam

    model = tiny_sam(seed=3)
    theirs = import_backend("segment_anything").SamPredictor(model)
    ours = SamPoints(theirs)  # one encoder pass serves both
    assert_points_match(ours, theirs, _blocks(40, 56))


# ------------------------------------------------------------- OpenCLIP --


@pytest.mark.skipif(not HAS_CLIP, reason=NO_CLIP)
def test_openclip_tiny_shapes_units_and_checkpoint(tmp_path):
    from ptovs.encoders.openclip import OpenClipEncoder, register_tiny

    name = register_tiny()
    enc = OpenClipEncoder(name, random_weights=True, batch_size=3)
    crops = np.random.default_rng(0).random((7, 224, 224, 3)).astype(np.float32)
    f = enc.encode_images(crops)
    assert f.shape == (7, 64) and f.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(f, axis=1), 1, atol=1e-5)
    np.testing.assert_allclose(
        enc.encode_images(crops[:2]), f[:2], atol=1e-5
    )  # batch-free
    t = enc.encode_texts(["Rose Window", "object"])
    assert t.shape == (2, 64)
    np.testing.assert_allclose(np.linalg.norm(t, axis=1), 1, atol=1e-5)
    # a saved state dict loads back (weights_only) and gives the same features
    ckpt = tmp_path / "tiny.pt"
    torch.save(enc.net.state_dict(), ckpt)
    enc2 = get_encoder("openclip", model=name, checkpoint=ckpt)
    np.testing.assert_allclose(enc2.encode_images(crops[:2]), f[:2], atol=1e-5)
    with pytest.raises(FileNotFoundError, match="clip_checkpoint"):
        get_encoder("openclip", model=name, checkpoint=tmp_path / "nope.pt")
    with pytest.raises(ValueError, match="clip_checkpoint"):
        get_encoder("openclip", model=name)


@pytest.mark.skipif(not HAS_CLIP, reason=NO_CLIP)
def test_extract_features_with_openclip_backend():
    from ptovs.encoders.openclip import OpenClipEncoder, register_tiny
    from ptovs.stages.extract_features import image_features

    enc = OpenClipEncoder(register_tiny(), random_weights=True)
    f = image_features(_blocks(), get_segmenter("graph"), enc, batch_size=4)
    f.validate()
    assert f.table.shape[1] == 64 and f.seg.shape == (3, 96, 128)
