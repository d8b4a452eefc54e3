"""The synthetic scene generator: layout, truth, labels, COLMAP model, determinism."""

from __future__ import annotations

import csv
import json
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


@pytest.mark.parametrize("preset", ["tiny", "bench", "scale"])
def test_every_written_label_loads_over_many_seeds(preset, tmp_path):
    """No label polygon under 3 points (issue: slivers seen in one view)."""
    from ptovs.scene import read_label_json
    from ptovs.synthetic.generate import eval_labels

    seeds = range(40) if preset == "tiny" else range(12)
    n = 0
    for seed in seeds:
        for lab in eval_labels(preset, seed):
            path = tmp_path / f"{seed}_{lab['info']['name']}.json"
            path.write_text(json.dumps(lab))
            read_label_json(path)  # raises on a polygon of fewer than 3 points
            for obj in lab["objects"]:
                assert len(obj["segmentation"]) >= 3
            n += 1
    assert n >= len(seeds)


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
