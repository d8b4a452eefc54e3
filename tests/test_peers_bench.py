"""bench/peers.py without OpenSplat: the project it hands OpenSplat, the two
ways it draws OpenSplat's PLY, the time-to-PSNR reading and the build's refusals. CI
never builds or runs OpenSplat; the benchmark does."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from conftest import bench_module
from ptovs.field.losses import psnr
from ptovs.field.ply import read_ply, write_ply
from ptovs.scene import load_scene


@pytest.fixture(scope="module")
def peers():
    yield from bench_module("peers")


def test_project_holds_the_train_photos_their_cameras_and_every_point(
    peers, tiny_scene_dir, tmp_path
):
    import cv2
    import pycolmap

    scene = load_scene(tiny_scene_dir)
    val = scene.test_views()[0]
    info = peers.export_project(scene, tmp_path / "proj", val)
    train = scene.train_views()
    assert info == {"train": len(train), "points": len(scene.points_xyz),
                    "val_image": f"{val.stem}.png"}  # fmt: skip
    rec = pycolmap.Reconstruction(str(tmp_path / "proj" / "sparse" / "0"))
    assert len(rec.images) == len(train) + 1 and len(rec.points3D) == len(
        scene.points_xyz
    )
    by_name = {im.name: im for im in rec.images.values()}
    for v in [*train, val]:
        im = by_name[f"{v.stem}.png"]
        cam = rec.cameras[im.camera_id]
        assert (cam.width, cam.height) == (v.width, v.height)
        np.testing.assert_allclose(
            cam.params, [v.K[0, 0], v.K[1, 1], v.K[0, 2], v.K[1, 2]]
        )
        np.testing.assert_allclose(
            im.cam_from_world().matrix(), v.cam_from_world[:3], atol=1e-9
        )
    # the pixels both tools train on: ptovs's loader, written losslessly
    png = cv2.imread(str(tmp_path / "proj" / "images" / f"{train[0].stem}.png"))
    assert (
        np.abs(png[..., ::-1] / 255.0 - scene.load_image(train[0])).max()
        <= 0.5 / 255 + 1e-6
    )


def _gaussians(path: Path, means, colours, opacity=0.6, scale=0.05):
    n = len(means)
    sh = np.zeros((n, 16, 3), np.float32)
    sh[:, 0] = (np.asarray(colours, np.float32) - 0.5) / 0.28209479177387814
    write_ply(path, np.asarray(means, np.float32), sh,
              np.full(n, np.log(opacity / (1 - opacity)), np.float32),
              np.full((n, 3), np.log(scale), np.float32),
              np.tile(np.float32([1, 0, 0, 0]), (n, 1)))  # fmt: skip


def _in_front(view, depth, dx=0.0, dy=0.0):
    """A world point `depth` in front of the view's camera, offset in its image plane."""
    m = np.asarray(view.cam_from_world, np.float64)
    return m[:3, :3].T @ (np.array([dx, dy, depth]) - m[:3, 3])


def test_own_reading_draws_separate_gaussians_as_the_rasterizer_does(
    peers, tiny_scene_dir, tmp_path
):
    """Where order cannot matter (no overlap), OpenSplat's image formation as we read
    it and ptovs's rasterizer draw the same picture."""
    scene = load_scene(tiny_scene_dir)
    view = scene.test_views()[0]
    means = [_in_front(view, 4.0, dx, dy) for dx, dy in ((-1, -0.5), (0, 0), (1, 0.5))]
    _gaussians(
        tmp_path / "g.ply", means, [(0.9, 0.2, 0.1), (0.1, 0.8, 0.2), (0.2, 0.3, 0.9)]
    )
    frame = peers.opensplat_frame([*scene.train_views(), view])
    own = peers.opensplat_draw(read_ply(tmp_path / "g.ply"), view, frame, step=0)
    depth = peers.render_ply(peers.ply_field(tmp_path / "g.ply"), view)
    assert own.shape == depth.shape == (view.height, view.width, 3)
    assert np.isfinite(own).all()
    assert psnr(own, depth) > 45.0
    assert np.abs(own - np.float32(peers.BACKGROUND)).max() > 0.3  # something is drawn


def test_own_reading_keeps_opensplats_scrambled_order(peers, tiny_scene_dir, tmp_path):
    """OpenSplat's CPU renderer sorts by a key read from a stride-3 view as if it were
    contiguous: Gaussian 0's key is its NDC depth (about 1), Gaussian 1's its NDC x
    (about 0 at the centre). So the far Gaussian 1 is drawn over the near 0."""
    scene = load_scene(tiny_scene_dir)
    view = scene.test_views()[0]
    near, far = _in_front(view, 3.0), _in_front(view, 6.0)
    _gaussians(tmp_path / "g.ply", [near, far, _in_front(view, 5.0, 50.0, 0)],
               [(0.9, 0.1, 0.1), (0.1, 0.1, 0.9), (0.5, 0.5, 0.5)],
               opacity=0.95, scale=0.3)  # fmt: skip
    frame = peers.opensplat_frame([*scene.train_views(), view])
    own = peers.opensplat_draw(read_ply(tmp_path / "g.ply"), view, frame, step=0)
    depth = peers.render_ply(peers.ply_field(tmp_path / "g.ply"), view)
    cy, cx = view.height // 2, view.width // 2
    assert depth[cy, cx, 0] > 0.8 and depth[cy, cx, 2] < 0.2  # the near red in front
    assert own[cy, cx, 2] > 0.8 and own[cy, cx, 0] < 0.2  # OpenSplat's: the far blue


def test_time_to_a_psnr_on_the_curve(peers):
    pts = [{"s": 10.0, "psnr_test": 12.0}, {"s": 20.0, "psnr_test": 16.0},
           {"s": 30.0, "psnr_test": 18.0}]  # fmt: skip
    assert peers.time_to(pts, 14.0) == pytest.approx(15.0)
    assert peers.time_to(pts, 11.0) == 10.0
    assert peers.time_to(pts, 18.5) is None


def test_build_refuses_what_is_not_an_opensplat_tree(peers, tmp_path):
    with pytest.raises(SystemExit, match="not an OpenSplat source tree"):
        peers.build_opensplat(tmp_path, tmp_path / "cache", None, 1)
    src = tmp_path / "src"
    src.mkdir()
    (src / "CMakeLists.txt").write_text("project(opensplat)\n")
    (src / "opensplat.cpp").write_text("int main() {}\n")
    (tmp_path / "deps" / "nanoflann").mkdir(parents=True)
    (tmp_path / "deps" / "nanoflann" / "CMakeLists.txt").write_text("\n")
    with pytest.raises(SystemExit, match="no source of nlohmann_json, cxxopts"):
        peers.build_opensplat(src, tmp_path / "cache", tmp_path / "deps", 1)
    assert not (tmp_path / "cache").exists()  # nothing built, nothing cached


def test_reach_is_ptovs_time_to_opensplats_best(peers):
    theirs = [{"s": 100.0, "psnr_test": 15.0, "psnr_test_own": 18.0},
              {"s": 200.0, "psnr_test": 17.0, "psnr_test_own": 20.0},
              {"s": 300.0, "psnr_test": 16.0, "psnr_test_own": 22.0}]  # fmt: skip
    ours = [{"step": 500, "s": 80.0, "psnr_test": 25.0},
            {"step": 100, "s": 20.0, "psnr_test": 16.0},
            {"step": 200, "s": 40.0, "psnr_test": 24.0}]  # fmt: skip
    own = peers.reach(ours, theirs, "psnr_test_own")  # its best: 22 dB at 300 s
    assert own["target_psnr"] == 22.0 and own["opensplat_s"] == 300.0
    assert own["ptovs_s"] == pytest.approx(35.0)  # 20 s + 6/8 of the 20 s to 24 dB
    assert own["speedup"] == pytest.approx(300.0 / 35.0, abs=0.01)
    assert own["bound"] is False
    depth = peers.reach(ours, theirs, "psnr_test")  # its best 17 dB at 200 s
    assert depth["ptovs_s"] == pytest.approx(22.5) and depth["bound"] is False
    # ptovs's shortest run already past the target: its time is an upper bound
    low = peers.reach([{"step": 50, "s": 10.0, "psnr_test": 18.0}], theirs, "psnr_test")
    assert low["ptovs_s"] == 10.0 and low["speedup"] == 20.0 and low["bound"] is True
    # never reached: no ratio
    none = peers.reach(
        [{"step": 50, "s": 10.0, "psnr_test": 12.0}], theirs, "psnr_test"
    )
    assert none["ptovs_s"] is None and none["speedup"] is None


def test_reach_table_reads_each_variants_whole_runs_at_these_iterations(peers):
    curve = [{"s": 100.0, "psnr_test": 15.0, "psnr_test_own": 18.0},
             {"s": 200.0, "psnr_test": 14.0, "psnr_test_own": 24.0}]  # fmt: skip

    def run(steps, s, db, n=500):
        return {"iterations": steps, "wall_s": s, "psnr_test": db, "for_iterations": n}

    rec = {"opensplat": {"curve": curve},
           "ptovs": run(500, 250.0, 26.0),  # past 24 dB
           "ptovs_reach_50": run(50, 40.0, 14.0),
           "ptovs_reach_200": run(200, 120.0, 23.0),
           "ptovs_reach_100": run(100, 60.0, 16.0, n=2500),  # another --iterations
           "ptovs_plain": run(500, 100.0, 20.0),
           "ptovs_plain_reach_50": run(50, 20.0, 19.0)}  # fmt: skip
    out = peers.reach_table(rec, 500)
    assert out["for_iterations"] == 500
    wild = out["ptovs"]["psnr_test_own"]  # 24 dB: between 200 (23) and 500 steps (26)
    assert wild["ptovs_s"] == pytest.approx(120.0 + 130.0 / 3, abs=0.1)
    assert out["ptovs"]["psnr_test"]["ptovs_s"] == pytest.approx(
        40.0 + 80.0 / 9, abs=0.1
    )
    plain = out["ptovs_plain"]
    assert plain["psnr_test"]["ptovs_s"] == 20.0 and plain["psnr_test"]["bound"]
    assert plain["psnr_test_own"]["speedup"] is None  # 20 dB never reaches 24


def test_table_gives_the_reach_rows(peers):
    run = {"wall_s": 30.0, "iterations": 50, "s_per_iteration": 0.4,
           "peak_rss_mb": 800, "gaussians": 3000, "psnr_test": 20.0}  # fmt: skip
    rec = {"ptovs_reach_50": run, "ptovs_plain_reach_50": {**run, "wall_s": 12.0},
           "reach": {"ptovs": {"psnr_test_own": {"target_psnr": 22.19, "opensplat_s": 881.7,
                                                 "ptovs_s": 90.0, "speedup": 9.8,
                                                 "bound": False},
                               "psnr_test": {"target_psnr": 17.27, "opensplat_s": 243.7,
                                             "ptovs_s": 30.0, "speedup": 8.12,
                                             "bound": True}},
                     "ptovs_plain": {"psnr_test_own": {"target_psnr": 22.19,
                                                       "opensplat_s": 881.7,
                                                       "ptovs_s": None, "speedup": None,
                                                       "bound": False}}}}  # fmt: skip
    text = peers.table({"scenes": {"herzjesu_p8": rec}})
    assert "| herzjesu_p8 | ptovs (in the wild), fewer steps | 50 | 30.0 |" in text
    assert (
        "| herzjesu_p8 | ptovs, plain 3DGS (wild=false), fewer steps | 50 | 12.0 |"
        in text
    )
    assert ("| herzjesu_p8 | ptovs (in the wild) | its own renderer | 22.19 | 881.7 | "
            "90.0 | 9.8× |") in text  # fmt: skip
    assert ("| herzjesu_p8 | ptovs (in the wild) | PLY, depth order | 17.27 | 243.7 | "
            "30.0 | ≥ 8.12× |") in text  # fmt: skip
    assert (
        "| herzjesu_p8 | ptovs, plain 3DGS (wild=false) | its own renderer | 22.19 |"
        " 881.7 | None | not in its runs |" in text
    )
