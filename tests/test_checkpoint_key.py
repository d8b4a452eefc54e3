"""A model file a config names enters its stage's key by content (`keys.MODEL_FILES`):
a fine-tuned checkpoint at the original's path gives new keys, a touched one the
same key without hashing it on every command, and configs without model files keep
the keys they had."""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from ptovs import keys
from ptovs.chain import Chain, RunContext
from ptovs.cli import main as cli
from ptovs.config import load_config
from ptovs.keys import MODEL_FILES, artifact_key
from ptovs.locate import resolve_scene
from ptovs.registry import REGISTRY, all_stages, config_class, scene_input

ROOT = Path(__file__).resolve().parents[1]


def _chain(work: Path, scene: Path, config: dict) -> Chain:
    ctx = RunContext(work, config)
    return Chain(ctx, resolve_scene(ctx, None, scene))


def _bump(path: Path, seconds: int = 10) -> None:
    """A later mtime, as any rewrite gives (set, not waited for: some file systems
    keep whole-tick times, and a rewrite in the same tick would look untouched)."""
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + seconds * 10**9))


@pytest.fixture
def hashed(monkeypatch: pytest.MonkeyPatch) -> list[Path]:
    """Every file `keys.file_sha256` reads, in order."""
    seen: list[Path] = []
    real = keys.file_sha256

    def counting(path: Path) -> str:
        seen.append(Path(path))
        return real(path)

    monkeypatch.setattr(keys, "file_sha256", counting)
    return seen


def test_same_path_new_content_is_a_new_key_touch_is_not(
    tiny_scene_dir: Path, tmp_path: Path, hashed: list[Path]
):
    ckpt = tmp_path / "ckpt" / "model.safetensors"
    ckpt.parent.mkdir()
    ckpt.write_bytes(b"\x01" * 4096)
    work = tmp_path / "work"
    config = {"extract-features": {"clip_checkpoint": str(ckpt)}}
    first = _chain(work, tiny_scene_dir, config)
    k1 = {s: first.key(s) for s in ("extract-features", "train-ae", "query")}
    assert first.deps("extract-features")["file:clip_checkpoint"] not in (
        "missing",
        "unreadable",
    )
    assert hashed.count(ckpt.resolve()) == 1
    # another command, nothing changed: the cached digest, no second read
    again = _chain(work, tiny_scene_dir, config)
    assert {s: again.key(s) for s in k1} == k1
    assert hashed.count(ckpt.resolve()) == 1
    # touched, same bytes: read once more (its mtime moved), same keys
    _bump(ckpt)
    touched = _chain(work, tiny_scene_dir, config)
    assert {s: touched.key(s) for s in k1} == k1
    assert hashed.count(ckpt.resolve()) == 2
    assert (
        _chain(work, tiny_scene_dir, config).key("extract-features")
        == k1["extract-features"]
    )
    assert hashed.count(ckpt.resolve()) == 2  # the new mtime is cached in turn
    # fine-tuned: same path, same size, other bytes → every key downstream moves
    ckpt.write_bytes(b"\x02" * 4096)
    _bump(ckpt, 20)
    tuned = _chain(work, tiny_scene_dir, config)
    k2 = {s: tuned.key(s) for s in k1}
    assert all(k2[s] != k1[s] for s in k1), (k1, k2)


def test_a_tokenizer_folder_digests_its_files(tiny_scene_dir: Path, tmp_path: Path):
    tok = tmp_path / "tokenizer"
    (tok / "sub").mkdir(parents=True)
    (tok / "tokenizer.json").write_text('{"a": 1}')
    (tok / "sub" / "vocab.txt").write_text("a\nb\n")
    config = {"extract-features": {"clip_tokenizer": str(tok)}}
    k1 = _chain(tmp_path / "w", tiny_scene_dir, config).key("extract-features")
    (tok / "sub" / "vocab.txt").write_text("a\nc\n")
    _bump(tok / "sub" / "vocab.txt")
    k2 = _chain(tmp_path / "w", tiny_scene_dir, config).key("extract-features")
    (tok / "extra.txt").write_text("")
    k3 = _chain(tmp_path / "w", tiny_scene_dir, config).key("extract-features")
    assert len({k1, k2, k3}) == 3


def test_configs_without_model_files_keep_their_keys(tiny_scene_dir: Path, tmp_path):
    """The demo's and CI's keys are what they were before content digests: every
    stage's key is still artifact_key(name, VERSION, config, upstream + extra)."""
    from ptovs.variants import variant_sets

    for name in ("default.toml", "ci.toml", "accuracy.toml"):
        ctx = RunContext(tmp_path / name, load_config(ROOT / "configs" / name))
        ref = resolve_scene(ctx, None, tiny_scene_dir)
        for variant in ("male", "langsplat"):
            chain = Chain(ctx, ref, variant_sets(variant, {}))
            for spec in all_stages():
                config = chain.config(spec.name)
                old = chain.upstream_keys(spec.name)
                if spec.extra_key is not None:
                    extra = spec.extra_key(config, ref)
                    old.update({f"extra:{k}": v for k, v in extra.items()})
                assert chain.deps(spec.name) == old, (name, spec.name)
                want = artifact_key(spec.name, spec.version, config, old)
                assert chain.key(spec.name) == want, (name, variant, spec.name)
    # a shipped config that names a checkpoint: its content (here: missing) counts
    ctx = RunContext(tmp_path / "p", load_config(ROOT / "configs" / "photos-cpu.toml"))
    chain = Chain(ctx, resolve_scene(ctx, None, tiny_scene_dir))
    assert chain.deps("extract-features")["file:clip_checkpoint"] == "missing"


def test_every_declared_model_field_exists_and_none_is_undeclared():
    """MODEL_FILES names real fields; a string field named like a checkpoint, a
    tokenizer, a model folder or a vocabulary in any section is declared there."""
    import re

    from ptovs.registry import section_names

    for section, names in MODEL_FILES.items():
        fields = {f.name for f in dataclasses.fields(config_class(section))}
        assert set(names) <= fields, (section, set(names) - fields)
    pattern = re.compile(r"checkpoint|tokenizer|_dir$|vocab|weights|model_path")
    for section in section_names():
        for f in dataclasses.fields(config_class(section)):
            if isinstance(f.default, str) and pattern.search(f.name):
                assert f.name in MODEL_FILES.get(section, ()), (section, f.name)


def test_a_missing_model_file_does_not_stop_status(tiny_scene_dir: Path, tmp_path):
    nope = tmp_path / "nope.pt"
    r = CliRunner().invoke(cli, ["--work-dir", str(tmp_path / "w"), "--set",
                                 f"extract-features.sam_checkpoint={nope}",
                                 "status", "--data", str(tiny_scene_dir)])  # fmt: skip
    assert r.exit_code == 0, r.output
    assert any(
        ln.strip().startswith("extract-features") for ln in r.output.splitlines()
    )
    assert not (tmp_path / "w").exists()  # status writes no digest cache either


def test_sfm_vocab_tree_content_is_in_the_sfm_key(tmp_path: Path):
    from ptovs.sfm import _photos_key
    from ptovs.sfm_match import SfmConfig

    photo = tmp_path / "photos" / "a.jpg"
    photo.parent.mkdir()
    photo.write_bytes(b"jpeg")
    tree = tmp_path / "tree.bin"
    tree.write_bytes(b"one")
    work = tmp_path / "work"
    plain = _photos_key([photo], photo.parent, work, "s", SfmConfig())
    config = SfmConfig(vocab_tree=str(tree))
    k1 = _photos_key([photo], photo.parent, work, "s", config)
    tree.write_bytes(b"two")
    _bump(tree)
    k2 = _photos_key([photo], photo.parent, work, "s", config)
    assert len({plain, k1, k2}) == 3


@dataclass(frozen=True)
class WeightsConfig:
    weights: str = ""


@dataclass(frozen=True)
class WeightsInputs:
    scene: object = scene_input()


def _run_weights(inputs: WeightsInputs, config: WeightsConfig) -> dict:
    return {"size": np.int64(Path(config.weights).stat().st_size)}


@pytest.fixture
def weights_stage(monkeypatch: pytest.MonkeyPatch):
    """A toy stage whose config names a model file (declared in MODEL_FILES)."""
    from ptovs.stage import stage_command

    command = stage_command("toy-weights", 1, WeightsConfig, WeightsInputs,
                            _run_weights, kind="single")  # fmt: skip
    monkeypatch.setitem(MODEL_FILES, "toy-weights", ("weights",))
    cli.add_command(command)
    yield
    cli.commands.pop("toy-weights", None)
    REGISTRY.pop("toy-weights", None)


def test_status_shows_stale_when_the_checkpoint_changed(
    weights_stage, scene_copy: Path, tmp_path: Path
):
    ckpt = tmp_path / "w.bin"
    ckpt.write_bytes(b"\x00" * 64)
    base = ["--work-dir", str(tmp_path / "work"), "--set",
            f"toy-weights.weights={ckpt}"]  # fmt: skip

    def line() -> str:
        r = CliRunner().invoke(cli, [*base, "status", "--data", str(scene_copy)])
        assert r.exit_code == 0, r.output
        return next(x for x in r.output.splitlines()
                    if x.strip().startswith("toy-weights "))  # fmt: skip

    r = CliRunner().invoke(cli, [*base, "toy-weights", "--data", str(scene_copy)])
    assert r.exit_code == 0, r.output
    assert " done " in line()
    ckpt.write_bytes(b"\x07" * 64)  # fine-tuned in place: same path, same size
    _bump(ckpt)
    stale = line()
    assert " stale " in stale and "model file changed (weights)" in stale, stale
