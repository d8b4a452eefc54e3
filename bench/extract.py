"""Benchmark render-appearances, extract-features and uncertainty on the bench preset.

python bench/extract.py                       # bench seeds 0 1 2
python bench/extract.py --seeds 0 --force     # recompute the three stages (timing)

Per seed, through the CLI: reconstruct (cached from bench/reconstruct.py's work dir
when present), then each stage in its own process: wall time and peak RSS; the
chosen appearances (ids, self-render L1, min pairwise L1); each novel render against
the world re-rendered with the target's appearance and no occluders (PSNR), and the
self render against the world under the view's own appearance without occluders;
stand-in encoding time per image; AUROC of U_T (and U_A) against the true transient
masks of the train images.

Results go to <work>/bench_extract.json and are printed as markdown rows.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, Results, bench_scene, run_ptovs  # noqa: E402  (same folder)

STAGES = ("render-appearances", "extract-features", "uncertainty")


def _art(stdout: str) -> Path:
    return Path(stdout.strip().splitlines()[-1].split(": ", 1)[1])


def run_stages(
    work: Path, scene: Path, recon_sets: list[str], force: bool = False
) -> dict:
    group = [f"--set=reconstruct.{s}" for s in recon_sets]
    wall, rss, out = run_ptovs(work, *group, "reconstruct", "--data", str(scene))
    res: dict = {"reconstruct": {"wall_s": round(wall, 1), "peak_rss_mb": round(rss)}}
    for stage in STAGES:
        extra = ["--force"] if force else []
        wall, rss, out = run_ptovs(work, *group, stage, "--data", str(scene), *extra)
        res[stage] = {
            "wall_s": round(wall, 1),
            "peak_rss_mb": round(rss),
            "path": str(_art(out)),
        }
    return res


def evaluate(res: dict, scene_dir: Path, n_views: int = 10) -> dict:
    import cv2

    from ptovs.artifacts import Artifact, read_json_dataset
    from ptovs.field.losses import auroc, psnr
    from ptovs.scene import load_scene
    from ptovs.synthetic.generate import load_truth, rerender
    from ptovs.synthetic.world import Appearance

    scene = load_scene(scene_dir)
    world, cams = load_truth(scene_dir)
    records = {r["name"]: r for r in cams["images"]}
    truth = scene_dir / "synthetic" / "truth"
    out: dict = {}
    with Artifact(Path(res["render-appearances"]["path"])) as art:
        sel = read_json_dataset(art.root()["selection_json"])
        slots = read_json_dataset(art.root()["slots_json"])
        out["selection"] = {
            k: sel.get(k)
            for k in (
                "mode",
                "chosen",
                "quality",
                "eps_q",
                "eps_d",
                "candidates",
                "min_pairwise_l1",
                "note",
            )
        }
        views = scene.train_views()
        pick = np.linspace(0, len(views) - 1, min(n_views, len(views))).astype(int)
        per_slot: dict[str, list[float]] = {s: [] for s in slots["slots"]}
        for i in pick:
            v = views[i]
            rgb = art[v.name]["rgb"].astype(np.float32) / 255.0
            for s, (slot, target) in enumerate(
                zip(slots["slots"], slots["targets"] + [v.name], strict=True)
            ):
                app = Appearance.from_dict(records[target or v.name]["appearance"])
                ref, _ = rerender(
                    world,
                    records[v.name],
                    appearance=app,
                    occluders="none",
                    seed=int(i),
                )
                ref = ref.image.astype(np.float32) / 255.0
                ref = cv2.resize(ref, (v.width, v.height), interpolation=cv2.INTER_AREA)
                per_slot[slot].append(psnr(rgb[s], ref))
        out["render_psnr"] = {
            k: round(float(np.mean(x)), 2) for k, x in per_slot.items()
        }
    with Artifact(Path(res["uncertainty"]["path"])) as art:
        st, sa, lab = [], [], []
        for name in art.names():
            t = np.load(truth / f"{Path(name).stem}.npz")["transient"]
            st.append(art[name]["u_t"].astype(np.float32).ravel())
            sa.append(art[name]["u_a"].astype(np.float32).ravel())
            lab.append(t.ravel() > 0.5)
        lab_all = np.concatenate(lab)
        out["ut_auroc"] = round(float(auroc(np.concatenate(st), lab_all)), 4)
        out["ua_auroc"] = round(float(auroc(np.concatenate(sa), lab_all)), 4)
        out["transient_share"] = round(float(lab_all.mean()), 4)
    with Artifact(Path(res["extract-features"]["path"])) as art:
        n_img = sum(
            len([k for k in art[n] if k.startswith("seg_")]) for n in art.names()
        )
        segs = [int(art[n]["nseg_orig"].sum()) for n in art.names()]
    out["images_encoded"] = n_img
    out["segments_per_original"] = round(float(np.mean(segs)), 1)
    out["extract_s_per_image"] = round(res["extract-features"]["wall_s"] / n_img, 3)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--data", type=Path, default=ROOT / "data")
    ap.add_argument("--work", type=Path, default=ROOT / "work" / "bench")
    ap.add_argument(
        "--force", action="store_true", help="recompute the three stages (timing)"
    )
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    results = Results(args.work / "bench_extract.json")
    save = results.save

    for seed in args.seeds:
        scene = bench_scene(args.data, seed)
        res = run_stages(args.work / "default", scene, [], args.force)
        res.update(evaluate(res, scene))
        results[f"bench_s{seed}"] = res
        save()
        t = " | ".join(
            f"{res[s]['wall_s']} s / {res[s]['peak_rss_mb']} MB" for s in STAGES
        )
        print(
            f"| {seed} | {t} | {res['ut_auroc']:.3f} | {res['ua_auroc']:.3f} | "
            f"{res['render_psnr']} | {res['selection']['chosen']} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
