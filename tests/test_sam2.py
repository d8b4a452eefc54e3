"""segmenter = "sam2": SAM 2.1 through the shared generator loop (extra [sam2]).

One randomly initialised (seeded) hiera-tiny, saved as sam2 saves its checkpoints
({"model": state_dict}), serves every test: the segmenter's levels are valid, our
point adapter answers exactly as sam2's own `SAM2ImagePredictor.predict` on the
same weights and image, and preflight refuses a missing file and another model's
checkpoint in one line, before any stage runs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from click.testing import CliRunner

from conftest import assert_points_match

pytest.importorskip("sam2")

from ptovs.cli import main as cli  # noqa: E402
from ptovs.errors import InputError, MissingInputError  # noqa: E402
from ptovs.preflight import check_extract_config  # noqa: E402
from ptovs.segment import NO_SEGMENT, get_segmenter  # noqa: E402
from ptovs.segment.sam2 import Sam2Points, build_sam2_model  # noqa: E402
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
    with pytest.raises(InputError, match="not a SAM 2.1 small checkpoint") as e:
        check(sam_checkpoint=str(tiny_ckpt), sam2_model="small")
    assert str(tiny_ckpt) in str(e.value) and "\n" not in str(e.value)
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
