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
    from ptovs.preflight import check_openclip

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
