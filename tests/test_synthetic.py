"""The synthetic scene generator: layout, truth, labels, COLMAP model, determinism."""

from __future__ import annotations

import csv
import json
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

from ptovs.synthetic import PRESETS, generate_scene
from ptovs.synthetic.generate import fill_label, load_truth, mask_polygons, rerender

SEED = 3


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("synth")
    return generate_scene(out, "tiny", SEED, progress=False)


def _truth(scene: Path) -> tuple[dict, dict]:
    t = scene / "synthetic" / "truth"
    return json.loads((t / "cameras.json").read_text()), json.loads(
        (t / "parts.json").read_text()
    )


def _npz(scene: Path, name: str) -> dict[str, np.ndarray]:
    with np.load(scene / "synthetic" / "truth" / f"{Path(name).stem}.npz") as z:
        return {k: z[k] for k in z.files}


def test_layout_and_sizes(tiny: Path) -> None:
    cams, parts = _truth(tiny)
    cfg = PRESETS["tiny"]
    assert tiny.name == f"tiny_s{SEED}"
    imgs = sorted((tiny / "dense" / "images").glob("*.jpg"))
    assert len(imgs) == len(cams["images"]) == cfg.n_train + cfg.n_test
    for name in ("cameras.bin", "images.bin", "points3D.bin"):
        assert (tiny / "dense" / "sparse" / name).is_file()
    assert (tiny / "synthetic" / "vocabulary.json").is_file()
    sizes = set()
    for r in cams["images"]:
        im = cv2.imread(str(tiny / "dense" / "images" / r["name"]))
        assert im.shape[:2] == (r["height"], r["width"])
        assert max(im.shape[:2]) <= 110
        sizes.add((r["width"], r["height"]))
        stem = Path(r["name"]).stem
        a, b = stem.split("_")
        assert a.isdigit() and b.isdigit()
        t = _npz(tiny, r["name"])
        assert t["part_id"].dtype == np.int16 and t["part_id"].shape == im.shape[:2]
        assert t["transient"].dtype == bool and t["depth"].dtype == np.float32
        # depth is inf exactly where nothing (landmark or ground) is hit: the sky
        sky = ~np.isfinite(t["depth"])
        assert (t["part_id"][sky] == -1).all()
    assert len(sizes) > 3
    assert len(parts["parts"]) == 3
    assert {p["name"] for p in parts["parts"]} >= {"wall", "column"}


def test_tsv(tiny: Path) -> None:
    cams, _ = _truth(tiny)
    with open(tiny / "tiny.tsv") as f:
        rows = list(csv.reader(f, delimiter="\t"))
    assert rows[0] == ["filename", "id", "split", "dataset"]
    body = rows[1:]
    assert [r[0] for r in body] == [c["name"] for c in cams["images"]]
    assert all(
        r[2] in ("train", "test") and r[3] == tiny.name and r[1].isdigit() for r in body
    )
    assert sum(r[2] == "test" for r in body) == PRESETS["tiny"].n_test
    assert {r[0] for r in body} == {
        p.name for p in (tiny / "dense" / "images").iterdir()
    }


def test_part_ids_and_queries(tiny: Path) -> None:
    cams, parts = _truth(tiny)
    ids = {p["id"] for p in parts["parts"]}
    seen = set()
    for r in cams["images"]:
        seen |= set(np.unique(_npz(tiny, r["name"])["part_id"]).tolist())
    assert seen <= ids | {-1}
    assert ids <= seen  # every part is visible somewhere
    qp = parts["query_parts"]
    assert set(qp) < set(parts["queries"])
    distractors = set(parts["queries"]) - set(qp)
    assert distractors and distractors == set(parts["distractors"])
    by_id = {p["id"]: p for p in parts["parts"]}
    for q, pids in qp.items():
        assert all(by_id[k]["query"] == q for k in pids)
    vocab = json.loads((tiny / "synthetic" / "vocabulary.json").read_text())
    assert set(parts["queries"]) <= set(vocab["phrases"])


def test_eval_labels(tiny: Path) -> None:
    cams, parts = _truth(tiny)
    label_dir = tiny.parent / "label" / tiny.name
    evals = [r for r in cams["images"] if r["eval"]]
    assert len(evals) >= PRESETS["tiny"].n_eval
    assert sorted(p.name for p in label_dir.glob("*.json")) == sorted(
        Path(r["name"]).stem + ".json" for r in evals
    )
    qp = parts["query_parts"]
    categories = set()
    for r in evals:
        assert r["split"] == "train" and not r["transients"]
        t = _npz(tiny, r["name"])
        assert not t["transient"].any()
        assert (label_dir / r["name"]).is_file()
        lab = json.loads((label_dir / (Path(r["name"]).stem + ".json")).read_text())
        info = lab["info"]
        assert info["name"] == r["name"] and (info["width"], info["height"]) == (
            r["width"],
            r["height"],
        )
        assert lab["objects"], "GT is never empty"
        for obj in lab["objects"]:
            assert obj["category"] in qp  # never the distractor
            x0, y0, x1, y1 = obj["bbox"]
            assert 0 <= x0 <= x1 < r["width"] and 0 <= y0 <= y1 < r["height"]
        for cat, m in fill_label(lab).items():
            gt = np.isin(t["part_id"], qp[cat])
            assert gt.any()
            iou = (m & gt).sum() / (m | gt).sum()
            assert iou >= 0.98, (r["name"], cat, iou)
            categories.add(cat)
    assert categories == set(qp)  # every query is evaluated somewhere


def test_mask_polygons_holes() -> None:
    m = np.zeros((40, 50), bool)
    m[5:35, 5:45] = True
    m[12:20, 15:25] = False  # hole
    m[25:28, 30:33] = False  # hole
    m[2, 2] = True  # single pixel component
    m[22:24, 18:20] = False
    polys = mask_polygons(m)
    assert len(polys) == 2
    out = np.zeros(m.shape, np.uint8)
    for p in polys:
        cv2.fillPoly(out, [p], 1)
    assert np.array_equal(out.astype(bool), m)


def test_colmap_model_matches_truth(tiny: Path) -> None:
    import pycolmap

    pycolmap.logging.minloglevel = 2
    cams, _ = _truth(tiny)
    rec = pycolmap.Reconstruction(str(tiny / "dense" / "sparse"))
    assert rec.num_reg_images() == len(cams["images"])
    by_name = {im.name: im for im in rec.images.values()}
    for r in cams["images"]:
        im = by_name[r["name"]]
        assert im.image_id == r["image_id"]
        cam = rec.cameras[im.camera_id]
        assert cam.model.name == "PINHOLE"
        assert (cam.width, cam.height) == (r["width"], r["height"])
        K = np.asarray(r["K"])
        np.testing.assert_allclose(
            cam.params, [K[0, 0], K[1, 1], K[0, 2], K[1, 2]], atol=1e-9
        )
        np.testing.assert_allclose(cam.calibration_matrix(), K, atol=1e-9)
        T = np.asarray(r["cam_from_world"])
        np.testing.assert_allclose(im.cam_from_world().matrix(), T[:3], atol=1e-9)
        np.testing.assert_allclose(T[3], [0, 0, 0, 1])
        np.testing.assert_allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-12)
    with np.load(tiny / "synthetic" / "truth" / "points3D.npz") as z:
        ids, xyz, part = z["point3D_id"], z["xyz"], z["part_id"]
    assert ids.dtype == np.int64 and xyz.dtype == np.float64 and part.dtype == np.int16
    assert len(ids) == rec.num_points3D() > 100
    for k, pid in enumerate(ids):
        np.testing.assert_allclose(rec.points3D[int(pid)].xyz, xyz[k], atol=1e-12)
    assert (part >= 0).mean() > 0.5  # mostly landmark, some ground


def test_tracks_are_visible(tiny: Path) -> None:
    import pycolmap

    pycolmap.logging.minloglevel = 2
    cams, _ = _truth(tiny)
    rec = pycolmap.Reconstruction(str(tiny / "dense" / "sparse"))
    recs = {r["image_id"]: r for r in cams["images"]}
    truth = {iid: _npz(tiny, r["name"]) for iid, r in recs.items()}
    n = 0
    for pid, p in rec.points3D.items():
        assert p.track.length() >= 2
        for el in p.track.elements:
            r = recs[el.image_id]
            T, K = np.asarray(r["cam_from_world"]), np.asarray(r["K"])
            xc = T[:3, :3] @ p.xyz + T[:3, 3]
            u = K[0, 0] * xc[0] / xc[2] + K[0, 2]
            v = K[1, 1] * xc[1] / xc[2] + K[1, 2]
            kp = rec.images[el.image_id].points2D[el.point2D_idx]
            assert kp.point3D_id == pid
            np.testing.assert_allclose(kp.xy, [u, v], atol=1e-6)
            i, j = int(np.floor(v)), int(np.floor(u))
            t = truth[el.image_id]
            assert abs(t["depth"][i, j] - xc[2]) <= 0.015 * xc[2], (pid, el.image_id)
            assert not t["transient"][i, j]
            n += 1
    assert n > 2 * rec.num_points3D()


def test_points_colour_and_part(tiny: Path) -> None:
    import pycolmap

    pycolmap.logging.minloglevel = 2
    rec = pycolmap.Reconstruction(str(tiny / "dense" / "sparse"))
    cams, _ = _truth(tiny)
    recs = {r["image_id"]: r for r in cams["images"]}
    with np.load(tiny / "synthetic" / "truth" / "points3D.npz") as z:
        part = dict(zip(z["point3D_id"].tolist(), z["part_id"].tolist(), strict=True))
    agree = total = 0
    for pid, p in rec.points3D.items():
        assert p.color.dtype == np.uint8
        el = p.track.elements[0]
        kp = rec.images[el.image_id].points2D[el.point2D_idx].xy
        pid_map = _npz(tiny, recs[el.image_id]["name"])["part_id"]
        agree += pid_map[int(kp[1]), int(kp[0])] == part[pid]
        total += 1
    assert agree / total > 0.99


def test_deterministic_and_seeded(tiny: Path, tmp_path: Path) -> None:
    again = generate_scene(tmp_path / "a", "tiny", SEED, progress=False)
    other = generate_scene(tmp_path / "b", "tiny", SEED + 1, progress=False)
    # byte-identical: images, truth (npz included), labels, COLMAP model
    for a, b in (
        (tiny, again),
        (tiny.parent / "label" / tiny.name, again.parent / "label" / again.name),
    ):
        fa = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
        fb = sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
        assert fa == fb and len(fa) >= 4
        for f in fa:
            assert (a / f).read_bytes() == (b / f).read_bytes(), f
    c1, p1 = _truth(tiny)
    c3, p3 = _truth(other)
    assert p3["parts"] != p1["parts"]
    assert [r["name"] for r in c3["images"]] != [r["name"] for r in c1["images"]]
    assert [r["cam_from_world"] for r in c3["images"]] != [
        r["cam_from_world"] for r in c1["images"]
    ]


def test_rerender_reproduces_truth(tiny: Path) -> None:
    world, cams = load_truth(tiny)
    for r in cams["images"][:4]:
        v, _ = rerender(world, r, "own", "own")
        t = _npz(tiny, r["name"])
        assert np.array_equal(v.part_id, t["part_id"])
        assert np.array_equal(v.transient, t["transient"])
        assert np.array_equal(v.depth, t["depth"])
        jpg = cv2.cvtColor(
            cv2.imread(str(tiny / "dense" / "images" / r["name"])), cv2.COLOR_BGR2RGB
        )
        assert np.abs(jpg.astype(int) - v.image).mean() < 4  # JPEG q95
        n, _ = rerender(world, r, "neutral", "none")
        assert not n.transient.any()


def test_bad_input(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="unknown preset"):
        generate_scene(tmp_path, "huge", 0, progress=False)
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "precious.txt").write_text("x")
    with pytest.raises(FileExistsError):
        generate_scene(tmp_path, "tiny", 0, name="mine", progress=False)
    with pytest.raises(FileNotFoundError):
        load_truth(tmp_path / "mine")


def _check_plan(preset: str, seed: int) -> dict[str, int]:
    """Plan (preset, seed) and check its screen and labels independently.

    Every query phrase wins the pipeline's relevancy rule (`relevancy`, τ = 10,
    against the canonical and background phrases) on the clean crops of its
    labelled instances, by the screen's margin; every written label polygon
    loads. Returns the screen's counts per status.
    """
    from ptovs.encoders import prepare_crop
    from ptovs.encoders.synthetic import SyntheticEncoder
    from ptovs.field.relevancy import BACKGROUND_PHRASES, CANONICAL, relevancy
    from ptovs.scene import read_label_json
    from ptovs.synthetic import screen
    from ptovs.synthetic.generate import (
        PRESETS,
        isat_label,
        plan_scene,
        query_mask,
        scene_vocabulary,
    )
    from ptovs.synthetic.presets import _min_px
    from ptovs.synthetic.world import neutral_appearance, render

    torch = pytest.importorskip("torch")
    plan = plan_scene(preset, seed)
    enc = SyntheticEncoder(scene_vocabulary(plan.world, PRESETS[preset], []))
    negs = list(dict.fromkeys([*CANONICAL, *BACKGROUND_PHRASES]))
    text = torch.from_numpy(enc.encode_texts([*plan.queries, *negs])).double()
    crops: dict[str, list[np.ndarray]] = {q: [] for q in plan.queries}
    labelled = set()
    for i in plan.eval_ids:
        cam = plan.cams[i]
        view = render(plan.world, cam, neutral_appearance(), aa=1)
        lab = isat_label(view.part_id, plan.queries, f"{plan.stems[i]}.jpg", "x",
                         _min_px(cam, 0.002, 12))  # fmt: skip
        path = Path(os.environ.get("TMPDIR", "/tmp")) / f"ptovs_{os.getpid()}.json"
        path.write_text(json.dumps(lab))
        read_label_json(path)  # raises on a polygon of fewer than 3 points
        path.unlink()
        for obj in lab["objects"]:
            assert len(obj["segmentation"]) >= 3
        for q in {o["category"] for o in lab["objects"]}:
            labelled.add(q)
            m = query_mask(view.part_id, plan.queries[q])
            crops[q].append(prepare_crop(view.image, m))
    assert labelled == set(plan.queries), (preset, seed)  # every query is labelled
    for k, q in enumerate(plan.queries):
        emb = torch.from_numpy(enc.encode_images(np.stack(crops[q]))).double()
        cos = emb @ text.T
        rel = relevancy(cos[:, k], cos[:, len(plan.queries) :], 10.0).numpy()
        # the relevancy's margin in cosine units: sigmoid(τ m) = rel
        assert np.median(np.log(rel / (1 - rel)) / 10.0) >= screen.MARGIN - 1e-6, (
            preset,
            seed,
            q,
        )
        assert (rel > 0.5).mean() >= screen.MIN_WIN, (preset, seed, q)
    counts: dict[str, int] = {}
    for v in plan.screen.values():
        counts[v.status] = counts.get(v.status, 0) + 1
        assert v.answerable == (v.query in plan.queries)
    return counts


@pytest.mark.parametrize("preset", ["tiny", "small", "bench", "scale"])
def test_screen_and_labels_hold_over_50_seeds(preset):
    """Every preset's query phrases are answerable on their clean truth
    crops, over 50 seeds; no label polygon under 3 points (slivers seen in one
    view). Two worker processes: the 200 plans are the suite's longest test."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    seeds = range(50)
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("spawn")) as ex:
        counts = list(ex.map(_check_plan, [preset] * len(seeds), seeds))
    total = {
        k: sum(c.get(k, 0) for c in counts) for k in ("pass", "redrawn", "dropped")
    }
    assert total["pass"] > 0 and total["redrawn"] > 0  # the screen acts
    assert total["dropped"] <= 0.05 * sum(total.values())


def test_screen_records_reproducible_textures(tiny: Path) -> None:
    """parts.json's screen names, per part, the draw its texture comes from."""
    from ptovs.synthetic import screen
    from ptovs.synthetic.presets import PRESETS, _world
    from ptovs.synthetic.world import Texture

    _, parts = _truth(tiny)
    rec = parts["screen"]
    assert rec["margin"] == screen.MARGIN and rec["negatives"] == list(screen.NEGATIVES)
    drawn = _world(PRESETS["tiny"], SEED)
    assert {v["status"] for v in rec["parts"].values()} <= {
        "pass", "redrawn", "dropped", "unseen"
    }  # fmt: skip
    for p in parts["parts"]:
        v = rec["parts"][str(p["id"])]
        tex = Texture.from_dict(p["texture"])
        if v["status"] == "redrawn":
            assert tex == screen.redraw_texture(SEED, p["id"], v["attempt"], p["size"])
            assert p["query"] in parts["query_parts"]
        else:
            assert tex == drawn.parts[p["id"]].texture
            assert (p["query"] in parts["query_parts"]) == (v["status"] == "pass")


def test_screen_rule_and_negatives() -> None:
    from ptovs.field.relevancy import BACKGROUND_PHRASES, CANONICAL
    from ptovs.synthetic import screen

    assert screen.NEGATIVES == tuple(dict.fromkeys([*CANONICAL, *BACKGROUND_PHRASES]))
    m = screen.MARGIN
    assert screen.passes(np.array([m, m, m + 0.1]))
    assert not screen.passes(np.array([m - 1e-3] * 3))  # median short of the margin
    assert not screen.passes(np.array([])) and not screen.passes(np.array([np.nan]))
    many = np.full(20, m + 0.05)
    many[:2] = -0.01  # 90 % of the crops won: passes
    assert screen.passes(many)
    many[:3] = -0.01  # 85 %: fails
    assert not screen.passes(many)


def test_clean_scene_is_444_and_photo_sized(tiny: Path, tmp_path: Path) -> None:
    """The oracle's re-renders (bench/accuracy.py): neutral, unoccluded, 4:4:4
    JPEG of exactly the photos' sizes; everything else copied unchanged."""
    from ptovs.synthetic.generate import clean_scene

    out = clean_scene(tiny, tmp_path / "clean" / tiny.name)
    cams, _ = _truth(tiny)
    for r in cams["images"]:
        photo = tiny / "dense" / "images" / r["name"]
        clean = out / "dense" / "images" / r["name"]
        assert _jpeg_sampling(photo) == _jpeg_sampling(clean) == [(1, 1)] * 3
        a, b = cv2.imread(str(photo)), cv2.imread(str(clean))
        assert a.shape == b.shape == (r["height"], r["width"], 3)
        if r["transients"]:
            assert not np.array_equal(a, b)
    for rel in ("tiny.tsv", "synthetic/truth/parts.json", "dense/sparse/images.bin"):
        assert (out / rel).read_bytes() == (tiny / rel).read_bytes()
    labels = out.parent / "label" / tiny.name
    assert sorted(p.name for p in labels.iterdir()) == sorted(
        p.name for p in (tiny.parent / "label" / tiny.name).iterdir()
    )


def _jpeg_sampling(path: Path) -> list[tuple[int, int]]:
    """(horizontal, vertical) sampling factors of each component (SOF0/SOF2)."""
    data = path.read_bytes()
    i = 2
    while i < len(data):
        assert data[i] == 0xFF
        marker, length = data[i + 1], int.from_bytes(data[i + 2 : i + 4], "big")
        if marker in (0xC0, 0xC1, 0xC2):
            n = data[i + 9]
            comps = data[i + 10 : i + 10 + 3 * n]
            return [(comps[3 * k + 1] >> 4, comps[3 * k + 1] & 15) for k in range(n)]
        i += 2 + length
    raise AssertionError(f"{path}: no SOF marker")


def test_query_mask_drops_only_slivers():
    from ptovs.synthetic.generate import MIN_COMPONENT_PX, query_mask

    part = np.zeros((20, 20), np.int16)
    part[2:8, 2:8] = 1  # a block: kept
    part[15, 15] = 1  # a 1-pixel sliver: dropped
    part[18, 3:5] = 1  # a 2-pixel sliver: dropped
    part[12, 10:13] = 1  # 3 pixels: kept (its contour has 4 points)
    m = query_mask(part, [1])
    assert m[2:8, 2:8].all() and m[12, 10:13].all()
    assert not m[15, 15] and not m[18, 3:5].any()
    assert MIN_COMPONENT_PX == 3
    assert not query_mask(part, [2]).any()


def test_landmark_preset_and_photos_make_one_world_at_any_size(tmp_path: Path) -> None:
    """`--photos N` keeps the preset's test and labelled views and the first other
    train photos: a smaller collection is a subset of a larger one, same pixels."""
    from click.testing import CliRunner

    from ptovs.cli import main
    from ptovs.scene import load_scene
    from ptovs.synthetic.generate import PhotoCountError, photo_subset, plan_scene

    cfg = PRESETS["landmark"]
    assert cfg.n_train == 763 and cfg.long_side == (640, 760)
    plan = plan_scene("landmark", 0)
    small, large = (
        photo_subset(plan, "landmark", 24),
        photo_subset(plan, "landmark", 40),
    )
    assert set(small) < set(large)
    assert set(plan.test_ids) | set(plan.eval_ids) <= set(small)
    assert len(small) == 24 + cfg.n_test
    assert photo_subset(plan, "landmark", None) == list(range(763 + cfg.n_test))
    # past the preset's 763 (up to Notre-Dame's 2,934): more photos of one world,
    # the preset's own plan unchanged
    more = plan_scene("landmark", 0, extra=3)
    assert more.test_ids == plan.test_ids and more.eval_ids == plan.eval_ids
    assert more.stems[: 763 + cfg.n_test] == plan.stems
    assert more.queries == plan.queries and more.distractor == plan.distractor
    assert len(set(more.stems)) == len(more.stems) == 766 + cfg.n_test
    assert photo_subset(more, "landmark", 766) == list(range(766 + cfg.n_test))
    assert cfg.max_train == 2934
    with pytest.raises(PhotoCountError, match="at most 2934"):
        plan_scene("landmark", 0, extra=2934 - 763 + 1)
    with pytest.raises(PhotoCountError, match="to 2934 train photos"):
        photo_subset(more, "landmark", 2935)

    runner = CliRunner()
    res = runner.invoke(main, ["synth-scene", str(tmp_path), "--preset", "landmark",
                               "--photos", "3"])  # fmt: skip
    assert res.exit_code == 2 and "labelled views" in res.output, res.output
    res = runner.invoke(main, ["synth-scene", str(tmp_path), "--preset", "landmark",
                               "--photos", "2935"])  # fmt: skip
    assert res.exit_code == 2 and "at most 2934" in res.output, res.output
    res = runner.invoke(main, ["synth-scene", str(tmp_path), "--preset", "landmark",
                               "--photos", "24"])  # fmt: skip
    assert res.exit_code == 0, res.output
    scene = load_scene(tmp_path / "landmark_s0_p24")
    assert len(scene.train_views()) == 24 and len(scene.test_views()) == cfg.n_test
    assert len(scene.labelled_views()) == len(plan.eval_ids)
    assert all(640 <= max(v.width, v.height) <= 760 for v in scene.views)
    names = {v.name for v in scene.views}
    assert names == {f"{plan.stems[i]}.jpg" for i in small}


def test_small_3x_is_small_photographed_at_three_times_the_side() -> None:
    """`small-3x` (the instrument at the stand-in's calibration size): the
    world, cameras, evaluation views and screen of `small`, with 9x the pixels."""
    from ptovs.synthetic.generate import plan_scene

    one, three = plan_scene("small", 7), plan_scene("small-3x", 7)
    assert PRESETS["small-3x"].scale == 3 and PRESETS["small"].scale == 1
    assert three.queries == one.queries and three.distractor == one.distractor
    assert three.eval_ids == one.eval_ids and three.test_ids == one.test_ids
    assert three.stems == one.stems
    assert {k: v.status for k, v in three.screen.items()} == {
        k: v.status for k, v in one.screen.items()
    }
    for a, b in zip(one.cams, three.cams, strict=True):
        assert (b.width, b.height) == (3 * a.width, 3 * a.height)
        np.testing.assert_array_equal(b.cam_from_world, a.cam_from_world)
        np.testing.assert_allclose(b.K[:2], 3 * a.K[:2])
        np.testing.assert_array_equal(b.K[2], a.K[2])
        # a world point lands at 3x its pixel position
        X = (b.centre + 5.0 * b.R[2] + 0.4 * b.R[0] - 0.3 * b.R[1])[None]
        np.testing.assert_allclose(b.project(X)[0], 3 * a.project(X)[0], rtol=1e-9)
    assert one.cams[0].scaled(1) is one.cams[0]
