"""A user's photo folder at any size and exposure: photos -> sfm -> reconstruct ->
extract-features with exit 0 and no traceback, and a photo decoded or resized at
any working size keeps its samples in [0, 1].

cv2's INTER_AREA at a factor that is not an integer can return 1 + 1.2e-7 over a
saturated region, which PhotoStack refuses; a blown-out sky at such a working
size used to end reconstruct with a ValueError.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
import torch
from click.testing import CliRunner

from ptovs.cli import main
from ptovs.scene import load_image, load_scene

ROOT = Path(__file__).resolve().parents[1]

# The photo walk: 20 views on a 70-degree arc of one synthetic landmark. Seed 3:
# SfM on one thread registers 20 of 20 of the mixed folder (seeds 4-6: 13-20).
N_VIEWS = 20
SIZE = (390, 300)  # (W, H), landscape
PORTRAIT = (4, 13)  # these views are taken upright: 300 x 390
EXPOSURES = ("plain", "blown", "dark")  # view i gets EXPOSURES[i % 3]
FORMATS = ("jpg8", "png16", "png8", "jpg8")  # and FORMATS[i % 4]
ITERS = ["--set", "reconstruct.iterations=30"]


def expose(rgb: np.ndarray, exposure: str, fmt: str) -> np.ndarray:
    """The render as a camera with that exposure would store it (BGR, 8 or 16 bit).

    "blown": 1.6 times brighter, clipped: the sky and the bright steps at the
    format's largest value (255 or 65535), the building still textured.
    "dark": 0.2 times and an offset below zero: brightest sample under 50 / 255,
    shadows at a few levels. "black" (one extra photo): at most 7 / 255.
    """
    gain, offset = {"plain": (1, 0), "blown": (1.6, 0), "dark": (0.2, 8),
                    "black": (0.03, 0)}[exposure]  # fmt: skip
    top = 65535 if fmt == "png16" else 255
    bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR).astype(np.float64) * (top / 255)
    out = np.clip(np.rint(bgr * gain - offset * top / 255), 0, top)
    return out.astype(np.uint16 if top == 65535 else np.uint8)


def write_photo(folder: Path, stem: str, img: np.ndarray, fmt: str) -> None:
    name = stem + (".jpg" if fmt.startswith("jpg") else ".png")
    opts = [cv2.IMWRITE_JPEG_QUALITY, 95] if fmt.startswith("jpg") else []
    assert cv2.imwrite(str(folder / name), img, opts)


@pytest.fixture(scope="module")
def renders() -> list[np.ndarray]:
    """RGB uint8 renders of the photo walk (views PORTRAIT upright)."""
    from ptovs.synthetic import world as sw

    world = sw.build_world(np.random.default_rng(3), 5)
    out = []
    for i in range(N_VIEWS):
        w, h = SIZE[::-1] if i in PORTRAIT else SIZE
        az = np.radians(-35 + 70 * i / (N_VIEWS - 1))
        dist = 2.6 * world.radius
        eye = world.center[:2] + dist * np.array([np.sin(az), -np.cos(az)])
        eye = np.array([*eye, 1.6 + 0.3 * (i % 3)])
        f = 0.9 * max(w, h)  # one lens, turned for the upright views
        K = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
        at = world.center + [0, 0, 0.2 * (i % 2)]
        cam = sw.Camera(K, sw.look_at(eye, at), w, h)
        out.append(sw.render(world, cam, sw.neutral_appearance(), [], aa=5).image)
    return out


def invoke(*args: str) -> str:
    """`ptovs ARGS` in-process: exit 0 and no traceback, else the output."""
    res = CliRunner().invoke(main, list(args))
    assert res.exit_code == 0 and res.exception is None, res.output + repr(
        res.exception
    )
    assert "Traceback" not in res.output, res.output
    return res.output


def pose(folder: Path, work: Path) -> Path:
    """SfM of the folder on one thread (repeatable; torch's count restored), and
    the posed scene folder it wrote."""
    before = torch.get_num_threads()
    try:
        invoke("--work-dir", str(work), "--threads", "1", "sfm", "--data", str(folder))
    finally:
        torch.set_num_threads(before)
    (out,) = [p for p in (work / folder.name / "sfm").iterdir() if p.is_dir()]
    return out


@pytest.fixture(scope="module")
def mixed(renders, tmp_path_factory) -> tuple[Path, Path, Path]:
    """(photo folder, work dir, posed scene): every exposure, bit depth, format
    and orientation in one folder, posed once for every case of the module."""
    root = tmp_path_factory.mktemp("photos")
    folder = root / "mixed"
    folder.mkdir()
    for i, rgb in enumerate(renders):
        exposure, fmt = EXPOSURES[i % 3], FORMATS[i % 4]
        stem = f"p{i:02d}_{exposure}_{fmt}"
        write_photo(folder, stem, expose(rgb, exposure, fmt), fmt)
    # one photo too dark for SfM: left out and listed (measured), never an error
    write_photo(folder, "p10b_black_jpg8", expose(renders[10], "black", "jpg8"), "jpg8")
    work = root / "work"
    return folder, work, pose(folder, work)


@pytest.fixture(scope="module")
def tiny_clip(tmp_path_factory) -> list[str]:
    """--set options for extract-features with the tests' tiny OpenCLIP (random
    weights) and the CPU segmenter on the photos alone."""
    from ptovs.encoders.openclip import build_net, register_tiny

    name = register_tiny()
    ckpt = tmp_path_factory.mktemp("clip") / "tiny.pt"
    torch.manual_seed(0)
    torch.save(build_net(name, None).state_dict(), ckpt)
    sets = {"encoder": "openclip", "clip_model": name, "clip_checkpoint": ckpt,
            "precision": "fp32", "segmenter": "hier", "images": "orig"}  # fmt: skip
    return [a for k, v in sets.items() for a in ("--set", f"extract-features.{k}={v}")]


def _kind(name: str) -> tuple[str, str]:
    exposure, fmt = Path(name).stem.split("_")[1:3]
    return exposure, fmt


def test_the_mixed_folder_is_posed_with_every_kind_of_photo(mixed):
    """What the cases below rely on: photos of every exposure, bit depth, format
    and orientation were registered."""
    scene = load_scene(mixed[2], downscale=1)
    kinds = {_kind(v.name) for v in scene.views}
    assert {e for e, _ in kinds} >= set(EXPOSURES), kinds
    assert {f for _, f in kinds} >= set(FORMATS), kinds
    assert {v.width > v.height for v in scene.views} == {True, False}
    # measured: 20 of the 21 (all but the black one)
    assert len(scene.views) >= 16, [v.name for v in scene.views]


@pytest.mark.parametrize("downscale", [1, 4], ids=["native", "r4"])
def test_a_mixed_folder_reaches_extract_features(mixed, tiny_clip, downscale):
    """Blown-out and dark, 8- and 16-bit, PNG and JPEG, landscape and upright
    photos in one folder: reconstruct and extract-features at full size and at
    working sizes the photos' sides do not divide. Undistortion gives each posed
    photo its own size (405 x 306, 361 x 277, ...), so after SfM nearly every
    r > 1 is such a size for some photo, whatever the camera's."""
    folder, work, posed = mixed
    scene = load_scene(posed, downscale=downscale)
    exact = {
        (v.full_width, v.full_height) == (downscale * v.width, downscale * v.height)
        for v in scene.views
    }
    assert (False in exact) == (downscale > 1), exact  # the case its name says
    sets = ["--work-dir", str(work), *ITERS, "--set", f"scene.downscale={downscale}"]
    invoke(*sets, "reconstruct", "--data", str(folder))
    invoke(*sets, *tiny_clip, "extract-features", "--data", str(folder))
    for stage in ("reconstruct", "extract-features"):
        assert list((work / folder.name / stage).glob("*.h5")), stage


def test_a_blown_out_collection_under_the_paper_recipe(renders, tmp_path):
    """The report that found it: every photo with a saturated sky, the paper's
    config, a working size the photos' sides do not divide."""
    folder = tmp_path / "sky"
    folder.mkdir()
    for i, rgb in enumerate(renders):
        if i not in PORTRAIT:
            write_photo(folder, f"sky_{i:02d}", expose(rgb, "blown", "jpg8"), "jpg8")
    posed = pose(folder, tmp_path / "work")
    views = load_scene(posed, downscale=2).views
    assert len(views) >= 12 and any(2 * v.width != v.full_width for v in views)
    invoke("--work-dir", str(tmp_path / "work"), "--config",
           str(ROOT / "configs" / "paper.toml"), *ITERS, "--set",
           "scene.downscale=2", "reconstruct", "--data", str(folder))  # fmt: skip


# ---------------------------------------------------------------- decoding


def _view(path: Path, full: tuple[int, int], size: tuple[int, int]):
    """What load_image reads of a view: its file, full and working sizes."""
    return SimpleNamespace(image_path=path, full_width=full[0], full_height=full[1],
                           width=size[0], height=size[1])  # fmt: skip


@pytest.mark.parametrize("kind", ["png8", "png16", "jpg8", "tiff-float"])
def test_a_saturated_photo_stays_in_range_at_a_non_integer_scale(tmp_path, kind):
    """A photo with a blown-out top half, decoded at 80 x 60 from 321 x 240 (a
    factor of 4.0125): every sample finite and in [0, 1]. A float TIFF's NaN,
    infinities and values past 1 come back as 0, 1, 0 and 1."""
    w, h = 321, 240
    rng = np.random.default_rng(0)
    img = rng.random((h, w, 3)) * 0.8
    img[: h // 2] = 1.0
    if kind == "png8" or kind == "jpg8":
        img = np.rint(img * 255).astype(np.uint8)
    elif kind == "png16":
        img = np.rint(img * 65535).astype(np.uint16)
    else:
        img = img.astype(np.float32)
        img[h // 2, :4] = np.array([np.nan, np.inf, -np.inf, 2.0])[:, None]
    ext = {"png8": ".png", "png16": ".png", "jpg8": ".jpg", "tiff-float": ".tiff"}
    path = tmp_path / f"photo{ext[kind]}"
    assert cv2.imwrite(str(path), img)
    for size in ((w, h), (107, 80), (80, 60)):  # factors 1, 3 and 4.0125
        out = load_image(_view(path, (w, h), size))
        assert out.shape == (size[1], size[0], 3) and out.dtype == np.float32
        assert np.isfinite(out).all() and out.min() >= 0.0, kind
        assert out.max() <= 1.0, (kind, size, float(out.max()) - 1.0)
    assert out[: 60 // 4].min() == 1.0  # the blown half stays white
    if kind == "tiff-float":
        full = load_image(_view(path, (w, h), (w, h)))
        np.testing.assert_array_equal(full[h // 2, :4, 0], [0, 1, 0, 1])


def test_resize_photo_and_the_appearance_nets_inputs_stay_in_range():
    """f_α and f_β see the photo resized to a square (64 px on the CPU preset): a
    white photo at 90 x 70 comes back white, not at 1 + 1.2e-7."""
    from ptovs.nets.wild import WildNets
    from ptovs.scene.images import resize_photo

    white = np.ones((70, 90, 3), np.float32)
    raw = cv2.resize(white, (64, 64), interpolation=cv2.INTER_AREA)
    assert raw.max() > 1.0  # what cv2 alone returns here
    assert resize_photo(white, (64, 64)).max() == 1.0
    grey = resize_photo(white[:, :, :1], (45, 35))
    assert grey.shape == (35, 45, 1) and grey.max() == 1.0
    nets = WildNets("cpu", 16)
    for x in nets.prepare(white):
        assert x.shape[0] == 3 and float(x.max()) <= 1.0 and float(x.min()) >= 0.0
