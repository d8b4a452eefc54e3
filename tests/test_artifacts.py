"""Artifact keys, atomic writes, verification and resumable shards."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import h5py
import numpy as np
import pytest

from ptovs.artifacts import Artifact, CorruptArtifact, Store
from ptovs.config import build_config, canonical_json, parse_sets
from ptovs.errors import InputError
from ptovs.keys import artifact_key


@dataclasses.dataclass(frozen=True)
class Cfg:
    tau: float = 0.9
    levels: tuple[int, ...] = (1, 2, 3)
    mode: str = "paper"


def test_key_is_deterministic_and_sensitive():
    k = artifact_key("uncertainty", 1, Cfg(), {"features": "a" * 64})
    assert k == artifact_key("uncertainty", 1, Cfg(), {"features": "a" * 64})
    assert len(k) == 64 and int(k, 16) >= 0
    others = {
        artifact_key("uncertainty", 1, Cfg(tau=0.85), {"features": "a" * 64}),  # config
        artifact_key("uncertainty", 2, Cfg(), {"features": "a" * 64}),  # VERSION
        artifact_key("uncertainty", 1, Cfg(), {"features": "b" * 64}),  # upstream
        artifact_key("train-ae", 1, Cfg(), {"features": "a" * 64}),  # stage
    }
    assert k not in others and len(others) == 4
    # a config given as a mapping keys the same as the dataclass
    assert k == artifact_key(
        "uncertainty",
        1,
        {"mode": "paper", "levels": [1, 2, 3], "tau": 0.9},
        {"features": "a" * 64},
    )


def test_canonical_json():
    assert canonical_json({"b": 1, "a": (0.1, 2)}) == '{"a":[0.1,2],"b":1}'
    assert canonical_json({"x": np.float32(0.5)}) == '{"x":0.5}'
    with pytest.raises(ValueError):
        canonical_json({"x": float("nan")})


def test_build_config_and_sets():
    sets = parse_sets(["tau=0.85", "levels=[1, 2]", "mode=code"], "unc")
    cfg = build_config(Cfg, sets["unc"], "unc")
    assert cfg == Cfg(tau=0.85, levels=(1, 2), mode="code")
    assert build_config(Cfg, {"tau": 1}, "unc").tau == 1.0  # int → float
    with pytest.raises(
        InputError, match="has no key .tua. .did you mean .tau.*valid keys"
    ):
        build_config(Cfg, {"tua": 0.5}, "unc")
    with pytest.raises(InputError, match="expected a number"):
        build_config(Cfg, {"tau": "high"}, "unc")
    with pytest.raises(InputError, match="needs its section"):
        parse_sets(["tau=1"])
    assert parse_sets(["scene.downscale=2", "a.b.c=x y"]) == {
        "scene": {"downscale": 2},
        "a": {"b": {"c": "x y"}},
    }


def _write(store: Store, key: str, views: dict[str, np.ndarray]) -> Artifact:
    w = store.writer(
        "sc", "st", key, {"version": 1, "config_json": "{}", "inputs_json": "{}"}
    )
    for name, arr in views.items():
        w.write_view(name, {"x": arr, "seg": np.arange(5000, dtype=np.int16)})
    w.write_root({"total": np.float64(3.5)})
    return w.finish()


def test_roundtrip_and_layout(tmp_path: Path):
    store = Store(tmp_path)
    key = "ab" * 32
    views = {
        "a/b.jpg": np.ones((3, 4), np.float32),
        "c.jpg": np.zeros((2,), np.float16),
    }
    art = _write(store, key, views)
    assert art.path == tmp_path / "sc" / "st" / f"{key[:12]}.h5"
    assert art.names() == ["a/b.jpg", "c.jpg"]
    np.testing.assert_array_equal(art["a/b.jpg"]["x"], views["a/b.jpg"])
    assert art["c.jpg"]["x"].dtype == np.float16
    assert art.root()["total"] == 3.5
    assert art.attrs["key"] == key and art.attrs["n_views"] == 2
    art.close()
    assert not list((tmp_path / "sc" / "st").glob("*.parts"))  # shards merged away
    again = store.lookup("sc", "st", key)
    assert again is not None and again.names() == ["a/b.jpg", "c.jpg"]
    again.close()
    assert store.lookup("sc", "st", "cd" * 32) is None


def test_nan_never_reaches_an_artifact(tmp_path: Path):
    w = Store(tmp_path).writer("sc", "st", "ef" * 32, {})
    with pytest.raises(ValueError, match="NaN"):
        w.write_view("v", {"x": np.array([1.0, np.nan])})
    assert w.done_views() == set()


@pytest.mark.parametrize("damage", ["flip", "truncate", "garbage"])
def test_corrupt_artifact_is_detected(tmp_path: Path, damage: str):
    store = Store(tmp_path)
    key = "12" * 32
    big = np.random.default_rng(0).random((64, 64)).astype(np.float32)
    art = _write(store, key, {"v": big})
    path = art.path
    art.close()
    raw = bytearray(path.read_bytes())
    if damage == "flip":  # flip bytes inside the float data, keep HDF5 structure
        needle = big.tobytes()[:64]
        at = bytes(raw).find(needle)
        assert at > 0
        raw[at + 10] ^= 0xFF
    elif damage == "truncate":
        raw = raw[: len(raw) // 2]
    else:
        raw = bytearray(b"not hdf5 at all" * 10)
    path.write_bytes(bytes(raw))
    with pytest.raises(CorruptArtifact):
        Artifact(path)
    assert store.lookup("sc", "st", key) is None  # reported, moved aside
    assert not path.exists() and path.with_name(path.name + ".corrupt").exists()


@pytest.mark.parametrize("attr", ["key", "config_json", "inputs_json", "stage"])
def test_changed_identity_attributes_are_corruption(tmp_path: Path, attr: str):
    """Key, config and inputs are under the identity digest: changed by hand, the
    artifact is moved aside like a failed checksum, and `exists` (what `status`
    reads) no longer says done. Timings are not: they may change freely."""
    store = Store(tmp_path)
    key = "34" * 32
    path = _write(store, key, {"v": np.ones(3, np.float32)}).path
    with h5py.File(path, "a") as h5:
        h5.attrs["timings_json"] = '{"run_s": 99}'
    assert store.exists("sc", "st", key)
    art = store.lookup("sc", "st", key)
    assert art is not None
    art.close()
    with h5py.File(path, "a") as h5:
        h5.attrs[attr] = ("56" * 32) if attr == "key" else '{"tampered": 1}'
    assert not store.exists("sc", "st", key)
    assert store.lookup("sc", "st", key) is None
    assert not path.exists() and path.with_name(path.name + ".corrupt").exists()


def test_an_artifact_under_another_keys_name_is_moved_aside(tmp_path: Path):
    store = Store(tmp_path)
    a, b = "78" * 32, "9a" * 32
    src = _write(store, a, {"v": np.ones(3, np.float32)}).path
    dst = store.path("sc", "st", b)
    src.rename(dst)  # copied or renamed by hand
    assert not store.exists("sc", "st", b)
    assert store.lookup("sc", "st", b) is None  # no RuntimeError
    assert dst.with_name(dst.name + ".corrupt").exists()


def test_partial_write_resumes_and_discards_damage(tmp_path: Path):
    store = Store(tmp_path)
    key = "34" * 32
    w = store.writer("sc", "st", key, {})
    w.write_view("v1", {"x": np.ones(3)})
    w.write_view("v2", {"x": np.ones(3)})
    parts = store.path("sc", "st", key).with_suffix(".parts")
    # an interrupted shard write leaves a .tmp: ignored; a damaged shard: dropped
    (parts / "v3.h5.tmp").write_bytes(b"half")  # the name before random names
    (parts / ".v3.h5.0123456789ab.tmp").write_bytes(b"half")
    stale_final = store.path("sc", "st", key).with_name(
        f".{key[:12]}.h5.0123456789ab.tmp"
    )  # an interrupted finish()
    stale_final.write_bytes(b"half")
    (parts / "v4.h5").write_bytes(b"broken")
    with h5py.File(parts / "v5.h5", "w") as h5:  # written by a different key
        h5.attrs["key"] = "other"
        h5.attrs["complete"] = True
    assert not store.path("sc", "st", key).exists()  # nothing final before finish()
    assert store.partial_views("sc", "st", key) == 4
    w2 = store.writer("sc", "st", key, {})
    assert w2.done_views() == {"v1", "v2"}
    assert sorted(p.name for p in parts.iterdir()) == ["v1.h5", "v2.h5"]
    assert not stale_final.exists()
    w2.write_view("v3", {"x": np.zeros(3)})
    art = w2.finish()
    assert art.names() == ["v1", "v2", "v3"]
    art.close()


def test_store_writes_never_follow_a_planted_link(tmp_path: Path):
    """Links planted at the old predictable temporary names (shard `<view>.h5.tmp`,
    final `<key12>.h5.tmp`, checkpoint `last.pt.<pid>.tmp`, memo cache
    `<cache>.<pid>.tmp`) and at the final names are never written through."""
    import os

    import torch

    from ptovs.checkpoint import Checkpoint
    from ptovs.keys import fingerprint_files

    victim = tmp_path / "victim"
    victim.write_bytes(b"precious")
    store = Store(tmp_path / "work")
    key = "56" * 32
    final = store.path("sc", "st", key)
    parts = final.with_suffix(".parts")
    parts.mkdir(parents=True)
    pid = os.getpid()
    for link in (
        parts / "v1.h5.tmp",
        parts / "v2.h5",  # a final name: replaced (and as a damaged shard, dropped)
        final.with_name(final.name + ".tmp"),
        final.with_name(final.name + f".{pid}.tmp"),
    ):
        link.symlink_to(victim)
    w = store.writer("sc", "st", key, {})
    w.write_view("v1", {"x": np.ones(3)})
    w.write_view("v2", {"x": np.zeros(3)})
    art = w.finish()
    assert art.names() == ["v1", "v2"] and not art.path.is_symlink()
    art.close()
    ck = Checkpoint(tmp_path / "x.ckpt", "k")
    ck.folder.mkdir()
    (ck.folder / f"last.pt.{pid}.tmp").symlink_to(victim)
    ck.path.symlink_to(victim)
    ck.save({"w": torch.ones(2)})
    assert not ck.path.is_symlink() and torch.equal(ck.load()["w"], torch.ones(2))
    photo = tmp_path / "p.jpg"
    photo.write_bytes(b"jpeg")
    cache = tmp_path / "cache.json"
    cache.with_name(f"cache.json.{pid}.tmp").symlink_to(victim)
    fingerprint_files([photo], tmp_path, cache)
    assert str(photo) in cache.read_text()
    assert victim.read_bytes() == b"precious"
    left = [
        p.name for p in tmp_path.rglob("*") if ".tmp" in p.name and not p.is_symlink()
    ]
    assert left == []  # no temporary file of ours is left behind


def test_a_planted_link_at_a_lock_is_refused(tmp_path):
    from ptovs.artifacts import Store
    from ptovs.errors import InputError

    store = Store(tmp_path / "work")
    victim = tmp_path / "victim"
    victim.write_text("keep")
    lock = store.path("s", "stage", "k" * 64).with_suffix(".lock")
    lock.parent.mkdir(parents=True)
    lock.symlink_to(victim)
    with pytest.raises(InputError, match="symbolic link"):
        with store.lock("s", "stage", "k" * 64):
            pass
    assert victim.read_text() == "keep"
