"""What extract-features costs a view with real-class models, on a landmark's photos.

    python bench/real_extract.py --photos 4 --out work/real_extract.json

The scene is the `landmark` preset's first 20 train photos (about 700 px on the
long side, as PT-OVS's; generated under --data when missing). On the first
--photos of them, on --threads threads, with random weights (seeded; the
arithmetic of the trained models, not their accuracy), each piece of a view's work
is timed on its own, as extract-features runs it:

  segment   hier (no weights), SAM 2.1 hiera tiny and SAM ViT-B at 8² and 16²
            points, no crop layer (LangSplat's generator loop, `ptovs.segment`)
  crops     hier's segments per photo, and the distinct ones extract-features
            encodes (a mask that recurs at several levels is encoded once)
  encode    the distinct crops through each encoder (`--encoders`), fp32 and bf16,
            with the bf16 copy's agreement (what precision = "auto" checks)

then composes the seconds a view for the recipes a CPU user can choose: the full
recipe (the photo and its 4 renders encoded; segmented once a view or once an
image) and the photo alone (`images = "orig"`), and the hours at 763 photos.
Crops of a render are counted as the photo's (segment = "once" crops every image of
a view with the same segments). Peak RSS of this process is reported.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT, machine  # noqa: E402  (same folder)

IMAGES_A_VIEW = 5  # the photo, 3 novel appearances, the self render (N = 4)


def photos(data: Path, n: int) -> list[np.ndarray]:
    scene = data / "landmark_s0_p20"
    if not (scene / "dense").is_dir():
        subprocess.run(
            [sys.executable, "-m", "ptovs", "-q", "synth-scene", str(data),
             "--preset", "landmark", "--seed", "0", "--photos", "20"],
            check=True,
        )  # fmt: skip
    files = sorted((scene / "dense" / "images").glob("*.jpg"))[:n]
    return [cv2.cvtColor(cv2.imread(str(f)), cv2.COLOR_BGR2RGB) for f in files]


def timed(fn, *args):
    t = time.perf_counter()
    out = fn(*args)
    return out, time.perf_counter() - t


def segmenters(points: list[int]) -> dict:
    from ptovs.segment import get_segmenter
    from ptovs.segment.sam import SamSegmenter
    from ptovs.segment.sam2 import Sam2Segmenter, build_sam2_model

    torch.manual_seed(0)
    out = {"hier": get_segmenter("hier")}
    tiny = build_sam2_model("tiny", None)
    from ptovs.compat import import_backend

    vit_b = import_backend("segment_anything").sam_model_registry["vit_b"](
        checkpoint=None
    )
    for p in points:
        kw = dict(points_per_side=p, crop_n_layers=0)
        out[f"sam2-tiny {p}²"] = Sam2Segmenter(model=tiny, **kw)
        out[f"sam-vit_b {p}²"] = SamSegmenter(model=vit_b, **kw)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--photos", type=int, default=4)
    ap.add_argument("--encoders", nargs="+", default=["MobileCLIP2-S0", "ViT-B-32"])
    ap.add_argument("--points", nargs="+", type=int, default=[8, 16])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--data", type=Path, default=ROOT / "work" / "real_extract")
    ap.add_argument("--out", type=Path, default=ROOT / "work" / "real_extract.json")
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    cv2.setNumThreads(a.threads)
    from ptovs.crop import prepare_crop
    from ptovs.encoders.openclip import (
        CHECK_PHRASES,
        OpenClipEncoder,
        centred_agreement,
    )
    from ptovs.stages.extract_features import unique_segments

    imgs = photos(a.data, a.photos)
    segs = segmenters(a.points)
    encs = {}
    for name in a.encoders:
        torch.manual_seed(0)
        encs[name] = OpenClipEncoder(name, random_weights=True, batch_size=32)
    rows = []
    for i, img in enumerate(imgs):
        row: dict = {"photo": i, "size": list(img.shape[:2]), "segment_s": {}}
        for name, seg in segs.items():
            levels, s = timed(seg.segment, img)
            row["segment_s"][name] = round(s, 2)
            if name == "hier":
                hier = levels
        order, _ = unique_segments(hier)
        row["crops"] = int(sum(lv.n for lv in hier))
        row["distinct_crops"] = len(order)
        row["encode_s"], row["agreement"] = {}, {}
        for name, enc in encs.items():
            crops = np.stack([prepare_crop(img, hier[lv].mask(k), enc.size)
                              for lv, k in order])  # fmt: skip
            enc._encode(crops[:4], "fp32")  # warm-up
            feats = {}
            for prec in ("fp32", "bf16"):
                feats[prec], s = timed(enc._encode, crops, prec)
                row["encode_s"][f"{name} {prec}"] = round(s, 2)
            text = enc.encode_texts(list(CHECK_PHRASES))
            row["agreement"][name] = centred_agreement(
                feats["fp32"], feats["bf16"], text
            )
        rows.append(row)
        print(json.dumps(row), flush=True)

    def mean(f):
        return float(np.mean([f(r) for r in rows]))

    seg_s = {k: mean(lambda r, k=k: r["segment_s"][k]) for k in segs}
    enc_s = {k: mean(lambda r, k=k: r["encode_s"][k]) for k in rows[0]["encode_s"]}
    recipes = {}
    for e, es in enc_s.items():
        for s, ss in seg_s.items():
            for recipe, n_img, n_seg in (("full, segment once", IMAGES_A_VIEW, 1),
                                         ("full, segment each", IMAGES_A_VIEW, IMAGES_A_VIEW),
                                         ("photo only", 1, 1)):  # fmt: skip
                view = n_seg * ss + n_img * es
                recipes[f"{e} | {s} | {recipe}"] = {
                    "s_a_view": round(view, 1),
                    "h_at_763": round(view * 763 / 3600, 2),
                }
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                            capture_output=True, text=True).stdout.strip()  # fmt: skip
    res = {
        "date": time.strftime("%Y-%m-%d %H:%M"), "commit": commit,
        "threads": a.threads, "machine": machine(),
        "load_after": list(np.round(__import__("os").getloadavg(), 2)),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
        "crops_a_photo": mean(lambda r: r["crops"]),
        "distinct_crops_a_photo": mean(lambda r: r["distinct_crops"]),
        "segment_s_a_photo": seg_s, "encode_s_a_photo": enc_s,
        "recipes": recipes, "rows": rows,
    }  # fmt: skip
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(res, indent=1) + "\n")
    print(json.dumps({k: res[k] for k in ("crops_a_photo", "distinct_crops_a_photo",
                      "segment_s_a_photo", "encode_s_a_photo", "peak_rss_mb")}))  # fmt: skip


if __name__ == "__main__":
    main()
