"""segmenter = "sam2": SAM 2.1 through the shared generator loop (extra [sam2]).

One randomly initialised (seeded) hiera-tiny, saved as sam2 saves its checkpoints
({"model": state_dict}), serves every test: the segmenter's levels are valid, our
point adapter answers exactly as sam2's own `SAM2ImagePredictor.predict` on the
same weights and image, our generator's masks are sam2's own
`SAM2AutomaticMaskGenerator`'s mask for mask (filters off, and at the settings
extract-features runs), and preflight refuses a missing file, a SAM 2.0
checkpoint and another model's checkpoint in one line, naming the fix, before
any stage runs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from conftest import (
    add_disks,
    assert_points_match,
    assert_same_masks,
    langsplat_paint_anns,
    one_output,
    reference_batched_nms,
)
from test_segment import (
    UPSTREAM_OPTIONS,
    assert_controls_fail,
    assert_every_filter_worked,
    count_filters,
    production_options,
    shaped_outputs,
)

pytest.importorskip("sam2")

from ptovs.cli import main as cli  # noqa: E402
from ptovs.errors import InputError, MissingInputError  # noqa: E402
from ptovs.preflight import check_extract_config  # noqa: E402
from ptovs.segment import NO_SEGMENT, get_segmenter  # noqa: E402
from ptovs.segment.sam2 import (  # noqa: E402
    SAM2_MODELS,
    SAM2_TRUNKS,
    Sam2Points,
    build_sam2_model,
)
from ptovs.stages.extract_features import Config, build_segmenter  # noqa: E402


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory: pytest.TempPathFactory) -> Path:
    torch.manual_seed(0)
    model = build_sam2_model("tiny")
    path = tmp_path_factory.mktemp("sam2") / "sam2.1_hiera_tiny_random.pt"
    torch.save({"model": model.state_dict()}, path)
    return path


def _image(h: int = 48, w: int = 64) -> np.ndarray:
    """Four flat blocks with a little noise (uint8 RGB)."""
    rng = np.random.default_rng(0)
    img = np.zeros((h, w, 3), np.uint8)
    img[: h // 2, : w // 2] = (200, 40, 40)
    img[: h // 2, w // 2 :] = (40, 200, 40)
    img[h // 2 :, : w // 2] = (40, 40, 200)
    img[h // 2 :, w // 2 :] = (220, 220, 60)
    noise = rng.integers(-10, 10, img.shape)
    return np.clip(img.astype(int) + noise, 0, 255).astype(np.uint8)


def test_sam2_segmenter_levels_are_valid(tiny_ckpt: Path) -> None:
    config = Config(
        segmenter="sam2",
        sam_checkpoint=str(tiny_ckpt),
        sam2_model="tiny",
        sam_points_per_side=4,
        sam_crop_n_layers=0,
    )
    seg = build_segmenter(config)
    assert seg.name == "sam2" and seg.levels == ("s", "m", "l")
    # random weights: SAM's IoU and stability filters would keep nothing
    seg.pred_iou_thresh = -1e9
    seg.stability_score_thresh = 0.0
    img = _image()
    levels = seg.segment(img)
    assert len(levels) == 3
    for lv in levels:
        assert lv.labels.shape == img.shape[:2] and lv.labels.dtype == np.int32
        assert lv.labels.min() >= NO_SEGMENT
        assert np.array_equal(np.unique(lv.labels[lv.labels >= 0]), np.arange(lv.n))
        assert len(lv.masks) == lv.n
        for k in range(lv.n):  # each painted id lies inside its own crop mask
            assert lv.masks[k].shape == img.shape[:2]
            assert lv.masks[k][lv.labels == k].all()
    assert sum(lv.n for lv in levels) > 0
    with pytest.raises(ValueError, match="choose from .*'tiny', 'small'"):
        get_segmenter("sam2", checkpoint=tiny_ckpt, model_type="hiera_t")
    with pytest.raises(ValueError, match="sam_checkpoint"):
        get_segmenter("sam2")


def test_adapter_equals_sam2_image_predictor(tiny_ckpt: Path) -> None:
    """Our loader gives the weights sam2's own builder loads from the checkpoint,
    and our batched point path answers as sam2's own `predict`, point by point."""
    from sam2.build_sam import build_sam2
    from sam2.sam2_image_predictor import SAM2ImagePredictor

    seg = get_segmenter("sam2", checkpoint=tiny_ckpt, points_per_side=4)
    model = build_sam2("configs/sam2.1/sam2.1_hiera_t.yaml", str(tiny_ckpt), "cpu")
    ours_sd, theirs_sd = seg.model.state_dict(), model.state_dict()
    assert ours_sd.keys() == theirs_sd.keys()
    assert all(torch.equal(ours_sd[k], v) for k, v in theirs_sd.items())
    theirs = SAM2ImagePredictor(model)
    ours = Sam2Points(theirs)  # one encoder pass serves both
    assert_points_match(ours, theirs, _image(40, 56))
    ours.reset()
    assert not theirs._is_image_set


def _memoise_encoder(predictor) -> None:
    """One encoder pass per distinct crop, for ours and upstream's generator."""
    keep = ("_features", "_orig_hw", "_is_image_set", "_is_batch")
    seen: dict = {}
    set_image = predictor.set_image

    def cached(image):
        key = (image.shape, image.tobytes())
        if key not in seen:
            set_image(image)
            seen[key] = {k: getattr(predictor, k) for k in keep}
        for k, v in seen[key].items():
            setattr(predictor, k, v)

    predictor.set_image = cached


def test_generator_equals_sam2s_automatic_mask_generator(
    tiny_ckpt: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Per level, our candidates are sam2's own `SAM2AutomaticMaskGenerator`'s
    masks when its predictor answers with that level's output (the three sorted
    by area, our SAM 2.1 default), mask for mask and in order, on seeded random
    weights over several batches: as sam2 runs it (no clean-up; "default", which
    pools the three outputs), and for every level with SAM-1's
    small-region clean-up from sam2's own `postprocess_small_regions` (LangSplat's
    recipe, what ptovs runs); the painted levels are LangSplat's of those masks.
    Thresholds 0 (upstream: filters off) and prompt-centred cones on the logits
    (conftest.add_disks), so random weights give masks of every size. No crop
    layer here (four more encoder passes); the test at production settings below
    has one. Random weights with LangSplat's thresholds find nothing: every level
    has n == 0."""
    from ptovs.compat import import_backend

    amg_gen = import_backend("sam2.automatic_mask_generator")
    from sam2.utils.amg import rle_to_mask

    monkeypatch.setattr(amg_gen, "batched_nms", reference_batched_nms)
    levels = ("default", "s", "m", "l")
    opts = dict(
        points_per_side=4,
        points_per_batch=8,
        pred_iou_thresh=0.0,
        stability_score_thresh=0.0,
        crop_n_layers=0,
    )
    seg = get_segmenter(
        "sam2", checkpoint=tiny_ckpt, levels=levels, min_mask_region_area=0, **opts
    )
    assert seg.level_order == "area"
    pred = seg.predictor
    _memoise_encoder(pred)
    radii = (12.0, 25.0, 5.0)  # output slots not in size order

    def to_pixels(p):  # sam2's normalised input frame → crop pixels
        h, w = pred._orig_hw[-1]
        return p / pred._transforms.resolution * torch.tensor([w, h])

    predict = pred._predict
    monkeypatch.setattr(pred, "_predict", add_disks(predict, radii, to_pixels))
    img = _image(96, 128)
    ours = {0: seg.candidates(img)}
    seg.min_mask_region_area = 20
    ours[20] = seg.candidates(img)
    painted = seg.segment(img)
    total = 0
    for i, level in enumerate(levels):
        gen = amg_gen.SAM2AutomaticMaskGenerator(seg.model, **opts)
        gen.predictor = pred  # the same predictor: no hole filling, one encoder pass
        outputs = (0, 1, 2) if level == "default" else (i - 1,)
        one = one_output(add_disks(predict, radii, to_pixels), outputs, True, 0.0)
        monkeypatch.setattr(pred, "_predict", one)
        if level == "default":  # sam2's own loop, as it runs it (all outputs)
            assert_same_masks(ours[0][level], gen.generate(img))
        data = gen._generate_masks(img)
        data = gen.postprocess_small_regions(data, 20, 0.7)  # SAM-1's step
        anns = [
            dict(segmentation=rle_to_mask(r), predicted_iou=p, stability_score=q)
            for r, p, q in zip(
                data["rles"], data["iou_preds"], data["stability_score"], strict=True
            )
        ]
        assert_same_masks(ours[20][level], anns)
        total += len(anns)
        labels, visible = langsplat_paint_anns(anns, img.shape[:2])
        assert np.array_equal(painted[i].labels, labels)
        assert len(painted[i].masks) == len(visible)
    assert total > 20
    # smallest to largest: s < m < l on average
    area = [float(ours[20][lv]["masks"].sum((1, 2)).float().mean()) for lv in "sml"]
    assert area[0] < area[1] < area[2]
    # nothing found is n == 0, not an error
    monkeypatch.setattr(pred, "_predict", predict)
    seg.pred_iou_thresh, seg.stability_score_thresh = 0.7, 0.85  # LangSplat's
    assert [lv.n for lv in seg.segment(img)] == [0, 0, 0, 0]


def _one_embedding(predictor) -> None:
    """Every image set gets the first one's embedding: one encoder pass serves
    ours and upstream's generator and every crop (the masks come from the shaped
    outputs; what is compared is the generator around the predictor)."""
    set_image = predictor.set_image
    first: dict = {}

    def shared(image):
        if not first:
            set_image(image)
            first["features"] = predictor._features
        predictor._features = first["features"]
        predictor._orig_hw = [image.shape[:2]]
        predictor._is_image_set, predictor._is_batch = True, False

    predictor.set_image = shared


def _memoised(predict, predictor):
    """`predict` (the predictor's `_predict`, shaped) run once for each prompt
    batch and crop size (one embedding for every crop: equal inputs, equal
    outputs)."""
    seen: dict = {}

    def cached(points, labels, *args, **kwargs):
        key = (tuple(predictor._orig_hw[-1]), points.cpu().numpy().tobytes())
        if key not in seen:
            seen[key] = predict(points, labels, *args, **kwargs)
        return tuple(t.clone() for t in seen[key])  # callers edit them in place

    return cached


def test_generator_equals_sam2s_at_production_settings(
    tiny_ckpt: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """At the settings extract-features runs SAM 2.1 with (`production_options`,
    read from the code: predicted IoU > 0.7, stability >= 0.85, one crop layer,
    box and crop NMS 0.7, holes and islands under 100 px; the three outputs
    sorted by area), built as extract-features builds it: per level, our
    candidates are sam2's own `SAM2AutomaticMaskGenerator`'s followed by its
    `postprocess_small_regions` (SAM-1's clean-up, which sam2's `generate` leaves
    out; NMS: torchvision's `batched_nms` as `reference_batched_nms`), mask for
    mask and in order, and the painted levels LangSplat's. The predictor's
    outputs are shaped (`shaped_outputs`) so that each filter keeps some masks
    and drops others, counted in upstream's run; each negative control (a step
    of ours off or its threshold moved) breaks the equality. One encoder pass
    serves every crop (`_one_embedding`), and each prompt batch is decoded once
    per crop size (`_memoised`)."""
    from sam2.utils.amg import rle_to_mask

    from ptovs.compat import import_backend

    amg_gen = import_backend("sam2.automatic_mask_generator")
    counts, counted = count_filters(monkeypatch, amg_gen)
    opts = production_options()
    levels = ("default", "s", "m", "l")
    config = Config(
        segmenter="sam2",
        sam_checkpoint=str(tiny_ckpt),
        sam_points_per_side=4,
        levels=levels,
    )
    seg = build_segmenter(config)
    stored = [k for k in UPSTREAM_OPTIONS if hasattr(seg, k)]
    assert {k: getattr(seg, k) for k in stored} == {k: opts[k] for k in stored}
    assert seg.level_order == "area" and opts["crop_n_layers"] > 0
    grid = dict(points_per_side=4, points_per_batch=8)
    seg.points_per_batch = grid["points_per_batch"]
    pred = seg.predictor
    _one_embedding(pred)

    def to_pixels(p):  # sam2's normalised input frame -> crop pixels
        h, w = pred._orig_hw[-1]
        return p / pred._transforms.resolution * torch.tensor([w, h])

    thresholds = opts["pred_iou_thresh"], opts["stability_score_thresh"]
    shaped = _memoised(shaped_outputs(pred._predict, to_pixels, 4, *thresholds), pred)
    monkeypatch.setattr(pred, "_predict", shaped)
    img = _image(96, 128)
    ours = seg.candidates(img)
    painted = seg.segment(img)
    theirs = {}
    for i, level in enumerate(levels):
        gen = amg_gen.SAM2AutomaticMaskGenerator(seg.model, **grid, **opts)
        gen.predictor = pred  # the same predictor: no hole filling
        outputs = (0, 1, 2) if level == "default" else (i - 1,)
        monkeypatch.setattr(
            pred, "_predict", counted(one_output(shaped, outputs, True, 0.0))
        )
        data = gen._generate_masks(img)
        data = gen.postprocess_small_regions(
            data,
            opts["min_mask_region_area"],
            max(opts["box_nms_thresh"], opts["crop_nms_thresh"]),
        )
        anns = theirs[level] = [
            dict(segmentation=rle_to_mask(r), predicted_iou=p, stability_score=q)
            for r, p, q in zip(
                data["rles"], data["iou_preds"], data["stability_score"], strict=True
            )
        ]
        assert_same_masks(ours[level], anns)
        labels, visible = langsplat_paint_anns(anns, img.shape[:2])
        assert np.array_equal(painted[i].labels, labels)
        assert len(painted[i].masks) == len(visible)
    assert all(theirs.values())
    assert_every_filter_worked(counts)
    monkeypatch.setattr(pred, "_predict", shaped)  # ours again
    assert_controls_fail(monkeypatch, seg, img, theirs)


def test_preflight_refuses_missing_and_other_models_checkpoints(
    tiny_ckpt: Path, tiny_scene_dir: Path, tmp_path: Path
) -> None:
    def check(**kw) -> None:
        check_extract_config(
            Config(segmenter="sam2", encoder="synthetic", **kw), synthetic=True
        )

    check(sam_checkpoint=str(tiny_ckpt))  # fits
    with pytest.raises(MissingInputError, match="none given"):
        check()
    with pytest.raises(MissingInputError, match="nope.pt"):
        check(sam_checkpoint=str(tmp_path / "nope.pt"))
    with pytest.raises(InputError, match=r"choose from \['tiny', 'small'"):
        check(sam_checkpoint=str(tiny_ckpt), sam2_model="hiera_t")
    # another size: tiny's tensors are a subset of small's (fewer blocks)
    with pytest.raises(
        InputError, match="is a SAM 2.1 tiny checkpoint, not small"
    ) as e:
        check(sam_checkpoint=str(tiny_ckpt), sam2_model="small")
    assert "set extract-features.sam2_model = 'tiny'" in str(e.value)
    assert str(tiny_ckpt) in str(e.value) and "\n" not in str(e.value)
    # SAM 2.0 (Meta's sam2_hiera_tiny.pt): 2.1 less three video-memory tensors
    from sam2.build_sam import build_sam2

    sam20 = build_sam2("configs/sam2/sam2_hiera_t.yaml", None, device="cpu")
    sam20_path = tmp_path / "sam2_hiera_tiny.pt"
    torch.save({"model": sam20.state_dict()}, sam20_path)
    for model, fix in [
        ("tiny", ""),
        ("small", " and set extract-features.sam2_model = 'tiny'"),
    ]:
        with pytest.raises(InputError, match="is a SAM 2.0 tiny checkpoint") as e:
            check(sam_checkpoint=str(sam20_path), sam2_model=model)
        msg = str(e.value)
        assert (
            msg.endswith(f"give Meta's sam2.1_hiera_tiny.pt{fix}") and "\n" not in msg
        )
        assert "no_obj_embed_spatial" in msg
    # a SAM 1 checkpoint (a bare state dict of segment_anything's names)
    try:
        from ptovs.segment.sam import tiny_sam

        sam1 = tiny_sam().state_dict()
    except ImportError:
        sam1 = {"image_encoder.patch_embed.proj.weight": torch.zeros(32, 3, 16, 16)}
    sam1_path = tmp_path / "sam_vit_b.pth"
    torch.save(sam1, sam1_path)
    with pytest.raises(InputError, match="not a SAM 2.1 tiny checkpoint") as e:
        check(sam_checkpoint=str(sam1_path))
    assert "\n" not in str(e.value)
    if "prompt_encoder.pe_layer.positional_encoding_gaussian_matrix" in sam1:
        assert "segmenter = 'sam' (this is a SAM 1 checkpoint)" in str(e.value)
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="could not be read"):
        check(sam_checkpoint=str(junk))
    # through the CLI: one line, nothing written, no traceback
    work = tmp_path / "work"
    r = CliRunner().invoke(
        cli,
        ["--work-dir", str(work), "extract-features", "--data", str(tiny_scene_dir),
         "--set", "segmenter=sam2", "--set", f"sam_checkpoint={sam1_path}"],
    )  # fmt: skip
    assert r.exit_code == 1 and str(sam1_path) in r.output, r.output
    assert "Traceback" not in r.output
    assert not work.exists()


def test_trunk_table_follows_sam2s_configs() -> None:
    """`SAM2_TRUNKS` (how preflight names a checkpoint's size) is what sam2's own
    configs build: Hiera's embed_dim and the sum of its stages (Hiera's defaults
    where a config leaves them out)."""
    import inspect

    import sam2
    import yaml
    from sam2.modeling.backbones.hieradet import Hiera

    default = inspect.signature(Hiera).parameters
    found = {}
    for name, cfg in SAM2_MODELS.items():
        text = (Path(sam2.__file__).parent / "configs" / "sam2.1" / cfg).read_text()
        trunk = yaml.safe_load(text)["model"]["image_encoder"]["trunk"]
        dim = trunk.get("embed_dim", default["embed_dim"].default)
        stages = trunk.get("stages", default["stages"].default)
        found[(dim, sum(stages))] = name
    assert found == SAM2_TRUNKS
