"""Benchmark the applications (issue 12 targets).

python bench/apps.py --seeds 0 1 2 --parts select style roam   # on the bench chains
python bench/apps.py --parts batch                             # make -j3 all over 7 tiny scenes

Parts:
  select  per bench seed and label query, `ptovs select` in a fresh process: wall
          time, Gaussians selected, and the share of them whose nearest truth
          surface sample (synthetic/truth/points3D.npz) lies on the query's part
  style   per seed, `ptovs style` (20 seeded train views) against the scene's style
          vocabulary, max-score vote (default) and pixel-count vote (the authors'
          script): the winner, whether it is the true style, the true style's rank
          and votes, wall time; and the raw-encoder baseline on the same views
          (whole photo; the landmark alone under its truth mask)
  roam    per seed, `ptovs roam` of the first label query, 90 frames at 320x240:
          frames per second of rendering (setup excluded) and wall time
  pictures  docs/img/select.png (photo | field | selected Gaussians alone) and
          docs/img/style_votes.png (a style panel) from --picture-seed's scene
  batch   7 tiny synthetic scenes (seeds 0-6) from scratch through `make -j3 all`
          with the default config: wall time and the per-scene table

Uses the default chains of bench/train.py (<work>/default); runs what is missing.
The scenes must carry the current style vocabulary (`ptovs synth-scene` writes it;
it is deterministic, so regenerating a scene keeps the trained stages valid).
Results go to <work>/bench_apps.json.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, Results, bench_scene, run_ptovs  # noqa: E402  (same folder)


def _truth(scene: Path) -> dict:
    return json.loads((scene / "synthetic/truth/parts.json").read_text())


def select_part(work: Path, scene: Path, out: Path) -> dict:
    from ptovs.field.ply import read_ply
    from ptovs.synthetic.generate import nearest_parts

    truth = _truth(scene)
    res = {}
    for text, part_ids in truth["query_parts"].items():
        ply = out / f"{text.replace(' ', '_')}.ply"
        try:
            wall, rss, _ = run_ptovs(
                work, "select", text, "--data", str(scene), "--out", str(ply)
            )
        except RuntimeError as exc:
            res[text] = {"error": str(exc).splitlines()[-1]}
            print(scene.name, text, res[text], flush=True)
            continue
        rec = json.loads(ply.with_suffix(".json").read_text())
        pid, _ = nearest_parts(scene, read_ply(ply)["means"])
        res[text] = {
            "selected": rec["selected"],
            "gaussians": rec["gaussians"],
            "inside": float(np.isin(pid, part_ids).mean()),
            "ground": float((pid == -1).mean()),
            "nowhere": float((pid == -2).mean()),
            "select_s": rec["seconds"],
            "wall_s": round(wall, 2),
            "peak_rss_mb": round(rss),
        }
        print(scene.name, text, res[text], flush=True)
    return res


def style_part(work: Path, scene: Path, out: Path) -> dict:
    truth = _truth(scene)
    vocab = json.loads((scene / "synthetic/vocabulary.json").read_text())
    kinds = {
        i["swatch"]["kind"] for look in vocab.get("styles", {}).values() for i in look
    }
    if "style" not in truth or kinds != {"landmark"}:
        raise SystemExit(
            f"{scene} has no style vocabulary or an old one (part-swatch mixtures): "
            "regenerate it with `ptovs synth-scene` (deterministic: the trained "
            "stages stay valid; query artifacts are keyed by the vocabulary)"
        )
    wall, rss, _ = run_ptovs(work, "style", "--data", str(scene), "--out", str(out))
    rec = json.loads((out / "style.json").read_text())
    res = {
        "true": truth["style"],
        "winner": rec["winner"],
        "correct": rec["winner"] == truth["style"],
        "true_rank": rec["ranking"].index(truth["style"]) + 1,
        "votes": rec["votes"],
        "views": len(rec["views"]),
        "style_s": rec["seconds"],
        "wall_s": round(wall, 2),
    }
    _, _, _ = run_ptovs(work, "style", "--data", str(scene), "--vote", "pixel_count",
                     "--pictures", "0", "--out", str(out.with_name("style_pixel_count")))  # fmt: skip
    pc = json.loads((out.with_name("style_pixel_count") / "style.json").read_text())
    res["pixel_count"] = {"winner": pc["winner"], "correct": pc["winner"] == truth["style"],
                          "votes": pc["votes"]}  # fmt: skip
    res["raw_encoder"] = raw_style_votes(scene, [v["view"] for v in rec["views"]])
    print(scene.name, res, flush=True)
    return res


def raw_style_votes(scene: Path, names: list[str]) -> dict:
    """The authors' raw-CLIP baseline with the stand-in encoder: each view's whole
    photo (and, for reference, the landmark alone under its truth mask) votes for
    the style text with the highest cosine."""
    import cv2

    from ptovs.encoders import prepare_crop, scene_encoder

    enc = scene_encoder(scene)
    text = enc.encode_texts(enc.styles)
    votes = {
        "whole": dict.fromkeys(enc.styles, 0),
        "landmark": dict.fromkeys(enc.styles, 0),
    }
    for name in names:
        stem = Path(name).stem
        img = (
            cv2.imread(str(scene / "dense/images" / name))[..., ::-1].astype(np.float32)
            / 255
        )
        part = np.load(scene / "synthetic/truth" / f"{stem}.npz")["part_id"]
        crops = np.stack(
            [prepare_crop(img, np.ones(part.shape, bool)), prepare_crop(img, part >= 0)]
        )
        best = (enc.encode_images(crops) @ text.T).argmax(1)
        votes["whole"][enc.styles[best[0]]] += 1
        votes["landmark"][enc.styles[best[1]]] += 1
    return votes


def roam_part(work: Path, scene: Path, out: Path) -> dict:
    text = next(iter(_truth(scene)["query_parts"]))
    video = out / "tour.mp4"
    wall, rss, _ = run_ptovs(work, "roam", text, "--data", str(scene), "--out", str(video),
                          "--frames", "90", "--size", "320x240")  # fmt: skip
    rec = json.loads(video.with_suffix(".json").read_text())
    res = {"text": text, **{k: rec[k] for k in ("frames", "width", "height", "seconds", "render_fps")},
           "wall_s": round(wall, 2), "peak_rss_mb": round(rss)}  # fmt: skip
    print(scene.name, res, flush=True)
    return res


def batch_part(root: Path, n: int = 7) -> dict:
    data, work = root / "batch_data", root / "batch_work"
    for seed in range(n):
        if not (data / f"tiny_s{seed}" / "dense").is_dir():
            run_ptovs(
                work, "synth-scene", str(data), "--preset", "tiny", "--seed", str(seed)
            )
    t0 = time.perf_counter()
    proc = subprocess.run(
        [
            "make",
            "-s",
            "-j3",
            "all",
            f"DATA={data}",
            f"WORK={work}",
            "SETUP=",
            f"PTOVS_BIN={sys.executable} -m ptovs",
        ],  # fmt: skip
        cwd=ROOT,
        capture_output=True,
        text=True,
    )
    wall = time.perf_counter() - t0
    table = (work / "table.md").read_text() if (work / "table.md").exists() else ""
    res = {
        "scenes": n,
        "wall_s": round(wall, 1),
        "exit": proc.returncode,
        "table": table,
    }
    print(json.dumps(res, indent=1), flush=True)
    return res


def pictures_part(work: Path, scene: Path, text: str, docs: Path) -> dict:
    """README pictures: a train view's photo, the field's render and the render of
    the selected Gaussians alone (select); a style panel (style)."""
    import shutil

    import torch

    from ptovs.apps import close_inputs
    from ptovs.apps.select import select_gaussians
    from ptovs.config import load_config
    from ptovs.raster import Camera
    from ptovs.stage import Chain, RunContext, resolve_scene
    from ptovs.visual import to_uint8, write_png

    ctx = RunContext(work, load_config(None), False)
    ref = resolve_scene(ctx, None, scene)
    chain = Chain(ctx, ref)
    sel, querier, inputs = select_gaussians(chain, text)
    field = querier.field
    view = ref.load().labelled_views()[0]
    cam = Camera.from_view(view)
    emb = field.embeddings_of([view.name])
    full = field.render(cam, emb)[0]
    sub = field.subset(torch.from_numpy(sel.mask))
    part = sub.render(cam, emb)[0]
    photo = ref.load().load_image(view)
    row = np.hstack([to_uint8(photo), to_uint8(full.numpy()), to_uint8(part.numpy())])
    docs.mkdir(parents=True, exist_ok=True)
    write_png(docs / "select.png", row)
    close_inputs(inputs)
    panels = sorted((work.parent / "apps" / scene.name / "style").glob("*_styles.png"))
    if panels:
        shutil.copyfile(panels[0], docs / "style_votes.png")
    return {"scene": scene.name, "text": text, "view": view.name,
            "selected": int(sel.mask.sum()), "style_panel": str(panels[0]) if panels else None}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--parts", nargs="+", default=["select", "style", "roam", "batch"])
    ap.add_argument("--data", type=Path, default=ROOT / "data")
    ap.add_argument("--work", type=Path, default=ROOT / "work" / "bench")
    ap.add_argument("--picture-seed", type=int, default=1)
    ap.add_argument("--picture-text", default="Rose Window")
    args = ap.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    results = Results(args.work / "bench_apps.json")
    save = results.save

    work = args.work / "default"
    for seed in args.seeds if {"select", "style", "roam"} & set(args.parts) else []:
        scene = bench_scene(args.data, seed)
        out = args.work / "apps" / scene.name
        for part, fn in (
            ("select", select_part),
            ("style", style_part),
            ("roam", roam_part),
        ):
            if part in args.parts:
                results[f"{part}_s{seed}"] = fn(work, scene, out / part)
                save()
    if "pictures" in args.parts:
        scene = bench_scene(args.data, args.picture_seed)
        results["pictures"] = pictures_part(
            work, scene, args.picture_text, ROOT / "docs" / "img"
        )
        save()
    if "batch" in args.parts:
        results["batch"] = batch_part(args.work)
        save()


if __name__ == "__main__":
    main()
