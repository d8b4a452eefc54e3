"""Scene I/O: layouts, models, splits, cameras, images, labels, synthetic truth."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest

from ptovs.errors import InputError, MissingInputError
from ptovs.scene import (
    Scene,
    View,
    check_size,
    label_categories,
    load_image,
    load_labels,
    load_scene,
    read_split_tsv,
    resize_map,
    scale_intrinsics,
    working_size,
)

pycolmap.logging.minloglevel = 2

W, H = 97, 61  # odd on purpose: r = 2 rounds halves


# -------------------------------------------------------------------- builders


def _rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return q / np.linalg.norm(q)  # xyzw for pycolmap.Rotation3d


def build_model(
    n: int = 3,
    *,
    model: str = "PINHOLE",
    params: list[float] | None = None,
    sizes: list[tuple[int, int]] | None = None,
    names: list[str] | None = None,
    seed: int = 0,
) -> pycolmap.Reconstruction:
    """A posed model: one camera per image, 6 points seen by images 1 and 2."""
    rng = np.random.default_rng(seed)
    rec = pycolmap.Reconstruction()
    sizes = sizes or [(W, H)] * n
    names = names or [f"{1000 + i}_{i}.png" for i in range(n)]
    for i in range(n):
        w, h = sizes[i]
        p = params or ([60.0 + i, 62.0 + i, w / 2 + 0.3, h / 2 - 0.2])
        cam = pycolmap.Camera(model=model, width=w, height=h, params=p, camera_id=i + 1)
        rec.add_camera_with_trivial_rig(cam)
        img = pycolmap.Image(
            name=names[i],
            keypoints=rng.random((6, 2)) * [w, h],
            camera_id=i + 1,
            image_id=10 + i,
        )
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(_rotation(rng)), rng.normal(size=3))
        rec.add_image_with_trivial_frame(img, pose)
    for k in range(6):
        track = pycolmap.Track()
        track.add_element(10, k)
        if n > 1:
            track.add_element(11, k)
        rec.add_point3D(
            rng.normal(size=3), track, rng.integers(0, 256, 3).astype(np.uint8)
        )
    return rec


def write_images(images_dir: Path, rec: pycolmap.Reconstruction, seed: int = 0):
    """Random 8-bit colour images at each camera's size; returns {name: RGB}."""
    rng = np.random.default_rng(seed)
    images_dir.mkdir(parents=True, exist_ok=True)
    out = {}
    for image in rec.images.values():
        cam = rec.cameras[image.camera_id]
        rgb = rng.integers(0, 256, (cam.height, cam.width, 3), dtype=np.uint8)
        path = images_dir / image.name
        path.parent.mkdir(parents=True, exist_ok=True)
        assert cv2.imwrite(str(path), rgb[:, :, ::-1])
        out[image.name] = rgb
    return out


def write_model(
    sparse: Path, rec: pycolmap.Reconstruction, fmt: str = "bin", five: bool = True
) -> None:
    sparse.mkdir(parents=True, exist_ok=True)
    if fmt == "bin":
        rec.write_binary(str(sparse))
    else:
        rec.write_text(str(sparse))
    if not five:  # a classic 3-file model (PhotoTourism, hand-written)
        for f in ("rigs", "frames"):
            (sparse / f"{f}.{fmt}").unlink()


def write_tsv(path: Path, rows: list[tuple[str, str]]) -> None:
    lines = ["filename\tid\tsplit\tdataset"]
    lines += [f"{name}\t{i}\t{split}\ttest" for i, (name, split) in enumerate(rows)]
    path.write_text("\n".join(lines) + "\n")


def make_scene(
    tmp: Path,
    *,
    layout: str = "pt",
    fmt: str = "bin",
    five: bool = True,
    subdir: bool = False,
    rec: pycolmap.Reconstruction | None = None,
    splits: list[str] | None = None,
    name: str = "brandenburg_gate",
) -> tuple[Path, pycolmap.Reconstruction, dict[str, np.ndarray]]:
    """Write a scene folder; returns (root, model, {name: RGB image})."""
    rec = rec or build_model()
    root = tmp / name
    base = root / "dense" if layout == "pt" else root
    sparse = base / "sparse"
    write_model(sparse / "0" if subdir else sparse, rec, fmt, five)
    images = write_images(base / "images", rec)
    if layout == "pt":
        names = sorted(images)
        splits = splits or ["train"] * (len(names) - 1) + ["test"]
        write_tsv(root / "brandenburg.tsv", list(zip(names, splits, strict=True)))
    return root, rec, images


def expected_K(cam: pycolmap.Camera) -> np.ndarray:
    return np.asarray(cam.calibration_matrix(), dtype=np.float64)


# ------------------------------------------------------------- layouts, models


@pytest.mark.parametrize(
    "layout,fmt,five,subdir",
    [
        ("pt", "bin", False, False),
        ("pt", "txt", True, True),
        ("colmap", "bin", True, True),
        ("colmap", "txt", False, False),
    ],
)
def test_layouts_and_formats_round_trip(tmp_path, layout, fmt, five, subdir):
    root, rec, _ = make_scene(
        tmp_path, layout=layout, fmt=fmt, five=five, subdir=subdir
    )
    scene = load_scene(root, downscale=1)
    assert scene.layout == ("phototourism" if layout == "pt" else "colmap")
    assert scene.name == "brandenburg_gate" and scene.downscale == 1
    assert not scene.synthetic
    names = sorted(im.name for im in rec.images.values())
    assert [v.name for v in scene.views] == names
    for v in scene.views:
        image = rec.images[v.image_id]
        assert image.name == v.name
        cam = rec.cameras[image.camera_id]
        np.testing.assert_array_equal(v.K, expected_K(cam))
        T = np.eye(4)
        T[:3] = image.cam_from_world().matrix()
        np.testing.assert_allclose(v.cam_from_world, T, rtol=0, atol=1e-12)
        assert (v.width, v.height, v.full_width, v.full_height) == (W, H, W, H)
        assert v.K.dtype == np.float64 and v.cam_from_world.shape == (4, 4)
    # points round-trip (text stores 17 significant digits)
    ids = sorted(rec.points3D)
    np.testing.assert_array_equal(scene.points_id, ids)
    np.testing.assert_allclose(
        scene.points_xyz, [rec.points3D[i].xyz for i in ids], rtol=1e-12
    )
    np.testing.assert_array_equal(
        scene.points_rgb, [rec.points3D[i].color for i in ids]
    )
    np.testing.assert_array_equal(scene.points_track_len, [2] * len(ids))
    assert scene.points_rgb.dtype == np.uint8 and scene.points_error.shape == (6,)
    if layout == "pt":
        assert [v.split for v in scene.views] == ["train", "train", "test"]
        assert scene.split_file == root / "brandenburg.tsv"
    else:  # no TSV in a COLMAP scene: all train
        assert all(v.split == "train" for v in scene.views) and scene.split_file is None


def test_bin_and_txt_models_agree(tmp_path):
    rec = build_model(4, seed=3)
    a, _, _ = make_scene(tmp_path / "a", rec=rec, fmt="bin")
    b, _, _ = make_scene(tmp_path / "b", rec=rec, fmt="txt")
    sa, sb = load_scene(a), load_scene(b)
    for va, vb in zip(sa.views, sb.views, strict=True):
        assert va.name == vb.name
        np.testing.assert_allclose(va.K, vb.K, rtol=1e-15)
        np.testing.assert_allclose(va.cam_from_world, vb.cam_from_world, atol=1e-15)


def test_helpers_and_fingerprint(tmp_path, caplog):
    root, rec, _ = make_scene(tmp_path)
    labels = tmp_path / "label" / root.name
    labels.mkdir(parents=True)
    v0 = sorted(im.name for im in rec.images.values())[0]
    stem = Path(v0).stem
    write_label(labels / f"{stem}.json", f"{stem}.jpg", W, H, [("Column", SQUARE)])
    write_label(labels / "stray.json", "stray.jpg", W, H, [("Column", SQUARE)])
    with caplog.at_level(logging.WARNING, logger="ptovs.scene"):
        scene = load_scene(root)
    assert "stray" in caplog.text
    assert scene.labels_dir == labels
    assert [v.has_label for v in scene.views] == [True, False, False]
    assert scene.view(stem) is scene.view(v0) is scene.views[0]
    assert len(scene.train_views()) == 2 and len(scene.test_views()) == 1
    with pytest.raises(KeyError, match="nope"):
        scene.view("nope")
    files = scene.fingerprint_files()
    assert root / "brandenburg.tsv" in files
    assert labels / f"{stem}.json" not in files  # labels key only query, evaluate
    assert scene.label_files() == [labels / f"{stem}.json"]
    assert {
        root / "dense" / "sparse" / f"{n}.bin" for n in ("cameras", "images")
    } <= set(files)
    assert all(v.image_path in files for v in scene.views)
    assert all(f.is_file() for f in files)


def test_many_views_load_without_decoding_images(tmp_path):
    n = 400
    sizes = [(8, 6)] * n
    rec = build_model(n, sizes=sizes, params=[5.0, 5.0, 4.0, 3.0])
    root = tmp_path / "big"
    write_model(root / "sparse" / "0", rec)
    (root / "images").mkdir()
    for im in rec.images.values():  # content is never decoded by load_scene
        (root / "images" / im.name).write_bytes(b"x")
    scene = load_scene(root)
    assert len(scene.views) == n
    assert [v.name for v in scene.views] == sorted(
        im.name for im in rec.images.values()
    )


# ------------------------------------------------------------------ resolution


@pytest.mark.parametrize(
    "size,r,expected",
    [
        ((97, 61), 2, (48, 30)),
        ((97, 61), 3, (32, 20)),
        ((96, 72), 1, (96, 72)),
        ((5, 3), 4, (1, 1)),
    ],
)
def test_working_size(size, r, expected):
    assert working_size(*size, r) == expected


def test_downscale_auto_and_explicit(tmp_path):
    root, rec, _ = make_scene(tmp_path)
    assert load_scene(root).downscale == 1  # auto: 97 px photos are kept whole
    scene = load_scene(root, downscale=2)
    assert scene.downscale == 2
    for v in scene.views:
        cam = rec.cameras[rec.images[v.image_id].camera_id]
        assert (v.width, v.height) == (48, 30)
        K = expected_K(cam)
        sx, sy = 48 / 97, 30 / 61
        np.testing.assert_allclose(v.K[0], K[0] * [sx, 1, sx], rtol=1e-15)
        np.testing.assert_allclose(v.K[1], K[1] * [1, sy, sy], rtol=1e-15)
        np.testing.assert_array_equal(v.K[2], [0, 0, 1])
        # a pixel-corner point maps to the scaled corner: scaling is exact
        X = np.array([0.0, 0.0, 1.0])
        full = K @ X
        work = v.K @ X
        np.testing.assert_allclose(work[:2], full[:2] * [sx, sy], rtol=1e-14)
    assert load_scene(root, downscale=3).views[0].width == 32
    assert load_scene(root, downscale="1").views[0].width == 97
    (root / "synthetic").mkdir()
    synth = load_scene(root)
    assert synth.synthetic and synth.downscale == 1 and synth.views[0].width == 97


@pytest.mark.parametrize(
    ("sizes", "r"),
    [
        ([(4000, 3000)] * 3, 4),  # 12 MP: 1000 px
        ([(3072, 2048)] * 3, 4),  # the real sets: 768 px
        ([(1600, 1200)] * 3, 2),  # PhotoTourism: the paper's r = 2
        ([(1000, 750)] * 3, 1),
        ([(750, 1000)] * 3, 1),  # portrait: the long side counts
        ([(640, 480), (5000, 4000), (6000, 4000)], 5),  # the median photo
    ],
)
def test_downscale_auto_long_side(sizes, r):
    from ptovs.scene.load import AUTO_LONG_SIDE, auto_downscale

    rec = build_model(3, sizes=sizes)
    by_name = {img.name: img_id for img_id, img in rec.images.items()}
    chosen = dict.fromkeys(by_name, "train")
    assert auto_downscale(rec, by_name, chosen) == r
    side = sorted(max(s) for s in sizes)[1]
    assert side / r <= AUTO_LONG_SIDE and (r == 1 or side / (r - 1) > AUTO_LONG_SIDE)


@pytest.mark.parametrize("bad", [0, -2, 1.5, "x", True])
def test_downscale_invalid(tmp_path, bad):
    root, _, _ = make_scene(tmp_path)
    with pytest.raises(InputError, match="downscale"):
        load_scene(root, downscale=bad)


def test_scale_intrinsics_projects_consistently():
    K = np.array([[60.0, 0, 48.5], [0, 62.0, 30.5], [0, 0, 1]])
    K2 = scale_intrinsics(K, (97, 61), (48, 30))
    x = K @ np.array([0.1, -0.2, 1.0])
    x2 = K2 @ np.array([0.1, -0.2, 1.0])
    np.testing.assert_allclose(x2[:2], x[:2] * [48 / 97, 30 / 61])


# ---------------------------------------------------------------------- images


def _single_image_scene(tmp_path: Path, name: str, img: np.ndarray) -> Path:
    h, w = img.shape[:2]
    rec = build_model(1, sizes=[(w, h)], names=[name])
    root = tmp_path / "s"
    write_model(root / "sparse", rec)
    (root / "images").mkdir(parents=True)
    assert cv2.imwrite(str(root / "images" / name), img)
    return root


def test_load_image_colour_png_exact(tmp_path):
    root, _, images = make_scene(tmp_path, layout="colmap")
    scene = load_scene(root, downscale=2)
    assert scene.downscale == 2
    full = load_scene(root, downscale=1)
    for v, vf in zip(scene.views, full.views, strict=True):
        rgb = images[v.name]
        img_full = full.load_image(vf)
        assert img_full.dtype == np.float32 and img_full.shape == (H, W, 3)
        np.testing.assert_allclose(img_full, rgb / 255.0, atol=1e-7)
        img = scene.load_image(v.name)
        assert img.shape == (30, 48, 3) and img.dtype == np.float32
        ref = cv2.resize(
            (rgb / np.float32(255)).astype(np.float32),
            (48, 30),
            interpolation=cv2.INTER_AREA,
        )
        np.testing.assert_allclose(img, ref, atol=1e-6)
        assert 0.0 <= img.min() and img.max() <= 1.0


@pytest.mark.parametrize("kind", ["gray", "rgba", "u16", "jpeg"])
def test_load_image_formats(tmp_path, kind):
    rng = np.random.default_rng(1)
    if kind == "gray":
        img = rng.integers(0, 256, (H, W), dtype=np.uint8)
        expected = np.repeat(img[:, :, None], 3, axis=2) / 255.0
        name = "g.png"
    elif kind == "rgba":
        img = rng.integers(0, 256, (H, W, 4), dtype=np.uint8)  # BGRA on disk
        expected = img[:, :, 2::-1] / 255.0
        name = "a.png"
    elif kind == "u16":
        img = rng.integers(0, 65536, (H, W, 3), dtype=np.uint16)
        expected = img[:, :, ::-1] / 65535.0
        name = "d.png"
    else:
        img = np.zeros((H, W, 3), np.uint8)
        img[:, :] = (30, 90, 200)  # BGR: flat colour survives JPEG
        expected = np.broadcast_to(np.array([200, 90, 30]) / 255.0, (H, W, 3))
        name = "j.jpg"
    root = _single_image_scene(tmp_path, name, img)
    scene = load_scene(root, downscale=1)
    out = load_image(scene.views[0])
    assert out.dtype == np.float32 and out.shape == (H, W, 3)
    atol = 3 / 255 if kind == "jpeg" else 1e-6
    np.testing.assert_allclose(out, expected, atol=atol)
    if kind == "gray":
        assert np.array_equal(out[..., 0], out[..., 2])


def test_transparency_is_reported_once_and_opaque_alpha_is_silent(tmp_path, caplog):
    rng = np.random.default_rng(2)
    img = rng.integers(0, 256, (H, W, 4), dtype=np.uint8)
    img[..., 3] = 255
    root = _single_image_scene(tmp_path / "opaque", "o.png", img)
    with caplog.at_level(logging.WARNING, logger="ptovs"):
        load_image(load_scene(root, downscale=1).views[0])
    assert "transparent" not in caplog.text
    img[: H // 2, :, 3] = 0  # the top half cut out
    root = _single_image_scene(tmp_path / "cut", "c.png", img)
    view = load_scene(root, downscale=1).views[0]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="ptovs"):
        out = load_image(view)
        load_image(view)
    lines = [r.getMessage() for r in caplog.records if "transparent" in r.getMessage()]
    assert len(lines) == 1, lines  # once a file
    assert "c.png" in lines[0] and f"{100 * (H // 2) / H:.0f} %" in lines[0]
    np.testing.assert_allclose(out, img[:, :, 2::-1] / 255.0, atol=1e-6)  # RGB kept


def test_load_image_size_mismatch_is_an_error(tmp_path):
    root, rec, _ = make_scene(tmp_path, layout="colmap")
    scene = load_scene(root)
    v = scene.views[0]
    cv2.imwrite(str(v.image_path), np.zeros((H, W + 1, 3), np.uint8))
    with pytest.raises(InputError, match=f"{v.name}.*98x61.*97x61"):
        scene.load_image(v)


def test_load_image_corrupt(tmp_path):
    root, _, _ = make_scene(tmp_path, layout="colmap")
    scene = load_scene(root)
    v = scene.views[1]
    v.image_path.write_bytes(b"\x89PNG garbage bytes" * 10)
    with pytest.raises(InputError, match=v.name):
        scene.load_image(v)


# ------------------------------------------------------------------- pixel maps


def test_resize_map_kinds():
    ids = np.arange(12, dtype=np.int32).reshape(3, 4)
    up = resize_map(ids, (6, 8), kind="nearest")
    assert up.dtype == np.int32
    np.testing.assert_array_equal(up, np.repeat(np.repeat(ids, 2, 0), 2, 1))
    np.testing.assert_array_equal(resize_map(up, (3, 4)), ids)  # exact inverse
    mask = np.zeros((4, 4), bool)
    mask[:2, :2] = True
    assert resize_map(mask, (2, 2)).tolist() == [[True, False], [False, False]]
    area = resize_map(mask, (2, 2), kind="area")
    np.testing.assert_allclose(area, [[1, 0], [0, 0]])
    feats = np.random.default_rng(0).random((8, 10, 12)).astype(np.float32)
    small = resize_map(feats, (4, 5), kind="area")
    assert small.shape == (4, 5, 12)
    np.testing.assert_allclose(small[0, 0], feats[:2, :2].mean((0, 1)), rtol=1e-5)
    assert resize_map(feats, (16, 20), kind="linear").shape == (16, 20, 12)
    assert resize_map(feats[:, :, :1], (4, 5), kind="area").shape == (4, 5, 1)
    with pytest.raises(ValueError, match="nearest"):
        resize_map(ids, (2, 2), kind="area")
    with pytest.raises(ValueError, match="kind"):
        resize_map(ids, (2, 2), kind="cubic")


def test_check_size(tmp_path):
    root, _, _ = make_scene(tmp_path)
    v = load_scene(root, downscale=2).views[0]
    check_size(np.zeros((30, 48)), v, "u_t")
    check_size(np.zeros((30, 48, 3)), v, "u_t")
    with pytest.raises(InputError, match="u_t .*(61, 97)"):
        check_size(np.zeros((61, 97)), v, "u_t")


# -------------------------------------------------------------------- cameras


@pytest.mark.parametrize(
    "model,params",
    [
        ("SIMPLE_PINHOLE", [60.0, 48.0, 30.0]),
        ("SIMPLE_RADIAL", [60.0, 48.0, 30.0, 0.0]),
        ("RADIAL", [60.0, 48.0, 30.0, 0.0, 0.0]),
        ("OPENCV", [60.0, 61.0, 48.0, 30.0, 0, 0, 0, 0]),
        ("FULL_OPENCV", [60.0, 61.0, 48.0, 30.0] + [0.0] * 8),
    ],
)
def test_pinhole_equivalent_models(tmp_path, model, params):
    rec = build_model(model=model, params=params)
    root, _, _ = make_scene(tmp_path, rec=rec)
    v = load_scene(root, downscale=1).views[0]
    fy = params[0] if model.startswith(("SIMPLE", "RADIAL")) else params[1]
    cx, cy = (params[1], params[2]) if fy == params[0] else (params[2], params[3])
    np.testing.assert_array_equal(v.K, [[params[0], 0, cx], [0, fy, cy], [0, 0, 1]])


def test_distortion_refused_or_ignored(tmp_path, caplog):
    rec = build_model(model="SIMPLE_RADIAL", params=[60.0, 48.0, 30.0, 0.1])
    root, _, _ = make_scene(tmp_path, rec=rec)
    with pytest.raises(InputError, match="(?s)SIMPLE_RADIAL.*distortion.*undistort"):
        load_scene(root)
    with caplog.at_level(logging.WARNING, logger="ptovs.scene"):
        scene = load_scene(root, distortion="ignore", downscale=1)
    assert "distortion" in caplog.text
    np.testing.assert_array_equal(
        scene.views[0].K, [[60.0, 0, 48.0], [0, 60.0, 30.0], [0, 0, 1]]
    )
    with pytest.raises(InputError, match="distortion must be"):
        load_scene(root, distortion="fix")


@pytest.mark.parametrize(
    "model,params",
    [
        ("SIMPLE_RADIAL_FISHEYE", [60.0, 48.0, 30.0, 0.0]),
        ("OPENCV_FISHEYE", [60.0, 60.0, 48.0, 30.0, 0.1, 0, 0, 0]),
        ("FOV", [60.0, 60.0, 48.0, 30.0, 0.0]),
    ],
)
def test_unsupported_models(tmp_path, model, params):
    rec = build_model(model=model, params=params)
    root, _, _ = make_scene(tmp_path, rec=rec)
    with pytest.raises(InputError, match=f"{model} camera model is not supported"):
        load_scene(root, distortion="ignore")


# ------------------------------------------------------------------ bad inputs


def test_missing_scene_folder(tmp_path):
    with pytest.raises(MissingInputError, match="nowhere"):
        load_scene(tmp_path / "nowhere")


def test_not_a_scene_folder(tmp_path):
    (tmp_path / "x").mkdir()
    with pytest.raises(InputError, match="(?s)dense.*images.*sparse"):
        load_scene(tmp_path / "x")


def test_missing_images_dir(tmp_path):
    root, _, _ = make_scene(tmp_path)
    shutil.rmtree(root / "dense" / "images")
    with pytest.raises(MissingInputError, match="dense/images"):
        load_scene(root)


def test_missing_sparse(tmp_path):
    root, _, _ = make_scene(tmp_path, layout="colmap")
    shutil.rmtree(root / "sparse")
    with pytest.raises(MissingInputError, match="sparse"):
        load_scene(root)
    (root / "sparse" / "0").mkdir(parents=True)
    with pytest.raises(MissingInputError, match="no COLMAP model"):
        load_scene(root)


def test_incomplete_model(tmp_path):
    root, _, _ = make_scene(tmp_path)
    (root / "dense" / "sparse" / "points3D.bin").unlink()
    with pytest.raises(MissingInputError, match="points3D.bin"):
        load_scene(root)


def test_image_in_model_but_absent(tmp_path):
    root, rec, _ = make_scene(tmp_path)
    name = sorted(im.name for im in rec.images.values())[1]
    (root / "dense" / "images" / name).unlink()
    with pytest.raises(MissingInputError, match=name):
        load_scene(root)


@pytest.mark.parametrize(
    "file,damage",
    [
        ("points3D.bin", "truncate"),  # pycolmap alone hangs on this one
        ("images.bin", "truncate"),
        ("cameras.bin", "garbage"),
        ("frames.bin", "garbage"),
        ("images.txt", "garbage"),
    ],
)
def test_corrupt_model(tmp_path, file, damage):
    fmt = file.rsplit(".", 1)[1]
    root, _, _ = make_scene(tmp_path, fmt=fmt)
    path = root / "dense" / "sparse" / file
    if damage == "truncate":
        data = path.read_bytes()
        path.write_bytes(data[: int(len(data) * 0.77)])
    elif fmt == "bin":
        path.write_bytes(np.random.default_rng(0).bytes(100))
    else:
        path.write_text("# header\n1 2 three four\n")
    # the binary walker names the file; pycolmap's text errors name the folder
    with pytest.raises(InputError, match=file if fmt == "bin" else "dense/sparse"):
        load_scene(root)


@pytest.mark.parametrize("file", ["cameras", "images", "points3D", "rigs", "frames"])
def test_truncated_bin_files_are_refused(tmp_path, file):
    root, _, _ = make_scene(tmp_path, rec=build_model(4))
    path = root / "dense" / "sparse" / f"{file}.bin"
    data = path.read_bytes()
    for frac in np.linspace(0.05, 0.99, 12):
        path.write_bytes(data[: int(len(data) * frac)])
        with pytest.raises(InputError, match=f"{file}.bin is corrupt or truncated"):
            load_scene(root)
    path.write_bytes(data)
    assert len(load_scene(root).views) == 4


def test_bin_preferred_when_both_formats_exist(tmp_path):
    root, rec, _ = make_scene(tmp_path)
    other = build_model(seed=5)  # different poses, same names
    other.write_text(str(root / "dense" / "sparse"))
    scene = load_scene(root)
    assert all(f.suffix == ".bin" for f in scene.model_files)
    v = scene.views[0]
    T = rec.images[v.image_id].cam_from_world().matrix()
    np.testing.assert_array_equal(v.cam_from_world[:3], T)


def test_malformed_tsv(tmp_path):
    root, _, _ = make_scene(tmp_path)
    tsv = root / "brandenburg.tsv"
    tsv.write_text("name,id,split\na.png,0,train\n")
    with pytest.raises(InputError, match=r"brandenburg\.tsv.*filename"):
        load_scene(root)
    tsv.write_text("filename\tid\tsplit\n\na.png\n")
    with pytest.raises(InputError, match=r"brandenburg\.tsv, line 3"):
        load_scene(root)
    tsv.write_text("")
    with pytest.raises(InputError, match=r"brandenburg\.tsv is empty"):
        load_scene(root)


def test_split_file_choices(tmp_path, caplog):
    root, rec, _ = make_scene(tmp_path, splits=["train", "test", "val"])
    scene = load_scene(root)
    assert [v.split for v in scene.views] == ["train", "test", "test"]
    # several TSVs: an error naming them
    (root / "other.tsv").write_text("filename\tsplit\n")
    with pytest.raises(InputError, match=r"brandenburg\.tsv, other\.tsv"):
        load_scene(root)
    # explicit path and all-train
    scene = load_scene(root, split_file=root / "brandenburg.tsv")
    assert scene.split_file == root / "brandenburg.tsv"
    scene = load_scene(root, split_file="all-train")
    assert scene.split_file is None and len(scene.train_views()) == 3
    (root / "other.tsv").unlink()
    with pytest.raises(MissingInputError, match="nope.tsv"):
        load_scene(root, split_file=tmp_path / "nope.tsv")
    # PhotoTourism without a TSV: an error with the fix
    (root / "brandenburg.tsv").unlink()
    with pytest.raises(InputError, match="all-train"):
        load_scene(root)


def test_tsv_mismatch_warns_and_leaves_out(tmp_path, caplog):
    root, rec, _ = make_scene(tmp_path)
    names = sorted(im.name for im in rec.images.values())
    write_tsv(root / "brandenburg.tsv", [(names[0], "train"), ("ghost.jpg", "test")])
    with caplog.at_level(logging.WARNING, logger="ptovs.scene"):
        scene = load_scene(root)
    assert [v.name for v in scene.views] == [names[0]]
    assert "ghost.jpg" in caplog.text
    assert names[1] in caplog.text and "left out" in caplog.text
    write_tsv(root / "brandenburg.tsv", [("ghost.jpg", "test")])
    with pytest.raises(InputError, match="lists none"):
        load_scene(root)


def test_read_split_tsv_nerfw_format(tmp_path):
    p = tmp_path / "trevi.tsv"
    p.write_text(
        "filename\tid\tsplit\tdataset\n"
        "00883281_9633489441.jpg\t0\ttrain\ttrevi\n"
        "01_2.jpg\t\ttest\ttrevi\n\n"
    )
    assert read_split_tsv(p) == {"00883281_9633489441.jpg": "train", "01_2.jpg": "test"}


# ---------------------------------------------------------------------- labels

SQUARE = [[10, 10], [30, 10], [30, 30], [10, 30]]


def write_label(
    path: Path, name: str, w: int, h: int, objects: list[tuple[str, list]]
) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    data = {
        "info": {
            "description": "ISAT",
            "folder": "x",
            "name": name,
            "width": w,
            "height": h,
            "depth": 3,
            "note": "",
        },
        "objects": [
            {
                "category": cat,
                "group": i,
                "segmentation": seg,
                "area": 0,
                "layer": float(i),
                "bbox": [0, 0, 1, 1],
                "iscrowd": False,
                "note": "",
            }
            for i, (cat, seg) in enumerate(objects)
        ],
    }
    path.write_text(json.dumps(data))


@pytest.fixture
def labelled(tmp_path):
    root, rec, _ = make_scene(tmp_path)
    scene = load_scene(root)
    v = scene.views[0]
    labels = tmp_path / "label" / root.name
    write_label(
        labels / f"{v.stem}.json",
        f"{v.stem}.jpg",
        W,
        H,
        [
            ("Iron Cross", SQUARE),
            ("iron cross", [[0, 0], [5, 0], [5, 5]]),
            ("Iron Cross", [[60, 40], [80.9, 40], [80.9, 50.7], [60, 50.7]]),
        ],
    )
    return load_scene(root, downscale=2), labels


def test_labels_or_per_category_and_verbatim(labelled):
    scene, labels = labelled
    v = scene.views[0]
    assert v.has_label
    full = load_labels(scene, v, size=(H, W))
    assert list(full) == ["Iron Cross", "iron cross"]  # case-sensitive, file order
    ref = np.zeros((H, W), np.uint8)
    cv2.fillPoly(ref, [np.array(SQUARE, np.int32)], 1)
    cv2.fillPoly(ref, [np.array([[60, 40], [80, 40], [80, 50], [60, 50]], np.int32)], 1)
    np.testing.assert_array_equal(full["Iron Cross"], ref.astype(bool))
    assert full["Iron Cross"][45, 70] and full["Iron Cross"][20, 20]
    assert full["Iron Cross"].dtype == np.bool_
    # default size: the working size, nearest
    work = load_labels(labels, v)
    assert work["Iron Cross"].shape == (30, 48)
    np.testing.assert_array_equal(
        work["Iron Cross"], resize_map(ref.astype(bool), (30, 48), kind="nearest")
    )
    bil = load_labels(scene, v, gt_resize="bilinear")["Iron Cross"]
    np.testing.assert_array_equal(
        bil, cv2.resize(ref, (48, 30), interpolation=cv2.INTER_LINEAR).astype(bool)
    )
    assert label_categories(scene) == ["Iron Cross", "iron cross"]
    assert label_categories(labels, v.stem) == ["Iron Cross", "iron cross"]
    assert load_labels(labels, v.stem)["iron cross"].shape == (H, W)


def test_label_errors(labelled):
    scene, labels = labelled
    v = scene.views[0]
    path = labels / f"{v.stem}.json"
    path.write_text("{not json")
    with pytest.raises(InputError, match=path.name):
        load_labels(scene, v)
    write_label(path, "other.jpg", W, H, [("Column", SQUARE)])
    with pytest.raises(InputError, match=f"{path.name}.*other.jpg"):
        load_labels(scene, v)
    write_label(path, f"{v.stem}.jpg", W, H, [("Column", [[1, 1], [5, 5]])])
    with pytest.raises(InputError, match=f"{path.name}.*2 point"):
        load_labels(scene, v)
    write_label(path, f"{v.stem}.jpg", W, H, [(3, SQUARE)])
    with pytest.raises(InputError, match=f"{path.name}.*category"):
        load_labels(scene, v)
    write_label(path, f"{v.stem}.jpg", 0, H, [("Column", SQUARE)])
    with pytest.raises(InputError, match=f"{path.name}.*width"):
        load_labels(scene, v)
    write_label(path, f"{v.stem}.jpg", 50, 50, [("Column", SQUARE)])
    with pytest.raises(InputError, match=f"{path.name}.*50x50"):
        load_labels(scene, v)
    with pytest.raises(MissingInputError, match=f"{scene.views[1].stem}.json"):
        load_labels(scene, scene.views[1])


def test_a_broken_label_file_fails_when_the_scene_loads(labelled):
    """Found at load (before reconstruct and training), not when query runs."""
    scene, labels = labelled
    path = labels / f"{scene.views[0].stem}.json"
    path.write_text("{not json")
    with pytest.raises(InputError, match=path.name):
        load_scene(scene.root)
    write_label(path, "other.jpg", W, H, [("Column", SQUARE)])
    with pytest.raises(InputError, match=f"{path.name}.*other.jpg"):
        load_scene(scene.root)


def test_label_vertices_far_outside_are_refused_near_ones_clipped(labelled, caplog):
    """Vertices of 1e30 were accepted (a numpy cast warning, minutes of filling, a
    different mIoU); a polygon reaching just past the border is clipped, with a
    warning that names the file."""
    scene, labels = labelled
    v = scene.views[0]
    path = labels / f"{v.stem}.json"
    for far in ([[0, 0], [1e30, 0], [0, 5]], [[-3 * W, 0], [5, 0], [5, 5]]):
        write_label(path, f"{v.stem}.jpg", W, H, [("Column", far)])
        with pytest.raises(InputError, match=f"{path.name}.*far outside"):
            load_labels(scene, v)
    write_label(
        path, f"{v.stem}.jpg", W, H, [("Column", [[-5, -5], [W + 9, 0], [0, 9]])]
    )
    with caplog.at_level("WARNING"):
        m = load_labels(scene, v, size=(H, W))["Column"]
    assert m[0, 0] and m.shape == (H, W)
    assert path.name in caplog.text and "clipped" in caplog.text


# ------------------------------------------------------------ synthetic scene


@pytest.fixture(scope="module")
def synth(tiny_scene_dir):
    """The session's tiny synthetic scene (conftest) and its loaded Scene."""
    return tiny_scene_dir, load_scene(tiny_scene_dir)


def _truth(scene_dir: Path) -> dict:
    return json.loads((scene_dir / "synthetic" / "truth" / "cameras.json").read_text())


def test_synthetic_scene_matches_truth(synth):
    scene_dir, scene = synth
    assert isinstance(scene, Scene) and scene.synthetic and scene.downscale == 1
    truth = {t["name"]: t for t in _truth(scene_dir)["images"]}
    assert {v.name for v in scene.views} == set(truth)
    for v in scene.views:
        t = truth[v.name]
        assert isinstance(v, View) and v.split == t["split"]
        assert (v.width, v.height) == (t["width"], t["height"])
        np.testing.assert_allclose(v.K, t["K"], rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(v.cam_from_world, t["cam_from_world"], atol=1e-9)
        img = scene.load_image(v)
        assert img.shape == (t["height"], t["width"], 3)


def test_synthetic_points_lie_on_truth_depth(synth):
    scene_dir, scene = synth
    rec = pycolmap.Reconstruction(str(scene.model_dir))
    truth_dir = scene_dir / "synthetic" / "truth"
    by_id = {v.image_id: v for v in scene.views}
    depth_cache: dict[str, np.ndarray] = {}
    rel_err = []
    for i, pid in enumerate(scene.points_id):
        X = scene.points_xyz[i]
        for el in rec.points3D[int(pid)].track.elements:
            v = by_id.get(el.image_id)
            if v is None:
                continue
            if v.stem not in depth_cache:
                depth_cache[v.stem] = np.load(truth_dir / f"{v.stem}.npz")["depth"]
            depth = depth_cache[v.stem]
            Xc = v.cam_from_world[:3, :3] @ X + v.cam_from_world[:3, 3]
            uv = (v.K @ Xc)[:2] / Xc[2]
            col, row = int(np.floor(uv[0])), int(np.floor(uv[1]))
            assert 0 <= col < v.width and 0 <= row < v.height
            # surfaces are smooth: compare with the nearest finite depth around
            patch = depth[max(row - 1, 0) : row + 2, max(col - 1, 0) : col + 2]
            d = patch[np.isfinite(patch)]
            assert d.size
            rel_err.append(np.min(np.abs(d - Xc[2])) / Xc[2])
    truth = np.load(truth_dir / "points3D.npz")
    np.testing.assert_array_equal(np.sort(truth["point3D_id"]), scene.points_id)
    order = np.argsort(truth["point3D_id"])
    np.testing.assert_allclose(scene.points_xyz, truth["xyz"][order], atol=1e-9)
    assert len(rel_err) > 20
    assert np.median(rel_err) < 0.01 and np.mean(np.array(rel_err) < 0.05) > 0.95


def test_synthetic_labels_match_truth_parts(synth):
    scene_dir, scene = synth
    truth_dir = scene_dir / "synthetic" / "truth"
    parts = json.loads((truth_dir / "parts.json").read_text())
    labelled = scene.labelled_views()
    assert labelled and all(v.split == "train" for v in labelled)
    for v in labelled:
        part_id = np.load(truth_dir / f"{v.stem}.npz")["part_id"]
        masks = load_labels(scene, v)
        assert masks
        for cat, mask in masks.items():
            ids = parts["query_parts"][cat]
            assert ids == [p["id"] for p in parts["parts"] if p["query"] == cat]
            gt = np.isin(part_id, ids)
            iou = (mask & gt).sum() / max((mask | gt).sum(), 1)
            assert iou >= 0.98, (v.name, cat, iou)


def test_photo_stack_holds_photos_in_half_the_bytes_within_a_65535th():
    """reconstruct keeps every train photo in memory: 16-bit samples, read back as
    float32 within 0.5/65535 of the decoded values (hard cases: 0, 1, 8-bit steps)."""
    from ptovs.scene import PhotoStack

    rng = np.random.default_rng(3)
    photos = [
        rng.random((7, 5, 3), dtype=np.float32),
        np.zeros((2, 3, 3), np.float32),
        np.ones((1, 1, 3), np.float32),
        (np.arange(256, dtype=np.float32) / 255.0).repeat(3).reshape(16, 16, 3),
    ]
    stack = PhotoStack(photos)
    assert len(stack) == 4
    assert stack.shapes == [(7, 5, 3), (2, 3, 3), (1, 1, 3), (16, 16, 3)]
    assert stack.nbytes * 2 == sum(p.nbytes for p in photos)
    for k, p in enumerate(photos):
        got = stack[k]
        assert got.dtype == np.float32 and got.shape == p.shape
        assert np.abs(got.astype(np.float64) - p).max() <= 0.5 / 65535 + 1e-7
    assert stack[-1][0, 0, 0] == 0.0 and stack[2].max() == 1.0
    assert len(stack[1:3]) == 2
    with pytest.raises(ValueError, match="finite and in"):
        PhotoStack([np.full((2, 2, 3), np.nan, np.float32)])
    with pytest.raises(ValueError, match="finite and in"):
        PhotoStack([np.full((2, 2, 3), 1.5, np.float32)])
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        PhotoStack([np.zeros((2, 2), np.float32)])
    assert len(PhotoStack([])) == 0
