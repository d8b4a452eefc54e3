"""Applications (issue: select, style, roam, batch): PLY selection, style votes,
roaming video, the per-scene table over a data folder."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from conftest import RECON, copy_work
from ptovs.cli import main
from ptovs.field import relevancy as rel
from ptovs.field.ply import read_ply


@pytest.fixture(scope="module")
def app_work(tmp_path_factory, trained_work):
    return copy_work(trained_work[0], tmp_path_factory.mktemp("apps") / "work")


def _cli(work: Path, *args: str):
    return CliRunner().invoke(main, ["--work-dir", str(work), *RECON, *args])


# --------------------------------------------------------- select (unit) --


def test_select_reduces_to_the_single_map_and_respects_valid():
    g = torch.Generator().manual_seed(0)
    s = torch.rand(3, 1, 50, generator=g)
    valid = torch.ones(50, dtype=torch.bool)
    valid[:10] = False
    settings = rel.QuerySettings(background_filter="off")
    out = rel.select(s, None, settings, valid)
    assert not out.mask[:10].any()
    assert np.all(out.scores[:, :10] == 0)
    level = int(torch.argmax((s[:, 0] * valid).amax(1)))
    assert out.level == level
    sl = s[level, 0, 10:].numpy()
    n = (sl - sl.min()) / (sl.max() - sl.min())
    assert np.array_equal(out.mask[10:], 2 * n - 1 > 0.4)


def test_select_background_and_fusion_match_the_pixel_pipeline():
    """Gaussians in place of pixels: the same weights and filter as `finish`."""
    g = torch.Generator().manual_seed(1)
    s = torch.rand(2, 4, 30, generator=g)
    b = torch.rand(2, 4, 30, generator=g)
    settings = rel.QuerySettings(smooth_kernel=1, majority=1)
    got = rel.select(s, b, settings)
    ref = rel.finish(s[..., None], b[..., None], settings)  # a 30 × 1 "image"
    assert np.allclose(got.scores, ref.smoothed[..., 0], atol=1e-6)
    assert got.level == ref.level
    assert np.array_equal(got.mask, ref.mask[:, 0])


def test_select_hard_cases_are_finite_and_empty_when_nothing_is_valid():
    s = torch.tensor([[[0.0, 1e30, float("nan"), 0.5]]]).clamp(0, 1).nan_to_num(0.5)
    out = rel.select(s, None, rel.QuerySettings(background_filter="off"))
    assert np.isfinite(out.scores).all() and out.mask.any()
    const = rel.select(torch.full((2, 2, 9), 0.3), None, rel.QuerySettings())
    assert not const.mask.any()  # a constant score selects nothing
    none = rel.select(torch.rand(1, 1, 5), None, rel.QuerySettings(),
                      torch.zeros(5, dtype=torch.bool))  # fmt: skip
    assert not none.mask.any() and none.score == 0.0
    empty = rel.select(torch.zeros(2, 1, 0), None, rel.QuerySettings())
    assert empty.mask.shape == (0,)


def test_select_smoothing_over_neighbours():
    """Self-only neighbours change nothing; a lone high score among low-scoring
    neighbours is averaged away; a constant score stays constant."""
    g = torch.Generator().manual_seed(2)
    s = torch.rand(2, 1, 40, generator=g)
    settings = rel.QuerySettings(background_filter="off")
    plain = rel.select(s, None, settings)
    own = rel.select(s, None, settings, neighbors=torch.arange(40)[:, None])
    assert np.array_equal(plain.mask, own.mask) and np.allclose(
        plain.scores, own.scores
    )
    spike = torch.full((1, 1, 40), 0.1)
    spike[0, 0, 5] = 1.0  # one outlier ...
    spike[0, 0, 20:30] = 0.6  # ... and a coherent patch
    nbr = torch.tensor([[i, (i + 1) % 40, (i - 1) % 40] for i in range(40)])
    out = rel.select(spike, None, settings, neighbors=nbr)
    assert not out.mask[5] and out.mask[21:29].all()
    assert rel.select(spike, None, settings).mask[5]  # without smoothing it wins
    const = rel.select(torch.full((1, 1, 40), 0.3), None, settings, neighbors=nbr)
    assert np.allclose(const.scores, 0.3)
    with pytest.raises(ValueError, match="neighbors"):
        rel.select(spike, None, settings, neighbors=nbr[:10])


def test_nearest_gaussians_are_exact_and_skip_invalid_ones():
    from ptovs.field.query import nearest_gaussians

    g = torch.Generator().manual_seed(4)
    means = torch.randn(300, 3, generator=g)
    valid = torch.rand(300, generator=g) > 0.3
    nbr = nearest_gaussians(means, valid, 8)
    idx = torch.nonzero(valid).squeeze(1)
    d = torch.cdist(means[idx], means[idx])
    ref = idx[d.topk(8, largest=False).indices]
    assert torch.equal(nbr[idx].sort(1).values, ref.sort(1).values)
    assert (nbr[idx, 0] == idx).all()  # itself first
    assert valid[nbr[idx]].all()  # only valid neighbours
    inv = torch.nonzero(~valid).squeeze(1)
    assert (nbr[inv] == inv[:, None]).all()
    few = nearest_gaussians(means, torch.arange(300) < 3, 8)
    assert few.shape == (300, 3)
    assert (
        nearest_gaussians(means, torch.zeros(300, dtype=torch.bool), 8).shape[0] == 300
    )
    bad = means.clone()
    bad[0] = float("nan")
    with pytest.raises(FloatingPointError):
        nearest_gaussians(bad, torch.ones(300, dtype=torch.bool), 4)


# ---------------------------------------------------------- select (CLI) --


def test_select_ply_holds_exactly_the_selected_gaussians(
    app_work, tiny_scene_dir, tmp_path
):
    from ptovs.apps import close_inputs
    from ptovs.apps.select import select_gaussians
    from ptovs.chain import Chain, RunContext
    from ptovs.locate import resolve_scene

    out, rest = tmp_path / "sel.ply", tmp_path / "rest.ply"
    res = _cli(app_work, "select", "Brick Facade", "--data", str(tiny_scene_dir),
               "--out", str(out), "--rest", str(rest))  # fmt: skip
    assert res.exit_code == 0, res.output + repr(res.exception)
    rec = json.loads(out.with_suffix(".json").read_text())
    sel, rst = read_ply(out), read_ply(rest)
    assert len(sel["means"]) == rec["selected"] > 0
    assert len(sel["means"]) + len(rst["means"]) == rec["gaussians"]
    assert f"{rec['selected']} of {rec['gaussians']} Gaussians" in res.output
    # the very Gaussians the selection chose, in order, with their parameters
    from ptovs.config import parse_sets

    sets = parse_sets([r.split("=", 1)[1] for r in RECON])  # "--set=a.b=c" → a.b=c
    ctx = RunContext(app_work, sets, False)
    chain = Chain(ctx, resolve_scene(ctx, None, tiny_scene_dir))
    selection, querier, inputs = select_gaussians(chain, "Brick Facade")
    means = inputs.reconstruct.root()["means"]
    close_inputs(inputs)
    assert np.array_equal(sel["means"], means[selection.mask].astype(np.float32))
    assert np.array_equal(rst["means"], means[~selection.mask].astype(np.float32))
    assert np.isfinite(sel["sh"]).all() and sel["sh"].shape[1] == 16
    # the selection leans to the wall by the world's truth (nearest truth surface
    # sample): a larger share of the selected Gaussians than of the whole field.
    # Measured on this CI field (300 reconstruct iterations): 0.40 of 538
    # selected against 0.32 of all 715. The tiny scene's select figures are
    # weak since the generator's answerability screen redrew its column and
    # roof textures; the instrument's figures are in docs/results.md.
    from ptovs.synthetic.generate import nearest_parts

    truth = json.loads((tiny_scene_dir / "synthetic/truth/parts.json").read_text())
    wall = next(p["id"] for p in truth["parts"] if p["query"] == "Brick Facade")
    pid, _ = nearest_parts(tiny_scene_dir, sel["means"])
    every, _ = nearest_parts(tiny_scene_dir, means)
    assert float(np.mean(pid == wall)) > float(np.mean(every == wall)) + 0.04
    # the 3-D gate and smoothing: visibility is a blend weight, the gated and
    # smoothed selection keeps to the selectable Gaussians and still finds the wall
    from ptovs.field.query import SelectOptions

    vis = querier.visibility()
    assert vis.shape == (len(means),) and torch.isfinite(vis).all()
    assert float(vis.min()) >= 0 and float(vis.max()) <= 1 and float(vis.max()) > 0.5
    opt = SelectOptions(min_visibility=0.05, smooth=8)
    gated = querier.select("Brick Facade", opt)
    assert gated.mask.any() and not gated.mask[(vis < 0.05).numpy()].any()
    res2 = _cli(app_work, "select", "Brick Facade", "--data", str(tiny_scene_dir),
                "--out", str(tmp_path / "g.ply"), "--min-visibility", "0.05",
                "--smooth", "8")  # fmt: skip
    assert res2.exit_code == 0, res2.output + repr(res2.exception)
    assert json.loads((tmp_path / "g.json").read_text())["selected"] == gated.mask.sum()


def test_nearest_parts_reads_the_world_truth(tiny_scene_dir):
    """The truth `select` is scored against (docs/results.md, applications): dense samples
    of every surface the cameras see; each tracked point (points3D, another
    sample of the same surfaces) maps to its own part, a far point to -2."""
    from ptovs.synthetic.generate import nearest_parts

    pts = np.load(tiny_scene_dir / "synthetic/truth/points3D.npz")
    pid, dist = nearest_parts(tiny_scene_dir, pts["xyz"][::7])
    assert np.array_equal(pid, pts["part_id"][::7]) and np.all(dist < 1e-5)
    far, _ = nearest_parts(tiny_scene_dir, np.array([[1e3, 1e3, 1e3]]))
    assert far.tolist() == [-2]
    from ptovs.synthetic.generate import surface_samples

    xyz, part = surface_samples(tiny_scene_dir.resolve())
    truth = json.loads((tiny_scene_dir / "synthetic/truth/parts.json").read_text())
    assert len(xyz) > 10 * len(pts["xyz"]) and np.isfinite(xyz).all()
    assert set(np.unique(part).tolist()) == {-1} | {p["id"] for p in truth["parts"]}


def test_empty_selection_is_a_clear_error_and_writes_nothing(
    app_work, tiny_scene_dir, tmp_path
):
    out = tmp_path / "none.ply"
    res = _cli(app_work, "select", "Brick Facade", "--data", str(tiny_scene_dir),
               "--out", str(out), "--min-visibility", "1.0")  # fmt: skip
    # (a blend weight is alpha x transmittance, alpha at most 0.99: none reaches 1)
    assert res.exit_code != 0
    assert "no Gaussian" in res.output and "nothing written" in res.output
    assert not out.exists()
    res = _cli(app_work, "select", "Hanging Gardens", "--data", str(tiny_scene_dir),
               "--out", str(out))  # fmt: skip
    assert res.exit_code != 0 and "vocabulary" in res.output


# ------------------------------------------------------------------ style --


def test_style_vocabulary_describes_the_whole_landmark(tiny_scene_dir):
    """The true style's text side is the landmark's look: the stand-in encoder,
    shown the landmark alone (its mask over the photo), prefers it over the
    distractor styles (other seeds' landmarks) in most photos."""
    from ptovs.encoders import prepare_crop, scene_encoder

    truth = json.loads((tiny_scene_dir / "synthetic/truth/parts.json").read_text())
    enc = scene_encoder(tiny_scene_dir)
    assert sorted(enc.styles) == enc.styles == truth["style_candidates"]
    assert truth["style"] in enc.styles and len(enc.styles) == 5
    text = enc.encode_texts(enc.styles)
    wins = []
    for jpg in sorted((tiny_scene_dir / "dense/images").glob("*.jpg")):
        img = cv2.cvtColor(cv2.imread(str(jpg)), cv2.COLOR_BGR2RGB) / 255.0
        part = np.load(tiny_scene_dir / "synthetic/truth" / f"{jpg.stem}.npz")[
            "part_id"
        ]
        crop = prepare_crop(img.astype(np.float32), part >= 0)
        wins.append(enc.styles[int(np.argmax(enc.encode_images(crop[None]) @ text.T))])
    assert wins.count(truth["style"]) > len(wins) / 2


def test_style_votes_table_json_and_pictures(app_work, tiny_scene_dir, tmp_path):
    out = tmp_path / "style"
    res = _cli(app_work, "style", "--data", str(tiny_scene_dir), "--images", "6",
               "--pictures", "2", "--out", str(out))  # fmt: skip
    assert res.exit_code == 0, res.output + repr(res.exception)
    rec = json.loads((out / "style.json").read_text())
    truth = json.loads((tiny_scene_dir / "synthetic/truth/parts.json").read_text())
    assert rec["candidates"] == truth["style_candidates"]
    assert len(rec["views"]) == 6 and sum(rec["votes"].values()) == 6
    # the field, queried with the candidate styles, puts the true one in its top
    # two on average (tiny_s0 since the answerability screen redrew two textures:
    # the 300-iteration test field votes Georgian on every view with Art Deco,
    # the truth, second at 0.43 against 0.45, where the photos' own 2-D crops
    # vote Art Deco on 10 of 13)
    mean = {
        s: np.mean([v["values"][s] for v in rec["views"]]) for s in rec["candidates"]
    }
    assert truth["style"] in sorted(mean, key=lambda s: -mean[s])[:2]
    assert rec["winner"] == rec["ranking"][0] and set(rec["ranking"]) == set(
        rec["votes"]
    )
    for v in rec["views"]:  # each view voted for its highest value (ties: first)
        vals = [v["values"][s] for s in rec["candidates"]]
        assert v["vote"] == rec["candidates"][int(np.argmax(vals))]
    assert len(rec["pictures"]) == 2 and all(Path(p).is_file() for p in rec["pictures"])
    assert "| style | votes | share |" in res.output
    # the same again gives the same votes (seeded views, deterministic pipeline)
    res2 = _cli(app_work, "style", "--data", str(tiny_scene_dir), "--images", "6",
                "--pictures", "0", "--out", str(tmp_path / "again"))  # fmt: skip
    assert (
        json.loads((tmp_path / "again/style.json").read_text())["votes"] == rec["votes"]
    )
    assert res2.exit_code == 0


def test_landmark_swatch_is_a_segment_crop_of_the_whole_landmark(tiny_scene_dir):
    from ptovs.synthetic.generate import STYLE_AZIMUTHS
    from ptovs.synthetic.world import render_swatch

    enc_vocab = json.loads((tiny_scene_dir / "synthetic/vocabulary.json").read_text())
    truth = json.loads((tiny_scene_dir / "synthetic/truth/parts.json").read_text())
    look = enc_vocab["styles"][truth["style"]]
    assert [item["swatch"]["azimuth"] for item in look] == list(STYLE_AZIMUTHS)
    assert abs(sum(item["weight"] for item in look) - 1.0) < 1e-5
    world = look[0]["swatch"]["world"]  # the landmark's own geometry, names blanked
    assert [p["primitive"] for p in world["parts"]] == [
        p["primitive"] for p in truth["parts"]
    ]
    assert all(p["name"] == p["query"] == "" for p in world["parts"])
    img = render_swatch(look[1]["swatch"], 96)
    assert img.shape == (96, 96, 3) and img.dtype == np.float32
    assert np.isfinite(img).all() and 0 <= img.min() and img.max() <= 1
    inside = img.max(axis=2) > 0
    # a square crop of the landmark's box: it touches two opposite sides, and
    # sky and ground are black (outside the mask) around it
    assert inside[:, 0].any() or inside[0].any()
    assert 0.2 < inside.mean() < 1.0
    assert np.array_equal(img, render_swatch(look[1]["swatch"], 96))  # deterministic
    bad = dict(look[1]["swatch"], azimuth=180.0)
    bad["world"] = dict(world, center=[0.0, 1e6, 0.0])  # looking away from it
    with pytest.raises(ValueError, match="not in view"):
        render_swatch(bad, 32)


def test_style_vote_rules():
    from ptovs.apps.style import vote_of
    from ptovs.stages.query import Config

    r = [rel.QueryResult(np.zeros((1, 2, 2), np.float32), 0, 0.5, np.zeros((2, 2), bool)),
         rel.QueryResult(np.ones((1, 2, 2), np.float32), 0, 0.5, np.ones((2, 2), bool))]  # fmt: skip
    assert vote_of(r, ["A", "B"], "max_score", Config())[0] == "A"  # tie: first
    sm = np.zeros((1, 2, 2), np.float32)
    sm[0, 0, 0] = 1.0
    r[1] = rel.QueryResult(sm, 0, 0.5, sm[0] > 0)
    winner, counts = vote_of(r, ["A", "B"], "pixel_count", Config())
    assert winner == "B" and counts == [0.0, 1.0]  # a constant map has no positives


def test_style_needs_candidates_on_a_real_scene(app_work, scene_copy):
    shutil.rmtree(scene_copy / "synthetic")
    res = _cli(app_work, "style", "--data", str(scene_copy))
    assert res.exit_code != 0


# ------------------------------------------------------------------- roam --


def test_roam_writes_the_requested_frames(app_work, tiny_scene_dir, tmp_path):
    out = tmp_path / "tour.mp4"
    res = _cli(app_work, "roam", "Brick Facade", "--data", str(tiny_scene_dir),
               "--out", str(out), "--frames", "12", "--size", "96x64")  # fmt: skip
    assert res.exit_code == 0, res.output + repr(res.exception)
    cap = cv2.VideoCapture(str(out))
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame)
    cap.release()
    rec = json.loads(out.with_suffix(".json").read_text())
    assert len(frames) == 12 == rec["frames"]
    assert frames[0].shape[:2] == (rec["height"], 96)
    res = _cli(app_work, "roam", "Brick Facade", "--data", str(tiny_scene_dir),
               "--out", str(out), "--size", "nope")  # fmt: skip
    assert res.exit_code != 0 and "WIDTHxHEIGHT" in res.output


def test_camera_path_passes_through_the_keyframes(tiny_scene_dir):
    from ptovs.apps.roam import camera_path, pick_keyframes
    from ptovs.scene import load_scene

    scene = load_scene(tiny_scene_dir)
    keys = pick_keyframes(scene.train_views(), 4, np.median(scene.points_xyz, 0))
    assert len({v.name for v in keys}) == 4
    cams = camera_path(keys, 7, 64, 48)  # s = 0, 0.5, 1, ..., 3
    for i, key in enumerate(keys):
        got = cams[2 * i].cam_from_world.double().numpy()
        assert np.allclose(got[:3, :3], key.cam_from_world[:3, :3], atol=1e-5)
        assert np.allclose(got[:3, 3], key.cam_from_world[:3, 3], atol=1e-4)
    for a, b in zip(cams, cams[1:], strict=False):  # no jumps between frames
        assert np.linalg.norm(a.cam_from_world[:3, 3] - b.cam_from_world[:3, 3]) < 5


# ------------------------------------------------------------------ table --


def test_table_of_one_scene_folder_is_that_scenes_column(tiny_scene_dir, tmp_path):
    """`--data` given one scene (not the folder of scenes) tables that scene, as
    the folder of scenes does; its own subfolders are not scenes."""
    work = tmp_path / "work"
    one = _cli(work, "table", "--data", str(tiny_scene_dir))
    assert one.exit_code == 0, one.output + repr(one.exception)
    assert "| variant | tiny_s0 | mean |" in one.output
    for sub in ("dense", "synthetic", "failed"):
        assert sub not in one.output, one.output
    every = _cli(work, "table", "--data", str(tiny_scene_dir.parent))
    assert every.exit_code == 0 and every.output == one.output
    # a failed scene shows as failed, and --strict says so with its status
    (work / "tiny_s0").mkdir(parents=True, exist_ok=True)
    (work / "tiny_s0" / "FAILED").write_text("log\nreconstruct failed: out of memory\n")
    failed = _cli(work, "table", "--data", str(tiny_scene_dir), "--strict")
    assert failed.exit_code == 1
    assert "| male | failed | – |" in failed.output
    assert "tiny_s0: failed (reconstruct failed: out of memory)" in failed.output


def test_a_scene_folder_is_told_from_a_folder_of_scenes(tmp_path):
    from ptovs.apps.table import is_scene, table_scenes

    photos = tmp_path / "fountain"
    photos.mkdir()
    for i in range(3):
        (photos / f"p{i}.jpg").write_bytes(b"x")
    assert is_scene(photos) and table_scenes(photos) == [photos]
    scenes = tmp_path / "scenes"
    for name in ("a", "b"):
        (scenes / name / "dense" / "sparse").mkdir(parents=True)
    (scenes / "label" / "a").mkdir(parents=True)
    (scenes / "cover.jpg").write_bytes(b"x")  # a stray photo beside posed scenes
    assert not is_scene(scenes)
    assert table_scenes(scenes) == [scenes / "a", scenes / "b"]
    assert is_scene(scenes / "a") and table_scenes(scenes / "a") == [scenes / "a"]
