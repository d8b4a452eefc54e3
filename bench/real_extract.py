"""extract-features with real-class encoders and segmenters, on a landmark's photos.

    python bench/real_extract.py --photos 20 --encoder MobileCLIP2-S0 \
        --segmenter sam2 --set extract-features.segment=once     # one configuration
    python bench/real_extract.py --photos 20 --config configs/photos-cpu.toml

Random weights (seeded; the arithmetic of the trained models, not their accuracy),
written once as checkpoints under <work>/ckpt. The scene is the `landmark` preset
(photos of about 700 px on the long side, as PT-OVS's) with its first --photos train
photos, generated under <work>/data when missing; reconstruct and render-appearances
run first (cached), then extract-features in a process of its own on --threads
threads: its wall time and peak RSS, the images and the segments it encoded, the
precision `auto` kept, and the seconds a view (the stage's wall divided by its views,
so the model loads and the precision check are charged to the views: an upper bound).
The hours at 763 photos are that rate times 763.

Results: one JSON line appended to <work>/real_extract.jsonl per run, and printed.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, machine, run_ptovs  # noqa: E402  (same folder)


def checkpoint(kind: str, model: str, folder: Path) -> Path:
    """A seeded random-weight checkpoint of `model` (written once)."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{kind}_{model}.pt"
    if path.is_file():
        return path
    torch.manual_seed(0)
    if kind == "clip":
        from ptovs.encoders.openclip import build_net

        state = build_net(model, None).state_dict()
    elif kind == "sam":
        from ptovs.compat import import_backend

        sa = import_backend("segment_anything")
        state = sa.sam_model_registry[model](checkpoint=None).state_dict()
    elif kind == "sam2":
        from ptovs.segment.sam2 import build_sam2_model

        state = {"model": build_sam2_model(model, None).state_dict()}
    else:
        raise ValueError(kind)
    tmp = path.with_suffix(".tmp")
    torch.save(state, tmp)
    tmp.replace(path)
    return path


def scene(data: Path, photos: int) -> Path:
    import subprocess

    out = data / f"landmark_s0_p{photos}"
    if not (out / "dense").is_dir():
        subprocess.run(
            [sys.executable, "-m", "ptovs", "-q", "synth-scene", str(data),
             "--preset", "landmark", "--seed", "0", "--photos", str(photos)],
            check=True,
        )  # fmt: skip
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--photos", type=int, default=20)  # the preset's least
    ap.add_argument("--encoder", default="MobileCLIP2-S0")
    ap.add_argument("--segmenter", default="hier", choices=["hier", "sam", "sam2"])
    ap.add_argument("--sam-model", default="", help="vit_b (sam) or tiny (sam2)")
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "default.toml")
    ap.add_argument("--set", action="append", default=[], metavar="STAGE.KEY=VALUE")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--work", type=Path, default=ROOT / "work" / "real_extract")
    ap.add_argument("--label", default="")
    a = ap.parse_args()
    work = a.work / "runs"
    sets = list(a.set)
    ckpts = a.work / "ckpt"
    sets += ["extract-features.encoder=openclip",
             f"extract-features.clip_model={a.encoder}",
             f"extract-features.clip_checkpoint={checkpoint('clip', a.encoder, ckpts)}",
             f"extract-features.segmenter={a.segmenter}"]  # fmt: skip
    if a.segmenter in ("sam", "sam2"):
        model = a.sam_model or ("vit_b" if a.segmenter == "sam" else "tiny")
        key = "sam_model" if a.segmenter == "sam" else "sam2_model"
        sets += [f"extract-features.{key}={model}",
                 f"extract-features.sam_checkpoint={checkpoint(a.segmenter, model, ckpts)}"]  # fmt: skip
    sc = scene(a.work / "data", a.photos)
    common = ["--config", str(a.config), "--threads", str(a.threads)]
    common += [f"--set={s}" for s in sets]
    times = {}
    for stage in ("reconstruct", "render-appearances"):
        wall, rss, _ = run_ptovs(work, *common, stage, "--data", str(sc))
        times[stage] = {"wall_s": round(wall, 1), "peak_rss_mb": round(rss)}
    wall, rss, out = run_ptovs(
        work, *common, "extract-features", "--data", str(sc), "--force"
    )
    art = Path(out.strip().splitlines()[-1].split(": ", 1)[1])
    from ptovs.artifacts import Artifact, read_json_dataset

    res = Artifact(art)
    meta = read_json_dataset(res.root()["levels_json"])
    views = res.names()
    crops = images = 0
    for name in views:
        v = res[name]
        for k in v:
            if k.startswith("nseg_"):
                crops += int(np.asarray(v[k]).sum())
                images += 1
    per_view = wall / max(len(views), 1)
    row = {
        "label": a.label, "date": time.strftime("%Y-%m-%d %H:%M"),
        "encoder": a.encoder, "segmenter": a.segmenter, "sets": a.set,
        "config": str(a.config), "photos": a.photos, "views": len(views),
        "images": images, "segments": crops, "segments_per_image": round(crops / max(images, 1), 1),
        "precision": (meta.get("precision") or {}).get("precision"),
        "precision_check": meta.get("precision"),
        "extract_wall_s": round(wall, 1), "extract_peak_rss_mb": round(rss),
        "s_per_view": round(per_view, 2), "h_at_763": round(per_view * 763 / 3600, 2),
        "upstream": times, "machine": machine(),
    }  # fmt: skip
    print(json.dumps(row))
    a.work.mkdir(parents=True, exist_ok=True)
    with open(a.work / "real_extract.jsonl", "a") as f:
        f.write(json.dumps(row) + "\n")


if __name__ == "__main__":
    main()
