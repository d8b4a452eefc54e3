"""OpenCLIP through ptovs's wrapper is the model the upstream package would run:
the same preprocessing (per pretrained tag), the same weights, the same features;
reduced precision is kept only where it agrees with fp32 on the crops at hand."""

from __future__ import annotations

import importlib.util

import numpy as np
import pytest
import torch

pytestmark = pytest.mark.skipif(
    importlib.util.find_spec("open_clip") is None,
    reason="open_clip not installed (extra [clip])",
)


def _oc():
    from ptovs.compat import import_backend

    return import_backend("open_clip")


def _crops(n: int, size: int, seed: int = 0) -> np.ndarray:
    """LangSplat-like crops: a textured disc on black."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[:size, :size] / size
    out = np.zeros((n, size, size, 3), np.float32)
    for i in range(n):
        r = rng.uniform(0.2, 0.5)
        cx, cy = rng.uniform(0.3, 0.7, 2)
        m = (xx - cx) ** 2 + (yy - cy) ** 2 < r * r
        tex = rng.random((size, size, 3)) * 0.4
        out[i][m] = np.clip(rng.random(3) * 0.6 + tex[m], 0, 1)
    return np.rint(out * 255) / np.float32(255)  # as prepare_crop gives them


def _upstream(model: str, tag: str, ckpt, monkeypatch):
    """open_clip's own model + eval transform for `tag`, its weights from ckpt
    (the tag's table entry pointed at the file, as a download would be)."""
    oc = _oc()
    entry = dict(oc.pretrained._PRETRAINED[model][tag], file=str(ckpt))
    monkeypatch.setitem(oc.pretrained._PRETRAINED[model], tag, entry)
    net, _, pre = oc.create_model_and_transforms(model, pretrained=tag)
    return net.eval(), pre


def _upstream_features(net, pre, crops: np.ndarray) -> np.ndarray:
    from PIL import Image

    u8 = [np.clip(np.rint(c * 255), 0, 255).astype(np.uint8) if c.dtype != np.uint8
          else c for c in crops]  # fmt: skip
    x = torch.stack([pre(Image.fromarray(c)) for c in u8])
    with torch.no_grad():
        return net.encode_image(x, normalize=True).numpy()


def _tiny_siglip(monkeypatch) -> str:
    """A tiny config with SigLIP's shape (a timm ViT tower) and the
    real ViT-B-16-SigLIP2 'webli' tag's preprocessing entry."""
    oc = _oc()
    name = "ptovs-tiny-siglip-test"
    cfg = dict(
        embed_dim=32,
        vision_cfg=dict(image_size=224, timm_model_name="vit_tiny_patch16_224",
                        timm_model_pretrained=False, timm_pool="avg",
                        timm_proj="linear"),
        text_cfg=dict(context_length=16, vocab_size=1000, width=32, heads=2,
                      layers=1, hf_tokenizer_name="timm/ViT-B-16-SigLIP2"),
        custom_text=True,
    )  # fmt: skip
    monkeypatch.setitem(oc.factory._MODEL_CONFIGS, name, cfg)
    webli = oc.pretrained._PRETRAINED["ViT-B-16-SigLIP2"]["webli"]
    monkeypatch.setitem(oc.pretrained._PRETRAINED, name, {"webli": dict(webli)})
    return name


@pytest.mark.parametrize("which", ["MobileCLIP2-S0", "siglip"])
def test_wrapper_features_equal_the_upstream_forward(which, tmp_path, monkeypatch):
    """Our features of a crop at the model's size and of a raw crop of another
    size equal open_clip's own transform + encode_image on the same weights:
    MobileCLIP2-S0 (mean 0 / std 1, bilinear, 256 px, FastViT re-parameterised by
    us, not upstream) and a SigLIP-shaped model (0.5 / 0.5, squash)."""
    from ptovs.encoders.openclip import OpenClipEncoder, build_net

    model, tag = (which, "dfndr2b") if which != "siglip" else (
        _tiny_siglip(monkeypatch), "webli")  # fmt: skip
    torch.manual_seed(0)
    ckpt = tmp_path / "model.pt"
    torch.save(build_net(model, None).state_dict(), ckpt)
    enc = OpenClipEncoder(model, ckpt, batch_size=2)
    assert enc.pre.tag == tag  # the only tag: its preprocessing, no setting needed
    if which != "siglip":
        assert (enc.pre.mean, enc.pre.std, enc.size) == ((0.0,) * 3, (1.0,) * 3, 256)
        # re-parameterised: no training-time branches left in the image tower
        assert any(hasattr(m, "reparameterize") for m in enc.net.visual.modules())
        assert all(getattr(m, "reparam_conv", True) is not None
                   for m in enc.net.visual.modules())  # fmt: skip
    else:
        assert enc.pre.mean == (0.5,) * 3 and enc.pre.resize_mode == "squash"
    net, pre = _upstream(model, tag, ckpt, monkeypatch)
    same = _crops(3, enc.size)
    rng = np.random.default_rng(1)
    raw = rng.integers(0, 256, (2, 40, 40, 3), dtype=np.uint8)  # another size
    for crops in (same, raw):
        ours = enc.encode_images(crops)
        theirs = _upstream_features(net, pre, crops)
        np.testing.assert_allclose(ours, theirs, atol=2e-5)
        assert np.allclose(np.linalg.norm(ours, axis=1), 1, atol=1e-5)


TOL = 2e-5  # fp32 features of the same model and input, two code paths


def _tiny_b32(monkeypatch) -> str:
    """A 2-layer ViT-B-32-shaped config registered as upstream registers
    ViT-B-32: a GELU name and a `-quickgelu` twin, with ViT-B-32's real
    'laion2b_s34b_b79k' (GELU) and 'openai' (QuickGELU) tag entries."""
    oc = _oc()
    from ptovs.encoders.openclip import TINY_CONFIG

    name = "ptovs-tiny-b32-test"
    cfg = dict(TINY_CONFIG, vision_cfg=dict(TINY_CONFIG["vision_cfg"], width=96))
    monkeypatch.setitem(oc.factory._MODEL_CONFIGS, name, cfg)
    monkeypatch.setitem(
        oc.factory._MODEL_CONFIGS, f"{name}-quickgelu", dict(cfg, quick_gelu=True)
    )
    real = oc.pretrained._PRETRAINED["ViT-B-32"]
    tags = {t: dict(real[t]) for t in ("laion2b_s34b_b79k", "openai")}
    monkeypatch.setitem(oc.pretrained._PRETRAINED, name, tags)
    monkeypatch.setitem(
        oc.pretrained._PRETRAINED, f"{name}-quickgelu", {"openai": dict(real["openai"])}
    )
    return name


def _trained_like(net) -> None:
    """Random init keeps MLP inputs near 0, where GELU and QuickGELU almost agree,
    and MLP outputs small beside the residual stream; trained towers do neither.
    Widen the MLPs so that the activation matters."""
    with torch.no_grad():
        for name, p in net.named_parameters():
            if "mlp.c_fc.weight" in name:
                p.mul_(1.5)
            elif "mlp.c_proj.weight" in name:
                p.mul_(10.0)


def _native_square(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The segment's square-padded crop at native resolution (uint8), as
    prepare_crop cuts it before resizing: what an upstream user would feed."""
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    img = image[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1].copy()
    img[~mask[rows[0] : rows[-1] + 1, cols[0] : cols[-1] + 1]] = 0
    h, w = img.shape[:2]
    side = max(h, w)
    pad = np.zeros((side, side, 3), np.uint8)
    pad[
        (side - h) // 2 : (side - h) // 2 + h, (side - w) // 2 : (side - w) // 2 + w
    ] = img
    return pad


def _segments(seed: int = 0):
    """Photos with a non-square segment each: one crop upsampled, one
    downsampled (the model reads 224 px)."""
    rng = np.random.default_rng(seed)
    out = []
    for h, w, (y0, y1, x0, x1) in ((97, 131, (20, 80, 10, 100)),
                                   (420, 380, (30, 400, 40, 330))):  # fmt: skip
        image = (rng.random((h, w, 3)) * 255).astype(np.uint8)
        yy, xx = np.mgrid[:h, :w]
        cy, cx, ry, rx = (y0 + y1) / 2, (x0 + x1) / 2, (y1 - y0) / 2, (x1 - x0) / 2
        out.append((image, ((yy - cy) / ry) ** 2 + ((xx - cx) / rx) ** 2 <= 1))
    return out


def test_image_and_text_features_equal_upstream_for_gelu_and_quickgelu_tags(
    tmp_path, monkeypatch
):
    """One checkpoint, two tags: our image and text features equal open_clip's
    own `create_model_and_transforms(..., pretrained=tag)` (the tag's entry
    pointed at the file; `-quickgelu` for the QuickGELU tag, as upstream names
    it) + the tag's transform + `get_tokenizer`, within 2e-5, on crops at the
    model's size, of another size, and cut from photos by `prepare_crop` with the
    encoder's `resample`. Negative controls: the wrong activation or the wrong
    mean/std move the same features by more than 100x the tolerance."""
    import warnings

    from PIL import Image

    from ptovs.crop import prepare_crop
    from ptovs.encoders.openclip import OpenClipEncoder, build_net

    oc = _oc()
    name = _tiny_b32(monkeypatch)
    torch.manual_seed(0)
    net0 = build_net(name, None)
    _trained_like(net0)
    ckpt = tmp_path / "model.pt"
    torch.save(net0.state_dict(), ckpt)
    for table in (oc.pretrained._PRETRAINED[name],
                  oc.pretrained._PRETRAINED[f"{name}-quickgelu"]):  # fmt: skip
        for entry in table.values():
            entry["file"] = str(ckpt)
    rng = np.random.default_rng(1)
    crops = np.concatenate([_crops(2, 224), rng.random((2, 224, 224, 3))])
    crops = (np.rint(crops * 255) / 255).astype(np.float32)
    raw = rng.integers(0, 256, (2, 40, 40, 3), dtype=np.uint8)
    texts = ["a column", "the sky over a dome", "a person on the stairs"]
    ours, theirs = {}, {}
    for tag, upstream in (("laion2b_s34b_b79k", name), ("openai", f"{name}-quickgelu")):
        enc = OpenClipEncoder(name, ckpt, pretrained=tag, batch_size=3)
        assert enc.pre.quick_gelu == (tag == "openai")
        assert (enc.resample, enc.pre.resize_mode) == ("bicubic", "shortest")
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no QuickGELU mismatch warning
            net, _, pre = oc.create_model_and_transforms(upstream, pretrained=tag)
        net.eval()
        tok = oc.get_tokenizer(upstream)
        cut = np.stack([prepare_crop(im, m, enc.size, resample=enc.resample)
                        for im, m in _segments()])  # fmt: skip
        native = [_native_square(im, m) for im, m in _segments()]
        assert {p.shape[0] for p in native} == {91, 371}  # up- and downsampled
        with torch.no_grad():
            up_cut = net.encode_image(
                torch.stack([pre(Image.fromarray(p)) for p in native]), normalize=True
            ).numpy()
            up_txt = net.encode_text(tok(texts), normalize=True).numpy()
        up_crops, up_raw = (_upstream_features(net, pre, c) for c in (crops, raw))
        for mine, ref in ((enc.encode_images(crops), up_crops),
                          (enc.encode_images(raw), up_raw),
                          (enc.encode_images(cut), up_cut),
                          (enc.encode_texts(texts), up_txt)):  # fmt: skip
            np.testing.assert_allclose(mine, ref, atol=TOL)
        ours[tag] = (enc.encode_images(crops), enc.encode_texts(texts))
        theirs[tag] = (net, pre)
    # negative control 1: QuickGELU weights driven with GELU (the old bug)
    net, pre = theirs["openai"]
    right = _upstream_features(net, pre, crops)
    with torch.no_grad():
        right_txt = net.encode_text(oc.get_tokenizer(name)(texts), normalize=True)
    wrong_img, wrong_txt = ours["laion2b_s34b_b79k"]
    assert np.abs(wrong_img - right).max() > 100 * TOL
    assert np.abs(wrong_txt - right_txt.numpy()).max() > 100 * TOL
    # negative control 2: the right model fed MobileCLIP's mean 0 / std 1
    x = torch.from_numpy(crops).permute(0, 3, 1, 2).float()
    with torch.no_grad():
        off = net.encode_image(x, normalize=True).numpy()
    assert np.abs(off - right).max() > 100 * TOL
    # upstream's own pitfall: the GELU name with the QuickGELU tag only warns
    with pytest.warns(UserWarning, match="QuickGELU mismatch"):
        oc.create_model_and_transforms(name, pretrained="openai")


@pytest.mark.parametrize("interpolation", ["bilinear", "bicubic"])
@pytest.mark.parametrize("mode", ["shortest", "squash", "longest"])
def test_a_crop_resized_by_the_tag_equals_the_upstream_transform(interpolation, mode):
    """prepare_crop(..., resample=tag's interpolation) + our batch normalisation
    is open_clip's eval transform (any resize mode) of the square-padded crop at
    native resolution, to the pixel; cv2's default resize is not."""
    from dataclasses import replace

    from PIL import Image

    from ptovs.crop import prepare_crop
    from ptovs.encoders.openclip import OpenClipEncoder, register_tiny

    oc = _oc()
    enc = OpenClipEncoder(register_tiny(), random_weights=True)
    enc.pre = replace(enc.pre, interpolation=interpolation, resize_mode=mode)
    cfg = oc.transform.PreprocessCfg(size=enc.size, mean=enc.pre.mean,
                                     std=enc.pre.std, interpolation=interpolation,
                                     resize_mode=mode)  # fmt: skip
    tf = oc.transform.image_transform_v2(cfg, is_train=False)
    off = []
    for image, mask in _segments(2):
        ref = tf(Image.fromarray(_native_square(image, mask)))[None]
        ours = enc.preprocess(prepare_crop(image, mask, enc.size, interpolation)[None])
        torch.testing.assert_close(ours, ref, atol=1e-6, rtol=0)
        cv2_cut = enc.preprocess(prepare_crop(image, mask, enc.size)[None])
        off.append(float((cv2_cut - ref).abs().mean()))
    # the choice matters where crops shrink: cv2 samples, PIL averages (antialias)
    assert off[1] > 0.1, off


def test_preprocessing_follows_the_pretrained_tag():
    from ptovs.encoders.openclip import preprocess_for

    openai = (0.48145466, 0.4578275, 0.40821073)
    assert preprocess_for("ViT-B-16", "laion2b_s34b_b88k").mean == openai
    assert preprocess_for("ViT-B-32", "laion2b_s34b_b79k").size == 224
    mc = preprocess_for("MobileCLIP2-S0")
    assert (mc.mean, mc.std, mc.interpolation) == ((0.0,) * 3, (1.0,) * 3, "bilinear")
    assert not mc.quick_gelu
    assert preprocess_for("MobileCLIP2-S3").mean == openai  # S3/S4: OpenAI's
    sig = preprocess_for("ViT-B-16-SigLIP2")
    assert (sig.mean, sig.resize_mode) == ((0.5,) * 3, "squash")
    with pytest.raises(ValueError, match="set clip_pretrained"):
        preprocess_for("ViT-L-14")  # openai and laion tags preprocess differently
    assert preprocess_for("ViT-L-14", "laion2b_s32b_b82k").tag == "laion2b_s32b_b82k"
    with pytest.raises(ValueError, match="not a tag of ViT-B-32"):
        preprocess_for("ViT-B-32", "dfndr2b")
    with pytest.raises(ValueError, match="not an OpenCLIP model"):
        preprocess_for("ViT-Q-99")
    with pytest.raises(ValueError, match="hf-hub"):
        preprocess_for("hf-hub:timm/ViT-B-16-SigLIP2")  # would download its config


def test_quickgelu_follows_the_pretrained_tag():
    """The activation is part of the tag: OpenAI's, DFN's and MetaCLIP's ViT-B-16
    are QuickGELU, laion2b's is GELU, so ViT-B-16 without a tag is refused in one
    line naming the tags and ViT-B-16-quickgelu. Tags are normalised as upstream's
    `_clean_tag` (lower case, '-' to '_')."""
    from ptovs.encoders.openclip import preprocess_for

    for model, quick, gelu in (
        ("ViT-B-16", ("openai", "dfn2b", "metaclip_400m"), ("laion2b_s34b_b88k",)),
        ("ViT-B-32", ("openai", "laion400m_e32", "metaclip_fullcc"),
         ("laion2b_s34b_b79k", "datacomp_xl_s13b_b90k")),
    ):  # fmt: skip
        assert all(preprocess_for(model, t).quick_gelu for t in quick), model
        assert not any(preprocess_for(model, t).quick_gelu for t in gelu), model
        with pytest.raises(ValueError) as e:
            preprocess_for(model)
        msg = str(e.value)
        assert "\n" not in msg and f"{model}-quickgelu" in msg, msg
        assert "QuickGELU: openai" in msg and "laion2b" in msg.split("GELU:")[-1]
    assert preprocess_for("ViT-B-16", "OpenAI").tag == "openai"
    assert preprocess_for("ViT-B-32", "Laion400M-E32").quick_gelu
    assert preprocess_for("ViT-B-32-quickgelu").quick_gelu  # every tag agrees
    assert preprocess_for("RN50").quick_gelu  # every tag: QuickGELU, config: not
    assert not preprocess_for("ViT-B-16-SigLIP2").quick_gelu


def test_a_checkpoint_loads_quietly_from_torch_or_safetensors(tmp_path, caplog):
    from safetensors.torch import save_file

    from ptovs.encoders.openclip import OpenClipEncoder, build_net, register_tiny

    name = register_tiny()
    ckpt = tmp_path / "tiny.pt"
    state = build_net(name, None).state_dict()
    torch.save(state, ckpt)
    with caplog.at_level("WARNING"):
        enc = OpenClipEncoder(name, ckpt)
    assert "initialized randomly" not in caplog.text
    # the hubs' .safetensors files load too, to the same weights
    safe = tmp_path / "open_clip_model.safetensors"
    save_file({k: v.contiguous() for k, v in state.items()}, safe)
    crops = _crops(2, 224)
    np.testing.assert_array_equal(
        OpenClipEncoder(name, safe).encode_images(crops), enc.encode_images(crops)
    )


def _outliers(enc, size: float = 1000.0) -> None:
    """Massive activations, as trained ViTs grow them: every residual channel
    offset by `size` after the first block's attention. fp32 keeps the signal
    riding on it (the next LayerNorm removes the offset); bf16's 8-bit mantissa
    rounds it away."""
    block = enc.net.visual.transformer.resblocks[0]
    with torch.no_grad():
        block.attn.out_proj.bias += size
    enc._fast = None


def _bf16_allowed(monkeypatch, enc, fp32_s: float = 2.0, bf16_s: float = 1.0):
    """Let the check run here whatever the CPU: bf16_is_fast says yes and the
    timings say bf16 took `bf16_s` where fp32 took `fp32_s` (the features are
    real)."""
    from ptovs.encoders import openclip

    monkeypatch.setattr(openclip, "bf16_is_fast", lambda *a, **k: (True, {"x": 1}))
    real = enc._timed_encode

    def timed(crops, precision):
        return real(crops, precision)[0], fp32_s if precision == "fp32" else bf16_s

    monkeypatch.setattr(enc, "_timed_encode", timed)


def test_bf16_is_kept_only_where_it_agrees_with_fp32_and_is_faster(monkeypatch):
    import json

    from ptovs.encoders.openclip import (
        MAX_RELEVANCY_CHANGE,
        MIN_CENTRED_COSINE,
        OpenClipEncoder,
        register_tiny,
    )

    torch.manual_seed(0)
    crops = _crops(24, 224)
    enc = OpenClipEncoder(register_tiny(), random_weights=True, precision="auto")
    assert enc.precision == "fp32"  # auto starts safe
    _bf16_allowed(monkeypatch, enc)
    # an agreeing bf16 tower: fp32's features rounded to bf16. The whole random
    # tiny tower in bf16 sits on the bars (centred cosine 0.996-0.998, a near-tie
    # that AMX's rounding flips and AVX-512's does not), so it cannot stand for "agrees"
    real = enc._forward

    def rounded(x, precision):
        f = real(x, "fp32")
        return f.to(torch.bfloat16).float() if precision == "bf16" else f

    monkeypatch.setattr(enc, "_forward", rounded)
    clean = enc.check_precision(crops)
    monkeypatch.setattr(enc, "_forward", real)
    assert clean["precision"] == "bf16" and enc.precision == "bf16", clean
    assert 0 < clean["worst_feature_distance"] < 0.01  # bf16 did round them
    assert clean["worst_centred_cosine"] >= MIN_CENTRED_COSINE
    assert clean["worst_relevancy_change"] <= MAX_RELEVANCY_CHANGE
    json.dumps(clean)  # stored with the features
    # agrees but slower on the sample: fp32
    _bf16_allowed(monkeypatch, enc, fp32_s=1.0, bf16_s=1.5)
    slow = enc.check_precision(crops)
    assert slow["precision"] == "fp32" and "slower" in slow["reason"], slow
    assert "worst_centred_cosine" not in slow  # stopped after the short trial
    _bf16_allowed(monkeypatch, enc)
    _outliers(enc)
    ref = enc._encode(crops[:4], "fp32")
    report = enc.check_precision(crops)
    assert report["precision"] == "fp32" and enc.precision == "fp32", report
    assert report["worst_centred_cosine"] < MIN_CENTRED_COSINE
    assert report["reason"] == "bf16 disagrees with fp32"
    np.testing.assert_array_equal(enc.encode_images(crops[:4]), ref)  # fp32 path
    assert set(report) >= {"crops", "bar", "top1_agreement", "checked", "seconds"}


def test_where_bf16_is_not_faster_nothing_runs_in_bf16(monkeypatch):
    """bf16_is_fast says no (as on a CPU without bf16 instructions): fp32, and
    not one crop goes through a bfloat16 model."""
    import json

    from ptovs.encoders import openclip

    enc = openclip.OpenClipEncoder(
        openclip.register_tiny(), random_weights=True, precision="auto"
    )
    evidence = {"capability": "AVX2", "bf16_flags": [], "probe": None}
    monkeypatch.setattr(openclip, "bf16_is_fast", lambda *a, **k: (False, evidence))

    def no_bf16():
        raise AssertionError("a bf16 forward ran")

    monkeypatch.setattr(enc, "_fast_model", no_bf16)
    report = enc.check_precision(_crops(6, 224))
    assert report["precision"] == "fp32" and enc.precision == "fp32"
    assert report["reason"] == "bf16 not faster on this CPU"
    assert report["bf16_probe"] == evidence and report["crops"] == 6
    json.loads(json.dumps(report))
    assert enc.encode_images(_crops(1, 224)).shape == (1, enc.dim)


def test_bf16_is_fast_reads_the_cpu_before_timing_anything(monkeypatch):
    """No bf16 instructions: False at once, no probe. With them: the matmul
    probe decides (>= 1.3x). CUDA with bf16: True. The evidence is JSON."""
    import json

    from ptovs.encoders import openclip

    def no_probe(width):
        raise AssertionError("probe ran")

    monkeypatch.setattr(openclip, "_matmul_probe", no_probe)
    for flags in (set(), {"avx2", "fma"}, {"avx2", "avx512f", "avx512bw"}):
        monkeypatch.setattr(openclip, "_cpu_flags", lambda f=flags: f)
        fast, ev = openclip.bf16_is_fast("cpu", 512)
        assert fast is False and ev["probe"] is None and ev["bf16_flags"] == []
        assert ev["capability"] == str(torch.backends.cpu.get_cpu_capability())
        json.dumps(ev)
    monkeypatch.setattr(openclip, "_cpu_flags", lambda: {"avx512f", "avx512_bf16"})
    for speedup, want in ((2.5, True), (1.1, False)):
        monkeypatch.setattr(
            openclip, "_matmul_probe",
            lambda w, s=speedup: {"fp32_s": s * 0.01, "bf16_s": 0.01, "speedup": s},
        )  # fmt: skip
        fast, ev = openclip.bf16_is_fast("cpu", 512)
        assert fast is want and ev["probe"]["width"] == 512, ev
        assert ev["bf16_flags"] == ["avx512_bf16"]
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *a, **k: True)
    assert openclip.bf16_is_fast("cuda")[0] is True
    # the real probe on this machine: times in seconds, a ratio, nothing asserted
    # about which is faster (that is the machine's business)
    monkeypatch.undo()
    out = openclip._matmul_probe(64)
    assert out["fp32_s"] > 0 and out["bf16_s"] > 0 and out["speedup"] > 0


def test_auto_precision_asks_the_cpu_before_segmenting_a_sample(tmp_path, monkeypatch):
    """extract-features' precision "auto": on a CPU without bf16 instructions the
    answer is fp32 with its reason, stored once, and no sample is segmented (SAM
    ViT-H would take minutes on it); where bf16 may be faster, the sample is
    segmented and the full check runs on its crops."""
    import json

    from ptovs.artifacts import Notes
    from ptovs.encoders import openclip
    from ptovs.encoders.decide import decide_precision
    from ptovs.segment import NO_SEGMENT, Level

    segmented: list[int] = []

    def sample():  # the first view, segmented: two halves at one level
        segmented.append(1)
        image = (_crops(1, 64)[0] * 255).astype(np.uint8)
        labels = np.full((64, 64), NO_SEGMENT, np.int32)
        labels[:, :32], labels[:, 32:] = 0, 1
        return [Level(labels)], image

    def no_probe(width):
        raise AssertionError("the matmul probe ran")

    monkeypatch.setattr(openclip, "_cpu_flags", lambda: set())  # e.g. plain AVX2
    monkeypatch.setattr(openclip, "_matmul_probe", no_probe)
    tiny = openclip.register_tiny()
    enc = openclip.OpenClipEncoder(tiny, random_weights=True, precision="auto")
    notes = Notes(tmp_path / "a", "key-a")
    report = decide_precision(enc, notes, sample, enc.size)
    assert segmented == [], "a sample was segmented where bf16 cannot be faster"
    assert report["precision"] == "fp32" and enc.precision == "fp32"
    assert report["reason"] == "bf16 not faster on this CPU" and report["crops"] == 0
    assert (
        report["bf16_probe"]["bf16_flags"] == []
        and report["bf16_probe"]["probe"] is None
    )
    assert notes.get("precision") == json.loads(json.dumps(report))  # kept, as JSON
    # the same report as the check's own where bf16 is not faster
    full = enc.check_precision(_crops(3, enc.size))
    assert set(report) == set(full) and full["reason"] == report["reason"]

    monkeypatch.setattr(openclip, "_cpu_flags", lambda: {"avx512f", "avx512_bf16"})
    monkeypatch.setattr(
        openclip, "_matmul_probe",
        lambda w: {"fp32_s": 0.02, "bf16_s": 0.01, "speedup": 2.0},
    )  # fmt: skip
    enc = openclip.OpenClipEncoder(tiny, random_weights=True, precision="auto")
    report = decide_precision(enc, Notes(tmp_path / "b", "key-b"), sample, enc.size)
    assert segmented == [1]  # bf16 may pay here: the sample decides
    assert report["crops"] == 2 and report["bf16_probe"]["probe"]["speedup"] == 2.0
    assert "seconds" in report  # bf16 was tried on the sample's crops


def test_bf16_is_upstreams_pure_bf16_encode_image(tmp_path):
    """precision "bf16" is open_clip's `precision="pure_bf16"` model's own
    encode_image on a bf16 input, to the bit."""
    from ptovs.encoders.openclip import OpenClipEncoder, build_net, register_tiny

    oc = _oc()
    name = register_tiny()
    torch.manual_seed(0)
    ckpt = tmp_path / "tiny.pt"
    torch.save(build_net(name, None).state_dict(), ckpt)
    enc = OpenClipEncoder(name, ckpt, precision="bf16")
    up = oc.create_model(name, precision="pure_bf16")
    oc.factory.load_checkpoint(up, str(ckpt))
    crops = _crops(3, 224)
    x = enc.preprocess(crops)
    with torch.no_grad():  # normalised in fp32, as ours (bf16's 8 bits would round)
        ref = up.eval().encode_image(x.to(torch.bfloat16)).float()
    ref = torch.nn.functional.normalize(ref, dim=-1)
    np.testing.assert_allclose(enc.encode_images(crops), ref.numpy(), atol=1e-6)
    # texts stay fp32
    fp32 = OpenClipEncoder(name, ckpt)
    np.testing.assert_array_equal(enc.encode_texts(["a dome"]),
                                  fp32.encode_texts(["a dome"]))  # fmt: skip


def _tiny_coca(monkeypatch) -> str:
    oc = _oc()
    name = "ptovs-tiny-coca-test"
    cfg = dict(
        embed_dim=32,
        multimodal_cfg=dict(context_length=16, width=32, heads=2, layers=1,
                            attn_pooler_heads=2),
        vision_cfg=dict(image_size=64, layers=1, width=32, patch_size=16,
                        head_width=16, attentional_pool=True, attn_pooler_heads=2,
                        output_tokens=True),
        text_cfg=dict(context_length=16, vocab_size=49408, width=32, heads=2,
                      layers=1, embed_cls=True, output_tokens=True),
        custom_text=True,
    )  # fmt: skip
    monkeypatch.setitem(oc.factory._MODEL_CONFIGS, name, cfg)
    return name


def test_coca_models_work_in_both_precisions(tmp_path, monkeypatch):
    """CoCa's visual tower returns (latent, tokens): its own encode_image is
    used, in fp32 and bf16, and texts go through its encode_text."""
    from ptovs.encoders.openclip import OpenClipEncoder, build_net

    oc = _oc()
    name = _tiny_coca(monkeypatch)
    torch.manual_seed(0)
    ckpt = tmp_path / "coca.pt"
    torch.save(build_net(name, None).state_dict(), ckpt)
    enc = OpenClipEncoder(name, ckpt, precision="bf16")
    net, _, pre = oc.create_model_and_transforms(name, pretrained=str(ckpt))
    crops = _crops(2, enc.size)
    with torch.no_grad():
        txt = net.eval().encode_text(oc.get_tokenizer(name)(["a dome"]))
    enc.precision = "fp32"
    np.testing.assert_allclose(
        enc.encode_images(crops), _upstream_features(net, pre, crops), atol=TOL
    )
    np.testing.assert_allclose(enc.encode_texts(["a dome"]), txt.numpy(), atol=TOL)
    enc.precision = "bf16"
    low = enc.encode_images(crops)
    assert low.shape == (2, enc.dim) and np.isfinite(low).all()


def test_a_hugging_face_text_tower_never_downloads(tmp_path, monkeypatch):
    """roberta-ViT-B-32's text tower is a Hugging Face model: without its local
    folder, or without transformers, it is refused in one line, and at no point
    is a download attempted (every download entry point raises here)."""
    import importlib

    from ptovs.encoders.openclip import OpenClipEncoder, build_net
    from ptovs.encoders.openclip_backend import check_openclip
    from ptovs.errors import InputError

    oc = _oc()

    def download(*a, **k):
        raise AssertionError(f"download attempted: {a}")

    for mod, attr in ((oc.pretrained, "download_pretrained"),
                      (oc.pretrained, "download_pretrained_from_hf"),
                      (oc.pretrained, "download_pretrained_from_url"),
                      (oc.factory, "_get_hf_config"),
                      (oc.factory, "download_pretrained"),
                      (oc.factory, "download_pretrained_from_hf")):  # fmt: skip
        monkeypatch.setattr(mod, attr, download)
    hub = importlib.import_module("huggingface_hub")
    monkeypatch.setattr(hub, "hf_hub_download", download)
    monkeypatch.setattr(hub, "snapshot_download", download)
    model = "roberta-ViT-B-32"
    ckpt = tmp_path / "model.pt"
    ckpt.write_bytes(b"")
    with pytest.raises(ValueError, match="clip_tokenizer") as e:
        build_net(model, None)
    assert "'roberta-base'" in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(InputError, match="clip_tokenizer") as e:
        check_openclip(model, ckpt, pretrained="laion2b_s12b_b32k")
    assert "\n" not in str(e.value)
    folder = tmp_path / "roberta-base"
    folder.mkdir()
    with pytest.raises(FileNotFoundError, match="no config.json"):
        build_net(model, None, hf_folder=folder)
    (folder / "config.json").write_text(
        '{"model_type": "roberta", "vocab_size": 100, "hidden_size": 32, '
        '"num_hidden_layers": 1, "num_attention_heads": 2, '
        '"intermediate_size": 64, "max_position_embeddings": 40}'
    )
    if oc.hf_model.transformers is None:
        with pytest.raises(ValueError, match="pip install transformers"):
            OpenClipEncoder(model, ckpt, tokenizer=folder)
    else:  # built from the local config, random text weights, nothing fetched
        net = build_net(model, None, quick_gelu=True, hf_folder=folder)
        assert net.text.config.hidden_size == 32


def test_extract_features_records_the_precision_it_kept(
    tiny_scene_dir, tmp_path, monkeypatch
):
    """extract-features with precision "auto" on the tiny scene's photos, on a CPU
    where bf16 may be faster: the check runs on the first view's crops, and
    levels_json says what was kept."""
    from click.testing import CliRunner

    from ptovs.artifacts import Artifact, read_json_dataset
    from ptovs.cli import main as cli
    from ptovs.encoders import openclip
    from ptovs.encoders.openclip import build_net, register_tiny

    monkeypatch.setattr(openclip, "_cpu_flags", lambda: {"avx512f", "avx512_bf16"})
    monkeypatch.setattr(
        openclip, "_matmul_probe",
        lambda w: {"fp32_s": 0.02, "bf16_s": 0.01, "speedup": 2.0},
    )  # fmt: skip
    name = register_tiny()
    ckpt = tmp_path / "tiny.pt"
    torch.manual_seed(0)
    torch.save(build_net(name, None).state_dict(), ckpt)
    work = tmp_path / "work"
    r = CliRunner().invoke(cli, [
        "--work-dir", str(work), "extract-features", "--data", str(tiny_scene_dir),
        "--set", "images=orig", "--set", "encoder=openclip",
        "--set", f"clip_model={name}", "--set", f"clip_checkpoint={ckpt}",
    ])  # fmt: skip
    assert r.exit_code == 0, r.output
    (path,) = sorted((work / tiny_scene_dir.name / "extract-features").glob("*.h5"))
    meta = read_json_dataset(Artifact(path).root()["levels_json"])
    assert meta["precision"]["precision"] in ("bf16", "fp32")
    assert meta["precision"]["crops"] > 0
    assert meta["encoder_spec"]["model"] == name


def test_preflight_runs_a_crop_and_a_phrase(tmp_path, monkeypatch):
    """A checkpoint that fits but a model the wrapper cannot drive (here: its
    Hugging Face tokenizer would be downloaded) fails preflight in one line."""
    from ptovs.encoders.openclip import build_net
    from ptovs.encoders.openclip_backend import check_openclip
    from ptovs.errors import InputError

    name = _tiny_siglip(monkeypatch)
    ckpt = tmp_path / "siglip.pt"
    torch.save(build_net(name, None).state_dict(), ckpt)
    with pytest.raises(
        InputError, match="could not encode a test crop and phrase"
    ) as e:
        check_openclip(name, ckpt)
    assert "clip_tokenizer" in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(InputError, match="not a tag of"):
        check_openclip(name, ckpt, pretrained="openai")


def test_preflight_refuses_an_ambiguous_model_and_runs_the_precision_used(
    tmp_path, monkeypatch
):
    """Before any stage: a model whose tags disagree on QuickGELU, with no tag,
    is refused in one line; the test crop runs in bf16 where bf16 will (or, with
    "auto", may) be used, so a model that fails only in bf16 fails here."""
    from ptovs.encoders import openclip
    from ptovs.encoders import openclip_backend as preflight
    from ptovs.errors import InputError

    some = tmp_path / "any.pt"
    some.write_bytes(b"")
    with pytest.raises(InputError) as e:
        preflight.check_openclip("ViT-B-16", some)
    msg = str(e.value)
    assert "ViT-B-16-quickgelu" in msg and "clip_pretrained" in msg and "\n" not in msg
    name = openclip.register_tiny()
    ckpt = tmp_path / "tiny.pt"
    torch.save(openclip.build_net(name, None).state_dict(), ckpt)

    def broken():
        raise RuntimeError("bf16 kernel missing")

    monkeypatch.setattr(openclip.OpenClipEncoder, "_fast_model", lambda self: broken())
    preflight.check_openclip(name, ckpt, precision="fp32")
    for fast in (False, True):
        preflight.openclip_fits.cache_clear()
        monkeypatch.setattr(openclip, "bf16_is_fast", lambda *a, f=fast: (f, {}))
        if not fast:
            preflight.check_openclip(name, ckpt, precision="auto")  # fp32 only
            continue
        with pytest.raises(InputError, match="bf16 kernel missing"):
            preflight.check_openclip(name, ckpt, precision="auto")
    with pytest.raises(InputError, match="could not encode a test crop"):
        preflight.check_openclip(name, ckpt, precision="bf16")


def test_openclip_features_carry_through_train_and_query(
    extracted_work, tiny_scene_dir, tmp_path
):
    """The photo-alone recipe with OpenCLIP features, end to end: query embeds
    its phrases with the model (and tag) the features recorded, no setting given."""
    import json

    from conftest import copy_work, run_cli
    from ptovs.encoders.openclip import build_net, register_tiny

    name = register_tiny()
    ckpt = tmp_path / "tiny.pt"
    torch.manual_seed(0)
    torch.save(build_net(name, None).state_dict(), ckpt)
    work = copy_work(extracted_work[0], tmp_path / "work")
    sets = ["--set", "extract-features.encoder=openclip",
            "--set", f"extract-features.clip_model={name}",
            "--set", f"extract-features.clip_checkpoint={ckpt}"]  # fmt: skip
    data = ["--data", str(tiny_scene_dir), "--variant", "langsplat-wild"]
    run_cli(work, *sets, "train", *data)  # extract-features (photos) runs first
    # a synthetic scene's query would check the stand-in's vocabulary: say openclip
    out = run_cli(work, *sets, "--set", "query.encoder=openclip", "query", *data,
                  "a column", "--views",
                  "00000002_1036464163.jpg")  # fmt: skip
    found = sorted(work.rglob("query-out/*/results.json"))
    assert found, out
    text = " ".join(p.read_text() for p in found)
    assert "a column" in text
    assert all(
        np.isfinite(v) for p in found for v in _numbers(json.loads(p.read_text()))
    )


def _numbers(obj):
    if isinstance(obj, dict):
        for v in obj.values():
            yield from _numbers(v)
    elif isinstance(obj, list):
        for v in obj:
            yield from _numbers(v)
    elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
        yield float(obj)


def test_a_torchscript_checkpoint_is_refused_naming_the_state_dict(tmp_path) -> None:
    """OpenAI's own ViT-*.pt files are TorchScript archives: never executed, refused
    in one line that names the state dict to take instead; a plain state dict in the
    same zip format still loads."""
    from ptovs.encoders.openclip_net import clip_state_dict as _state_dict

    net = torch.nn.Linear(2, 2)
    torch.jit.save(torch.jit.script(net), tmp_path / "ViT-B-16.pt")
    with pytest.raises(ValueError, match="TorchScript.*open_clip_model.safetensors"):
        _state_dict(tmp_path / "ViT-B-16.pt")
    torch.save(net.state_dict(), tmp_path / "plain.pt")
    assert sorted(_state_dict(tmp_path / "plain.pt")) == ["bias", "weight"]
