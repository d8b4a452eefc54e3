"""Runtimes for the image tower: the registry, the export cache, the choice on a
sample, and extract-features' artifacts under each runtime against PyTorch's."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import torch

from ptovs.encoders import runtimes
from ptovs.encoders.runtimes import choose as choosing
from ptovs.errors import InputError


def _tiny_encoder(runtime: str = "torch", seed: int = 0):
    from ptovs.encoders.openclip import OpenClipEncoder, register_tiny

    torch.manual_seed(seed)
    return OpenClipEncoder(register_tiny(), random_weights=True, runtime=runtime)


def _crops(n: int, size: int = 224, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).random((n, size, size, 3)).astype(np.float32)


def test_every_registered_runtime_loads_and_says_whether_it_can_run():
    assert set(runtimes.RUNTIMES) == {"auto", *runtimes.BACKENDS}
    for name in runtimes.BACKENDS:
        backend = runtimes.get_backend(name)
        assert backend.name == name
        why = backend.missing()
        assert why is None or (name in why and "pip install" in why)
    assert runtimes.installed()[0] == "torch"
    # what CI installs (the [clip] extra) runs here
    assert {"onnxruntime", "openvino"} <= set(runtimes.installed())
    with pytest.raises(InputError, match="choose from"):
        runtimes.get_backend("tensorrt")


def test_a_runtime_not_installed_is_refused_in_one_line_naming_the_extra(monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec",
        lambda name, *a: None if name == "openvino" else real(name, *a),
    )  # fmt: skip
    with pytest.raises(InputError) as err:
        runtimes.require("openvino")
    msg = str(err.value)
    assert "\n" not in msg and "[clip]" in msg and "runtime = 'torch'" in msg
    with pytest.raises(InputError):
        _tiny_encoder("openvino")
    # auto never tries it, and says why
    assert "openvino" in choosing.screen("cpu")[1]


@pytest.mark.parametrize("name", ["onnxruntime", "openvino"])
def test_each_runtime_gives_pytorchs_features(name):
    """The tiny tower's unit features in each runtime: within 1e-4 of PyTorch's
    (a batch of the tower's own size and an odd one: the batch side is dynamic)."""
    enc = _tiny_encoder()
    crops = _crops(11)
    ref = enc.encode_images(crops)
    enc.tower.use(name)
    assert enc.runtime == name
    for n in (11, 3):
        got = enc.encode_images(crops[:n])
        assert got.shape == (n, enc.dim) and got.dtype == np.float32
        assert np.abs(got - ref[:n]).max() <= choosing.MAX_ABS_DIFF


def test_the_export_is_made_once_atomically_and_keyed_by_the_weights(monkeypatch):
    from ptovs.encoders.runtimes import export

    enc = _tiny_encoder(seed=1)
    enc.tower.use("onnxruntime")
    folder = runtimes.cache_dir() / "onnx"
    key = enc._runtime_key()
    path = folder / f"{export.export_key(key)}.onnx"
    assert path.is_file() and not list(folder.glob(".*.tmp*"))
    calls = []
    monkeypatch.setattr(torch.onnx, "export", lambda *a, **k: calls.append(a))
    enc2 = _tiny_encoder(seed=1)  # the same weights: the cached file serves
    enc2.tower.use("onnxruntime")
    assert calls == []
    other = _tiny_encoder(seed=2)._runtime_key()
    assert other["weights"] != key["weights"]
    assert export.export_key(other) != export.export_key(key)
    assert export.export_key({**key, "size": 256}) != export.export_key(key)


_SUBNORMAL_PROBE = """
import sys, numpy as np, torch
from ptovs.encoders.runtimes import get_backend, ov
if sys.argv[1] == "unprimed":
    ov._flush_subnormals = lambda *a: None
class Square(torch.nn.Module):
    def forward(self, x):
        return x * x
x = np.full((2, 8), 1e-20, np.float32)  # squares of 1e-40: subnormal
run = get_backend("openvino").load(Square().eval(), torch.zeros(1, 8), {"m": "ftz"}, 2)
print(float(np.abs(run(x)).max()))
"""


def test_openvino_flushes_subnormals_also_from_its_compiled_cache(tmp_path):
    """A model OpenVINO reads back from its compiled cache flushes subnormal floats
    as one compiled afresh does (unflushed, a tower ran 1.4x slower); the
    negative control, without the primer, keeps them."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "PTOVS_RUNTIME_CACHE": str(tmp_path)}

    def largest(mode: str) -> float:
        out = subprocess.run(
            [sys.executable, "-c", _SUBNORMAL_PROBE, mode],
            env=env, capture_output=True, text=True, check=True,
        )  # fmt: skip
        return float(out.stdout.split()[-1])

    assert largest("primed") == 0.0  # compiled afresh, the blob now cached
    assert list(tmp_path.glob("openvino-*-f32-ftz/*.blob"))
    assert largest("primed") == 0.0  # read back from the blob
    assert largest("unprimed") > 0.0  # the blob alone keeps 1e-40


def test_a_checkpoint_file_is_keyed_by_its_bytes(tmp_path):
    from ptovs.encoders.openclip import OpenClipEncoder, build_net, register_tiny

    name = register_tiny()
    torch.manual_seed(3)
    ckpt = tmp_path / "tiny.pt"
    torch.save(build_net(name, None).state_dict(), ckpt)
    enc = OpenClipEncoder(name, ckpt)
    assert enc._runtime_key()["weights"] == runtimes.file_digest(ckpt)


def _runner(delay: float, shift: float = 0.0, dim: int = 4):
    def run(x: np.ndarray) -> np.ndarray:
        time.sleep(delay * len(x))
        out = np.ones((len(x), dim), np.float32)
        out[:, 0] += shift
        return out

    return run


def test_auto_keeps_the_fastest_runtime_that_agrees_and_refuses_one_that_does_not():
    """Timings set by sleeping (10 ms a crop for PyTorch): a runtime 10x faster
    whose features are off by 1e-3 is refused (the negative control); one 5x
    faster that agrees is kept; one slower is dropped at the trial."""
    x = np.zeros((16, 3, 2, 2), np.float32)
    torch_run = _runner(0.01)
    loads = {"wrong": _runner(0.001, shift=2e-3), "right": _runner(0.002),
             "slow": _runner(0.02)}  # fmt: skip
    report = choosing.choose(x, torch_run, torch_run, loads.__getitem__,
                             ["wrong", "right", "slow"], {})  # fmt: skip
    assert report["runtime"] == "right", report["reason"]
    assert report["max_abs_diff"]["wrong"] > choosing.MAX_ABS_DIFF
    assert report["max_abs_diff"]["right"] <= choosing.MAX_ABS_DIFF
    assert "sample" not in report["seconds"]["slow"]  # stopped at the trial
    json.dumps(report)
    # nothing agrees: PyTorch, saying why
    only_wrong = choosing.choose(x, torch_run, torch_run, loads.__getitem__,
                                 ["wrong"], {})  # fmt: skip
    assert only_wrong["runtime"] == "torch" and "agreed" in only_wrong["reason"]


def test_a_runtime_that_fails_to_load_is_skipped_not_fatal():
    x = np.zeros((4, 3, 2, 2), np.float32)

    def broken(name):
        raise RuntimeError("no such op")

    report = choosing.choose(x, _runner(0.0), _runner(0.0), broken, ["onnxruntime"], {})
    assert report["runtime"] == "torch"
    assert "no such op" in report["skipped"]["onnxruntime"]


def test_on_cuda_pytorch_stays_without_encoding_anything(monkeypatch):
    keep, why = choosing.screen("cuda")
    assert keep == [] and set(why) == {"onnxruntime", "openvino"}
    from ptovs.encoders.runtimes.tower import Tower

    tower = Tower(torch.nn.Identity(), (3, 2, 2), dict, "cpu", "auto")
    monkeypatch.setattr(tower, "device", torch.device("cuda"))
    report = tower.without_sample()
    assert report["runtime"] == "torch" and report["crops"] == 0
    assert "can win" in report["reason"] and "CPU only" in report["reason"]


def test_a_resumed_artifact_keeps_its_runtime_and_does_not_measure(tmp_path):
    from ptovs.artifacts import Notes
    from ptovs.encoders.decide import decide_runtime

    def sample():
        raise AssertionError("measured again")

    enc = _tiny_encoder("auto")
    notes = Notes(tmp_path / "n", "key")
    notes.put("runtime", {"runtime": "onnxruntime", "reason": "earlier"})
    report = decide_runtime(enc, notes, sample, enc.size)
    assert report["runtime"] == "onnxruntime" and enc.runtime == "onnxruntime"
    enc2 = _tiny_encoder("openvino")  # asked for: used as it is, recorded
    notes2 = Notes(tmp_path / "n2", "key2")
    assert decide_runtime(enc2, notes2, sample, enc2.size)["reason"] == "asked for"
    assert notes2.get("runtime")["runtime"] == "openvino"


def test_crops_are_encoded_once_by_their_pixels():
    from ptovs.encoders.memo import CropMemo

    enc = _tiny_encoder()
    seen = []
    real = enc.encode_images

    def counting(crops):
        seen.append(len(crops))
        return real(crops)

    enc.encode_images = counting
    memo = CropMemo(enc)
    crops = _crops(3)
    rows = memo.encode_images(np.concatenate([crops, crops[:1]]))
    assert seen == [3] and np.array_equal(rows[0], rows[3])
    memo.pin()
    memo.encode_images(_crops(2, seed=5))
    memo.forget()  # the unpinned rows go; the pinned stay
    again = memo.encode_images(crops)
    assert seen == [3, 2] and np.allclose(again, rows[:3])
    assert memo.encode_images(_crops(2, seed=5)).shape == (2, enc.dim)
    assert seen == [3, 2, 2] and memo.hits == 4 and memo.encoded == 7
    assert memo.name == "openclip" and memo.dim == enc.dim


def _features(work, scene):
    from ptovs.artifacts import Artifact, read_json_dataset

    (path,) = sorted((work / scene.name / "extract-features").glob("*.h5"))
    art = Artifact(path)
    meta = read_json_dataset(art.root()["levels_json"])
    return meta, {n: art[n] for n in art.names()}


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory):
    from ptovs.encoders.openclip import build_net, register_tiny

    name = register_tiny()
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("ckpt") / "tiny.pt"
    torch.save(build_net(name, None).state_dict(), path)
    return name, path


def _extract(tmp_path, scene, tiny_ckpt, runtime: str):
    from click.testing import CliRunner

    from ptovs.cli import main as cli

    name, ckpt = tiny_ckpt
    work = tmp_path / runtime
    r = CliRunner().invoke(cli, [
        "--work-dir", str(work), "extract-features", "--data", str(scene),
        "--set", "images=orig", "--set", "encoder=openclip", "--set", "precision=fp32",
        "--set", f"clip_model={name}", "--set", f"clip_checkpoint={ckpt}",
        "--set", f"runtime={runtime}",
    ])  # fmt: skip
    assert r.exit_code == 0, r.output
    return _features(work, scene)


def _worst(a: dict, b: dict) -> float:
    """The largest feature difference between two artifacts' views, less one unit
    in the last place of the stored float16 (a 1e-7 difference may round a row's
    value to the neighbouring float16); the segment maps must be the same."""
    worst = 0.0
    assert a.keys() == b.keys()
    for view in a:
        for k in a[view]:
            if k.startswith("seg_"):
                assert np.array_equal(a[view][k], b[view][k])
            if k.startswith("feat_"):
                x, y = a[view][k], b[view][k]
                ulp = np.spacing(np.maximum(np.abs(x), np.abs(y))).astype(np.float64)
                d = np.abs(x.astype(np.float64) - y) - ulp
                worst = max(worst, float(d.max(initial=0)))
    return worst


def test_every_runtime_gives_the_artifact_pytorch_gives(tiny_scene_dir, tmp_path,
                                                        tiny_ckpt, monkeypatch):  # fmt: skip
    """extract-features on the tiny scene with a random checkpoint: runtime torch,
    each runtime by name and the default "auto" write the same features within
    1e-4, and say which runtime computed them. The negative control: a runtime
    whose tower is off by 1e-3 writes an artifact the same check refuses."""
    meta_t, torch_feats = _extract(tmp_path, tiny_scene_dir, tiny_ckpt, "torch")
    assert meta_t["runtime"]["runtime"] == "torch"
    for runtime in ("onnxruntime", "openvino", "auto"):
        meta, feats = _extract(tmp_path, tiny_scene_dir, tiny_ckpt, runtime)
        assert meta["runtime"]["runtime"] in runtimes.BACKENDS
        if runtime != "auto":
            assert meta["runtime"]["runtime"] == runtime
        else:
            assert meta["runtime"]["reason"] and meta["runtime"]["crops"] > 0
        assert meta["crops"]["encoded"] > 0
        assert _worst(torch_feats, feats) <= choosing.MAX_ABS_DIFF
    # negative control: the ONNX Runtime backend with a tower that drifts
    from ptovs.encoders.runtimes import ort

    real_load = ort.OnnxRuntime.load

    def drifting(self, module, example, key, threads):
        run = real_load(self, module, example, key, threads)
        return lambda x: run(x) + np.float32(0.05)

    monkeypatch.setattr(ort.OnnxRuntime, "load", drifting)
    _, bad = _extract(tmp_path / "bad", tiny_scene_dir, tiny_ckpt, "onnxruntime")
    assert _worst(torch_feats, bad) > choosing.MAX_ABS_DIFF


def test_preflight_refuses_a_named_runtime_that_is_not_installed(monkeypatch):
    """Before anything runs: the backend answers, in the one line of `require`."""
    from ptovs.encoders.runtimes import ov
    from ptovs.preflight import check_extract_config
    from ptovs.stages.extract_features import Config

    monkeypatch.setattr(ov.OpenVino, "missing", lambda self: "openvino: not here")
    config = Config(encoder="openclip", runtime="openvino", clip_checkpoint="x.pt")
    with pytest.raises(InputError, match="openvino: not here"):
        check_extract_config(config)
