"""How many of the pairs COLMAP verified on the bench photos are geometrically wrong.

python bench/sfm_pairs.py WORK/runs/s0/database.db DATA/bench_s0

Reads the verified two-view geometries of an SfM database (`bench/sfm.py` leaves
one per run) and scores each pair's inlier matches with the true fundamental
matrix of the two cameras (synthetic truth): a pair is wrong when fewer than half
of its inliers lie within 2 px (Sampson distance) of the true epipolar lines.
Prints, per COLMAP geometry type, the pairs and the wrong ones, and the inlier
counts of right and wrong pairs.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

CONFIGS = {2: "calibrated", 3: "uncalibrated (F)", 4: "planar", 5: "panoramic",
           6: "planar or panoramic", 7: "watermark", 8: "multiple"}  # fmt: skip


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])


def true_fundamental(a: dict, b: dict) -> np.ndarray:
    """F with x_b^T F x_a = 0 from two truth records (K, cam_from_world)."""
    pa, pb = np.array(a["cam_from_world"]), np.array(b["cam_from_world"])
    r = pb[:3, :3] @ pa[:3, :3].T
    t = pb[:3, 3] - r @ pa[:3, 3]
    ka, kb = np.array(a["K"]), np.array(b["K"])
    return np.linalg.inv(kb).T @ _skew(t) @ r @ np.linalg.inv(ka)


def sampson(f: np.ndarray, xa: np.ndarray, xb: np.ndarray) -> np.ndarray:
    """Sampson distances (px) of matches xa [n, 2] -> xb [n, 2] under F."""
    ha, hb = np.c_[xa, np.ones(len(xa))], np.c_[xb, np.ones(len(xb))]
    fa, fb = ha @ f.T, hb @ f
    num = np.sum(hb * fa, 1) ** 2
    den = fa[:, 0] ** 2 + fa[:, 1] ** 2 + fb[:, 0] ** 2 + fb[:, 1] ** 2
    return np.sqrt(num / np.maximum(den, 1e-12))


def score(db_path: Path, scene: Path, px: float = 2.0) -> list[tuple[float, int, int]]:
    """(share of inliers the truth explains, inliers, COLMAP config) per pair."""
    import pycolmap

    truth = {
        r["name"]: r
        for r in json.loads(
            (scene / "synthetic" / "truth" / "cameras.json").read_text()
        )["images"]
    }
    db = pycolmap.Database.open(str(db_path))
    try:
        names = {im.image_id: im.name for im in db.read_all_images()}
        ids, geoms = db.read_two_view_geometries()
        rows = []
        for pid, g in zip(ids, geoms, strict=True):
            m = g.inlier_matches
            if len(m) == 0:
                continue
            i, j = pycolmap.pair_id_to_image_pair(pid)
            f = true_fundamental(truth[names[i]], truth[names[j]])
            xa = db.read_keypoints(i)[m[:, 0], :2]
            xb = db.read_keypoints(j)[m[:, 1], :2]
            rows.append(
                (float(np.mean(sampson(f, xa, xb) < px)), len(m), int(g.config))
            )
    finally:
        db.close()
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("database", type=Path)
    ap.add_argument("scene", type=Path, help="the bench scene folder (with truth)")
    args = ap.parse_args()
    rows = np.array(score(args.database, args.scene))
    wrong = rows[:, 0] < 0.5
    print(f"verified pairs {len(rows)}, wrong {int(wrong.sum())}")
    print("| geometry | pairs | wrong | median inliers |\n|---|---|---|---|")
    for c in np.unique(rows[:, 2]).astype(int):
        sel = rows[:, 2] == c
        print(
            f"| {CONFIGS.get(c, c)} | {int(sel.sum())} | {int((wrong & sel).sum())} "
            f"| {np.median(rows[sel, 1]):.0f} |"
        )
    for label, sel in (("right", ~wrong), ("wrong", wrong)):
        if sel.any():
            q = np.quantile(rows[sel, 1], [0.25, 0.5, 0.75, 0.95])
            print(f"inliers of {label} pairs, quartiles and 95th: {q.round(0)}")


if __name__ == "__main__":
    main()
