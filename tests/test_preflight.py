"""Preflight: what would fail hours into a chain fails before it starts,
as one line naming the file and the fix, and leaves the work dir as it was."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
import torch
from click.testing import CliRunner

from ptovs.cli import main as cli
from ptovs.errors import InputError, MissingInputError

HAS_CLIP = importlib.util.find_spec("open_clip") is not None


def _run(work: Path, *args: str):
    return CliRunner().invoke(cli, ["--work-dir", str(work), *args])


@pytest.mark.skipif(not HAS_CLIP, reason="open_clip not installed (extra [clip])")
def test_a_checkpoint_that_does_not_fit_is_refused_before_anything_runs(
    tiny_scene_dir: Path, tmp_path: Path
) -> None:
    from ptovs.encoders.openclip import OpenClipEncoder, register_tiny
    from ptovs.encoders.openclip_backend import check_openclip

    name = register_tiny()
    net = OpenClipEncoder(name, random_weights=True).net
    good = tmp_path / "good.pt"
    torch.save(net.state_dict(), good)
    check_openclip(name, good)  # fits
    state = net.state_dict()
    key = next(k for k, v in state.items() if v.ndim == 2)
    state[key] = torch.zeros(3, 3)
    bad = tmp_path / "other_model.pt"
    torch.save(state, bad)
    with pytest.raises(InputError, match="of another shape"):
        check_openclip(name, bad)
    junk = tmp_path / "junk.pt"
    junk.write_bytes(b"not a checkpoint")
    with pytest.raises(InputError, match="could not be read"):
        check_openclip(name, junk)
    with pytest.raises(MissingInputError, match="does not exist"):
        check_openclip(name, tmp_path / "nope.pt")
    with pytest.raises(InputError, match="not an OpenCLIP model"):
        check_openclip("ViT-Q-99", good)
    # through the CLI, on a whole chain: one line, nothing written, no traceback
    work = tmp_path / "work"
    r = _run(work, "extract", "--data", str(tiny_scene_dir), "--set",
             "extract-features.encoder=openclip", "--set",
             f"extract-features.clip_model={name}", "--set",
             f"extract-features.clip_checkpoint={bad}")  # fmt: skip
    assert r.exit_code == 1 and str(bad) in r.output and "Traceback" not in r.output
    assert not work.exists()


def test_phrases_views_and_labels_are_checked_first(tiny_scene_dir: Path, tmp_path):
    work = tmp_path / "work"
    data = str(tiny_scene_dir)
    for args, says in (
        (["query", "Not A Part", "--data", data], "not in the synthetic scene's"),
        (["query", "Wall", "--views", "nope.jpg", "--data", data], "no view 'nope.jpg'"),
        (["extract-features", "--data", data, "--set", "segmenter=sam"],
         "sam_checkpoint"),
    ):  # fmt: skip
        r = _run(work, *args)
        assert r.exit_code == 1 and says in r.output, (args, r.output)
        assert "Traceback" not in r.output
        assert not work.exists(), args  # not a fingerprint, lock or part file


def test_unposed_photos_are_checked_before_sfm_poses_them(tiny_scene_dir, tmp_path):
    """A folder of photos: what the features will need is checked before SfM's
    minutes, and a failure writes nothing (not even SfM's lock)."""
    import shutil

    photos = tmp_path / "myphotos"
    photos.mkdir()
    for p in sorted((tiny_scene_dir / "dense" / "images").glob("*.jpg"))[:3]:
        shutil.copy(p, photos / p.name)
    work = tmp_path / "work"
    r = _run(work, "extract", "--data", str(photos))
    assert r.exit_code == 1 and "clip_checkpoint" in r.output, r.output
    r = _run(work, "train", "--data", str(photos), "--set",
             f"extract-features.clip_checkpoint={tmp_path / 'nope.pt'}")  # fmt: skip
    assert r.exit_code == 1 and "nope.pt" in r.output, r.output
    assert not work.exists()


ROOT = Path(__file__).resolve().parents[1]


def _checkpoint_table() -> str:
    """The guide's section that every missing-checkpoint error points at (it
    fails here, not in a user's terminal, when the heading is renamed)."""
    from ptovs.encoders.weights import CHECKPOINT_TABLE

    page, title = CHECKPOINT_TABLE.split(", ", 1)
    head = f"### {title.strip(chr(39))}\n"
    text = (ROOT / page).read_text()
    assert head in text, f"{page} has no heading {head!r} ({CHECKPOINT_TABLE})"
    return text.split(head, 1)[1].split("\n## ", 1)[0].split("\n### ", 1)[0]


def test_a_missing_checkpoint_names_the_file_and_the_guides_table(tmp_path):
    from types import SimpleNamespace

    from ptovs.encoders.openclip_backend import check_openclip
    from ptovs.encoders.weights import CHECKPOINT_TABLE
    from ptovs.segment.backend import get_segmenter_backend

    def check_sam_checkpoint(config):
        get_segmenter_backend(config.segmenter).check(config)

    _checkpoint_table()
    cases = [
        (lambda: check_openclip("MobileCLIP2-S0", ""), InputError,
         "open_clip_model.safetensors from Hugging Face timm/MobileCLIP2-S0-OpenCLIP"),
        (lambda: check_openclip("ViT-B-16", tmp_path / "nope.bin", "laion2b-s34b-b88k"),
         MissingInputError, "does not exist"),
        (lambda: check_openclip("ViT-B-16", tmp_path / "nope.bin", "laion2b_s34b_b88k"),
         MissingInputError, "open_clip_pytorch_model.bin from Hugging Face laion/"),
        (lambda: check_openclip("ViT-B-32", ""), InputError, "clip_checkpoint=FILE"),
        (lambda: check_sam_checkpoint(SimpleNamespace(
            segmenter="sam", sam_model="vit_h", sam_checkpoint="")),
         MissingInputError, "take sam_vit_h_4b8939.pth from Meta"),
        (lambda: check_sam_checkpoint(SimpleNamespace(
            segmenter="sam2", sam2_model="tiny", sam_checkpoint=str(tmp_path / "n.pt"))),
         MissingInputError, "take sam2.1_hiera_tiny.pt from Meta"),
    ]  # fmt: skip
    for call, error, says in cases:
        with pytest.raises(error) as e:
            call()
        msg = str(e.value)
        assert says in msg and msg.endswith(f"where to download it: {CHECKPOINT_TABLE}")
        assert "\n" not in msg


def test_the_shipped_configs_expect_the_files_the_guides_table_names():
    """photos-cpu/-gpu's checkpoint paths (SAM 2.1's in a comment) are in the
    table, under the names preflight expects: the file as its publisher names it."""
    import re

    from ptovs.config import load_config
    from ptovs.encoders.openclip_backend import CLIP_FILES
    from ptovs.encoders.openclip_backend import clip_file as _clip_file
    from ptovs.segment.sam import SAM_FILES

    table = _checkpoint_table()
    paths = []
    for name in ("photos-cpu.toml", "photos-gpu.toml"):
        text = (ROOT / "configs" / name).read_text()
        cfg = load_config(ROOT / "configs" / name)["extract-features"]
        clip = cfg["clip_checkpoint"]
        assert (
            Path(clip).name
            == _clip_file(cfg["clip_model"], cfg.get("clip_pretrained", ""))[0]
        ), name
        paths.append(clip)
        if "sam_checkpoint" in cfg:
            assert Path(cfg["sam_checkpoint"]).name == SAM_FILES[cfg["sam_model"]]
            paths.append(cfg["sam_checkpoint"])
        for model, path in re.findall(
            r'# sam2_model = "(\w+)"\n# sam_checkpoint = "([^"]+)"', text
        ):
            assert Path(path).name == f"sam2.1_hiera_{model}.pt", name
            paths.append(path)
    assert len(paths) == 4, paths
    for path in paths:
        assert f"`{path}`" in table, path
    for file, source in CLIP_FILES.values():
        assert f"`{file}`" in table and f"`{source.split()[-1]}`" in table, source
    assert f"`{SAM_FILES['vit_h']}`" in table
