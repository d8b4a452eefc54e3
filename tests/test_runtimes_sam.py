"""SAM's and SAM 2.1's image encoders under each runtime (`runtime` of the SAM
segmenters): the encoder outputs are PyTorch's within the runtimes' bar, the
segmenter's masks are PyTorch's, "auto" decides on the first image and reports
why, and a runtime whose encoder drifts is refused. Tiny SAM (random, 256 px) and
a random SAM 2.1 hiera-tiny (1024 px, the predictor's only size); exports go to
the session's runtime cache (conftest)."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import torch

from ptovs.compat import available
from ptovs.encoders import runtimes
from ptovs.encoders.runtimes import choose as choosing
from ptovs.encoders.runtimes import export, ort, ov
from ptovs.encoders.runtimes.tower import Tower
from test_segment import HAS_SAM, NO_SAM, _blocks, one_thread  # noqa: F401 - a fixture

HAS_SAM2 = available("sam2")
if HAS_SAM2:
    from test_sam2 import _image, tiny_ckpt  # noqa: F401 - a fixture

pytestmark = pytest.mark.usefixtures("one_thread")  # tiny networks: one thread

NAMED = ["onnxruntime", "openvino"]
FILTERS_OFF = dict(
    crop_n_layers=0,
    pred_iou_thresh=-1e9,
    stability_score_thresh=0.0,
    min_mask_region_area=0,
)
"""Random weights: every grid point's masks are kept (upstream's filters off)."""


def _sam(runtime: str = "torch", seed: int = 0):
    from ptovs.segment.sam import SamSegmenter, tiny_sam

    return SamSegmenter(model=tiny_sam(seed=seed), runtime=runtime,
                        points_per_side=8, **FILTERS_OFF)  # fmt: skip


def _sam2(ckpt, runtime: str = "torch"):
    from ptovs.segment.sam2 import Sam2Segmenter

    return Sam2Segmenter(ckpt, "tiny", runtime=runtime, points_per_side=4,
                         **FILTERS_OFF)  # fmt: skip


def _encoded(seg, image: np.ndarray) -> list[torch.Tensor]:
    """The encoder's outputs on `image` as the predictor computed them: SAM's
    embedding, SAM 2.1's image embedding and high-resolution features."""
    seg.points.set_image(image)
    pred = seg.predictor
    if seg.name == "sam":
        return [pred.features.clone()]
    feats = pred._features
    return [feats["image_embed"].clone(), *(f.clone() for f in feats["high_res_feats"])]


def _logits(seg, image: np.ndarray) -> torch.Tensor:
    """The three multimask logits of every grid point, at the image's size."""
    h, w = image.shape[:2]
    seg.points.set_image(image)
    logits, _ = seg.points.predict(seg.point_grids[0] * np.array([[w, h]]))
    seg.points.reset()
    return logits


def _borderline(ref: torch.Tensor, thr: float) -> torch.Tensor:
    """Pixels [N, 3, h, w] where PyTorch's own logit is within the runtimes' bar
    (1e-4 of the largest) of the mask threshold."""
    return (ref - thr).abs() <= choosing.MAX_ABS_DIFF * ref.abs().max()


def _assert_same_masks(ref_seg, seg, image: np.ndarray) -> None:
    """The segmenter's masks under a runtime are PyTorch's: every grid point's three
    masks, and each level of `segment`.

    Exactly, but for borderline pixels: encoder outputs 1e-6 apart (relative)
    move the decoder's logits by ~1e-7, which flips a pixel whose logit lies
    that close to the threshold (tiny SAM on seed 1: one of 589,824 mask pixels,
    its PyTorch logit 1.4e-8 from it, in both runtimes). So the masks must be
    the same wherever PyTorch's logit is farther than 1e-4 of the largest from
    the threshold, and the painted levels wherever no mask flipped (everywhere,
    where none did)."""
    thr = ref_seg.points.mask_threshold
    ref, got = _logits(ref_seg, image), _logits(seg, image)
    assert (got - ref).abs().max() <= choosing.MAX_ABS_DIFF * ref.abs().max()
    flips = (ref > thr) != (got > thr)
    assert not flips[~_borderline(ref, thr)].any()
    assert flips.float().mean() < 1e-4  # and they are rare
    flipped = flips.any(0).any(0).numpy()  # [h, w]
    for a, b in zip(ref_seg.segment(image), seg.segment(image), strict=True):
        assert a.labels.shape == b.labels.shape
        assert np.array_equal(a.labels[~flipped], b.labels[~flipped])


def _relative(got: list[torch.Tensor], ref: list[torch.Tensor]) -> float:
    return choosing.relative_diff([g.numpy() for g in got], [r.numpy() for r in ref])


# ---------------------------------------------------------------- SAM --


@pytest.mark.skipif(not HAS_SAM, reason=NO_SAM)
@pytest.mark.parametrize("name", NAMED)
def test_sam_encoder_in_each_runtime_gives_pytorchs_outputs_and_masks(name):
    image = _blocks(48, 64)
    ref_seg, seg = _sam(), _sam(name)
    assert ref_seg.runtime_report is None and seg.runtime_report is None
    ref, got = _encoded(ref_seg, image), _encoded(seg, image)
    assert seg.runtime == name and ref_seg.runtime == "torch"
    assert seg.runtime_report == {"runtime": name, "reason": "asked for"}
    assert got[0].shape == ref[0].shape == (1, 32, 16, 16)  # tiny SAM: [B, 32, 16, 16]
    assert _relative(got, ref) <= 1e-5  # well within the bar (1e-4): ~1e-6
    _assert_same_masks(ref_seg, seg, image)
    # a model given is keyed by its encoder's tensors, the export kept in the
    # session's cache: the same weights find it, other weights do not
    key = seg.encoder_runtime.tower._key()
    assert key["weights"] == runtimes.tensors_digest(
        seg.model.image_encoder.state_dict()
    )
    assert (runtimes.cache_dir() / "onnx" / f"{export.export_key(key)}.onnx").is_file()
    other = _sam(seed=1).encoder_runtime.tower._key()
    assert other["weights"] != key["weights"]
    assert export.export_key(other) != export.export_key(key)
    # the encoder stays in the model: the state dict is segment_anything's
    from ptovs.segment.sam import tiny_sam

    assert seg.model.state_dict().keys() == tiny_sam().state_dict().keys()


def _slower_torch(monkeypatch) -> None:
    """PyTorch in the check made 2.5x slower and 20 ms more: whether a runtime is
    kept then turns on its agreement, not on its speed on a busy machine."""
    real = Tower.torch_forward

    def slower(self, x):
        t0 = time.perf_counter()
        y = real(self, x)
        time.sleep(0.02 + 1.5 * (time.perf_counter() - t0))
        return y

    monkeypatch.setattr(Tower, "torch_forward", slower)


@pytest.mark.skipif(not HAS_SAM, reason=NO_SAM)
def test_auto_decides_once_on_the_first_image_and_reports_why(monkeypatch):
    """Runtime "auto" keeps a runtime that agrees with PyTorch (PyTorch made
    slower), decided on the first image only, and says so in a JSON report."""
    _slower_torch(monkeypatch)
    seg = _sam("auto")
    assert seg.runtime_report is None and seg.runtime == "torch"
    image = _blocks(48, 64)
    levels = seg.segment(image)
    report = seg.runtime_report
    json.dumps(report)
    assert report["runtime"] in NAMED and seg.runtime == report["runtime"]
    assert report["crops"] == 1 and "1 image" in report["reason"]
    assert set(report["max_abs_diff"]) == set(NAMED)
    assert max(report["max_abs_diff"].values()) <= choosing.MAX_ABS_DIFF
    assert "sample" in report["seconds"]["torch"]
    # decided once: the next image is not measured again
    monkeypatch.setattr(Tower, "check", lambda *a, **k: pytest.fail("measured again"))
    seg.segment(_blocks(40, 40))
    assert seg.runtime_report is report
    # and the masks are PyTorch's
    assert [lv.labels.shape for lv in levels] == [image.shape[:2]] * 3
    _assert_same_masks(_sam(), seg, image)


@pytest.mark.skipif(not HAS_SAM, reason=NO_SAM)
def test_extract_features_keeps_the_segmenters_runtime_for_a_resumed_run(
    tmp_path, monkeypatch
):
    """extract-features gives its runtime to the SAM segmenters, keeps the
    segmenter's decision in the partial artifact's notes after its first image,
    and a resumed run's segmenter runs that runtime without measuring again."""
    from ptovs.artifacts import Notes
    from ptovs.segment import backend as segb
    from ptovs.segment import sam as sam_module
    from ptovs.stages import extract_features as ef

    got = {}
    with monkeypatch.context() as m:
        m.setattr(sam_module, "SamSegmenter", lambda **kw: got.update(kw))
        ef.build_segmenter(ef.Config(segmenter="sam", runtime="openvino"))
    assert got["runtime"] == "openvino"

    _slower_torch(monkeypatch)
    notes = Notes(tmp_path / "notes", "key")
    first = _sam("auto")
    segb.restore_segmenter_runtime(first, notes)  # nothing kept yet: decides itself
    segb.note_segmenter_runtime(first, notes)  # nothing decided yet: nothing kept
    assert notes.get("segmenter_runtime") is None
    first.segment(_blocks(48, 64))
    segb.note_segmenter_runtime(first, notes)
    kept = notes.get("segmenter_runtime")
    assert kept["runtime"] in NAMED and kept["runtime"] == first.runtime

    monkeypatch.setattr(Tower, "check", lambda *a, **k: pytest.fail("measured again"))
    resumed = _sam("auto")
    segb.restore_segmenter_runtime(resumed, Notes(tmp_path / "notes", "key"))
    assert resumed.runtime == kept["runtime"] and resumed.runtime_report == kept
    levels = resumed.segment(_blocks(48, 64))
    assert [lv.labels.shape for lv in levels] == [(48, 64)] * 3
    # a segmenter without a runtime (hier, graph) is left as it is
    hier = ef.build_segmenter(ef.Config(segmenter="hier"))
    segb.restore_segmenter_runtime(hier, Notes(tmp_path / "notes", "key"))
    segb.note_segmenter_runtime(hier, Notes(tmp_path / "other", "key2"))
    assert Notes(tmp_path / "other", "key2").get("segmenter_runtime") is None


def _drifting(monkeypatch, shift: float = 1e-2) -> None:
    """Every exported runtime's encoder output off by `shift` (the negative
    control): one array or each of a list."""
    for cls in (ort.OnnxRuntime, ov.OpenVino):
        real = cls.load

        def load(self, module, example, key, threads, real=real):
            run = real(self, module, example, key, threads)

            def off(x):
                y = run(x)
                if isinstance(y, list):
                    return [a + np.float32(shift) for a in y]
                return y + np.float32(shift)

            return off

        monkeypatch.setattr(cls, "load", load)


@pytest.mark.skipif(not HAS_SAM, reason=NO_SAM)
def test_auto_refuses_a_runtime_whose_encoder_drifts(monkeypatch):
    """The same check with each runtime's output off by 1e-2 (relative ~1e-3):
    faster, but refused; PyTorch is kept and the report says why."""
    _slower_torch(monkeypatch)
    _drifting(monkeypatch)
    seg = _sam("auto")
    seg.points.set_image(_blocks(48, 64))
    report = seg.runtime_report
    assert report["runtime"] == "torch" and seg.runtime == "torch"
    assert set(report["max_abs_diff"]) == set(NAMED)
    assert min(report["max_abs_diff"].values()) > choosing.MAX_ABS_DIFF
    assert "agreed" in report["reason"] and "max |PyTorch|" in report["reason"]
    # named, the drift would be used: the control is real
    seg2 = _sam("onnxruntime")
    ref = _encoded(_sam(), _blocks(48, 64))
    assert _relative(_encoded(seg2, _blocks(48, 64)), ref) > choosing.MAX_ABS_DIFF


def test_relative_difference_takes_the_worst_output():
    a = np.array([[1.0, -4.0]], np.float32)
    b = np.array([[0.01, 0.02]], np.float32)
    assert choosing.relative_diff(a + 4e-4, a) == pytest.approx(1e-4, rel=1e-3)
    assert choosing.relative_diff([a, b + 1e-4], [a, b]) == pytest.approx(
        5e-3, rel=1e-3
    )
    # the default (unit features) is unchanged: rows normalised first
    assert choosing.unit_diff(a * 3, a) < 1e-7


class _Two(torch.nn.Module):
    """Two outputs, as SAM 2.1's encoder flattened (at a few kB)."""

    def __init__(self):
        super().__init__()
        self.conv = torch.nn.Conv2d(3, 4, 3, padding=1)

    def forward(self, x):
        y = self.conv(x)
        return y, torch.nn.functional.avg_pool2d(y, 2)


def test_a_module_with_several_outputs_runs_in_every_runtime():
    """A tuple-returning module (SAM 2.1's shape of output) exports "y0".."yk" and
    every runtime answers a list in that order; a one-output module still answers
    one array."""
    torch.manual_seed(0)
    module = _Two().eval()
    x = torch.rand(2, 3, 8, 8)
    key = {
        "net": "two outputs",
        "weights": runtimes.tensors_digest(module.state_dict()),
    }
    tower = Tower(module, (3, 8, 8), lambda: key)
    ref = tower(x)
    assert isinstance(ref, tuple) and [r.shape for r in ref] == [(2, 4, 8, 8),
                                                                 (2, 4, 4, 4)]  # fmt: skip
    assert export.output_names(module, x[:1]) == ["y0", "y1"]
    for name in runtimes.installed():
        tower.use(name)
        got = tower(x)
        assert isinstance(got, tuple) and len(got) == 2
        for g, r in zip(got, ref, strict=True):
            assert g.shape == r.shape and (g - r).abs().max() < 1e-5
    one = Tower(module.conv, (3, 8, 8), lambda: {**key, "net": "one output"})
    for name in NAMED:
        one.use(name)
        assert isinstance(one(x), torch.Tensor)
        run = one._loaded[name]
        assert isinstance(run(x.numpy()), np.ndarray)


@pytest.mark.parametrize("drift", [0.0, 1e-2])
def test_auto_compares_every_output_of_a_module_with_several(drift, monkeypatch):
    """Runtime "auto" on a tuple-returning module (SAM 2.1's encoder's path, at a
    few kB: its 1024 px check costs minutes on a CPU) measures each output
    against PyTorch's: a runtime that agrees is kept, one off by `drift` on
    every output is refused (PyTorch made slower: agreement decides)."""
    torch.manual_seed(0)
    module = _Two().eval()
    key = {"net": "two outputs, auto",
           "weights": runtimes.tensors_digest(module.state_dict())}  # fmt: skip
    _slower_torch(monkeypatch)
    if drift:
        _drifting(monkeypatch, drift)
    tower = Tower(module, (3, 8, 8), lambda: key, "cpu", "auto")
    report = tower.check(torch.rand(3, 3, 8, 8), compare=choosing.relative_diff,
                         unit="images")  # fmt: skip
    json.dumps(report)
    assert set(report["max_abs_diff"]) == set(NAMED)
    if drift:
        assert report["runtime"] == "torch" and "agreed" in report["reason"]
        assert min(report["max_abs_diff"].values()) > choosing.MAX_ABS_DIFF
    else:
        assert report["runtime"] in NAMED and "3 images" in report["reason"]
        assert max(report["max_abs_diff"].values()) < 1e-6
        assert isinstance(tower(torch.rand(2, 3, 8, 8)), tuple)


def test_an_export_over_2gb_keeps_its_tensors_in_one_file_of_its_own(monkeypatch):
    """Over 2 GB (SAM's ViT-H) the exporter writes each tensor beside the model,
    in a file named by the tensor: faked here with a tiny graph saved that way.
    Each export's tensors end in one data file of its own (two exports of
    tensors with the same names do not overwrite each other), and both run."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    def fake_export(module, args, f, **kwargs):
        # w over 1 kB: kept outside the model by onnx, as the exporter's are
        w = module.scale.detach().numpy().reshape(1, 3, 1, 1) * np.ones((16, 16))
        graph = helper.make_graph(
            [helper.make_node("Mul", ["x", "w"], ["y"])], "g",
            [helper.make_tensor_value_info("x", TensorProto.FLOAT, ["b", 3, 16, 16])],
            [helper.make_tensor_value_info("y", TensorProto.FLOAT, ["b", 3, 16, 16])],
            [numpy_helper.from_array(w.astype(np.float32), "w")],
        )  # fmt: skip
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
        onnx.save_model(model, f, save_as_external_data=True,
                        all_tensors_to_one_file=False, size_threshold=0)  # fmt: skip

    class Scale(torch.nn.Module):
        def __init__(self, s):
            super().__init__()
            self.scale = torch.nn.Parameter(torch.tensor(s))

        def forward(self, x):
            return x * self.scale.view(1, 3, 1, 1)

    monkeypatch.setattr(torch.onnx, "export", fake_export)
    x = np.ones((2, 3, 16, 16), np.float32)
    paths = []
    for s in ([1.0, 2.0, 3.0], [5.0, 6.0, 7.0]):
        key = {"net": "over 2 GB", "scale": s}
        paths.append(export.onnx_file(Scale(s), torch.zeros(1, 3, 16, 16), key))
    folder = paths[0].parent
    for path, s in zip(paths, ([1.0, 2.0, 3.0], [5.0, 6.0, 7.0]), strict=True):
        (data,) = folder.glob(f"{path.stem}.*.data")
        model = onnx.load(str(path), load_external_data=False)
        (w,) = model.graph.initializer
        assert {e.key: e.value for e in w.external_data}["location"] == data.name
        run = runtimes.get_backend("onnxruntime").load(
            None, None, {"net": "over 2 GB", "scale": s}, 1
        )
        assert np.array_equal(run(x)[:, :, 0, 0], np.array([s, s], np.float32))
    assert not (folder / "w").exists() and not list(folder.glob(".*.tmp*"))


# ------------------------------------------------------------ SAM 2.1 --


@pytest.fixture(scope="module")
def sam2_torch(tiny_ckpt):
    """The reference: SAM 2.1 in PyTorch (one for every runtime's test)."""
    return _sam2(tiny_ckpt)


@pytest.mark.skipif(not HAS_SAM2, reason="extra [sam2] not installed")
@pytest.mark.parametrize("name", NAMED)
def test_sam2_encoder_in_each_runtime_gives_pytorchs_outputs_and_masks(
    name, tiny_ckpt, sam2_torch
):
    """Hiera exports (legacy exporter, opset 17); its dict output travels as a
    tuple and comes back whole: the predictor's features and the masks are
    PyTorch's. A checkpoint is keyed by its file's bytes."""
    image = _image(48, 64)
    ref_seg, seg = sam2_torch, _sam2(tiny_ckpt, name)
    ref, got = _encoded(ref_seg, image), _encoded(seg, image)
    assert seg.runtime == name
    assert [g.shape for g in got] == [r.shape for r in ref] == [
        (1, 256, 64, 64), (1, 32, 256, 256), (1, 64, 128, 128)]  # fmt: skip
    assert _relative(got, ref) <= 1e-5
    _assert_same_masks(ref_seg, seg, image)
    key = seg.encoder_runtime.tower._key()
    assert key["weights"] == runtimes.file_digest(tiny_ckpt)
    assert key["size"] == 1024 and key["model"] == "tiny"
