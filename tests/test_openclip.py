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


def test_preprocessing_follows_the_pretrained_tag():
    from ptovs.encoders.openclip import preprocess_for

    openai = (0.48145466, 0.4578275, 0.40821073)
    assert preprocess_for("ViT-B-16").mean == openai  # all its tags agree
    assert preprocess_for("ViT-B-32").size == 224
    mc = preprocess_for("MobileCLIP2-S0")
    assert (mc.mean, mc.std, mc.interpolation) == ((0.0,) * 3, (1.0,) * 3, "bilinear")
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


def test_bf16_is_kept_only_where_it_agrees_with_fp32():
    from ptovs.encoders.openclip import (
        MIN_CENTRED_COSINE,
        OpenClipEncoder,
        register_tiny,
    )

    torch.manual_seed(0)
    crops = _crops(24, 224)
    enc = OpenClipEncoder(register_tiny(), random_weights=True, precision="auto")
    assert enc.precision == "fp32"  # auto starts safe
    clean = enc.check_precision(crops)
    assert clean["precision"] == "bf16", clean  # the plain model agrees
    assert clean["worst_centred_cosine"] >= MIN_CENTRED_COSINE
    _outliers(enc)
    ref = enc._encode(crops[:4], "fp32")
    report = enc.check_precision(crops)
    assert report["precision"] == "fp32" and enc.precision == "fp32", report
    assert report["worst_centred_cosine"] < MIN_CENTRED_COSINE
    np.testing.assert_array_equal(enc.encode_images(crops[:4]), ref)  # fp32 path
    assert set(report) >= {"crops", "bar", "top1_agreement", "checked"}


def test_extract_features_records_the_precision_it_kept(tiny_scene_dir, tmp_path):
    """extract-features with precision "auto" on the tiny scene's photos: the
    check runs on the first view's crops, and levels_json says what was kept."""
    from click.testing import CliRunner

    from ptovs.artifacts import Artifact, read_json_dataset
    from ptovs.cli import main as cli
    from ptovs.encoders.openclip import build_net, register_tiny

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
    from ptovs.errors import InputError
    from ptovs.preflight import check_openclip

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
