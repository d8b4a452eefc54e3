"""How the stand-in reads the crops the pipeline makes, on one instrument scene (issue 41).

    python bench/standin_segments.py data/accuracy-v2/small_s100 --views 6
    python bench/standin_segments.py data/accuracy-v2/small_s100 --views 6 --scale 3

For the first N evaluation views of a generated scene, at the scene's own photo
size: top-1 accuracy among the scene's part phrases of (a) the crops of the truth
part masks and (b) the crops of the segmenter's segments that lie within one part
(at least 80 % of their pixels on it, 70 % on some part), per level. The stand-in
is the one the scene's vocabulary names. `--scale S` renders the same views again
at S times the side (same cameras, appearances and occluders) instead of reading
the photos: what a larger photo would give. Diagnostic only: no field, no mIoU.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from ptovs.crop import prepare_crop
from ptovs.encoders import synthetic_encoder
from ptovs.segment import get_segmenter

MIN_PX = 30


def _photo(scene: Path, rec: dict, scale: int) -> tuple[np.ndarray, np.ndarray]:
    """(RGB uint8 photo, truth part ids) of a view: the scene's own, or rendered
    again at `scale` times its side."""
    stem = rec["name"].rsplit(".", 1)[0]
    truth = scene / "synthetic" / "truth"
    if scale == 1:
        image = cv2.imread(str(scene / "dense" / "images" / rec["name"]))[..., ::-1]
        return np.ascontiguousarray(image), np.load(truth / f"{stem}.npz")["part_id"]
    from ptovs.synthetic.generate import load_truth, rerender
    from ptovs.synthetic.world import Camera

    world, _ = load_truth(scene)
    big = Camera.from_dict(rec).scaled(scale)
    view, _ = rerender(world, {**rec, **big.to_dict()}, "own", "own", seed=0)
    return view.image, view.part_id


def measure(scene: Path, n_views: int, segmenter: str = "hier", scale: int = 1) -> dict:
    truth = scene / "synthetic" / "truth"
    vocab = json.loads((scene / "synthetic" / "vocabulary.json").read_text())
    enc = synthetic_encoder(vocab)
    query = {
        p.get("id"): p.get("query") for p in vocab.get("world", {}).get("parts", [])
    }
    if not query:  # a version-1 vocabulary: the parts file names them
        parts = json.loads((truth / "parts.json").read_text())["parts"]
        query = {int(p["id"]): p["query"] for p in parts}
    phrases = sorted(set(query.values()))
    text = enc.encode_texts(phrases)
    seg = get_segmenter(segmenter, levels=("s", "m", "l"))
    cams = json.loads((truth / "cameras.json").read_text())["images"]
    hits: dict[str, list[bool]] = {"truth": [], "s": [], "m": [], "l": []}

    def classify(key: str, crops: list, labels: list) -> None:
        if crops:
            pred = np.argmax(enc.encode_images(np.stack(crops)) @ text.T, axis=1)
            hits[key] += list(pred == np.array(labels))

    for rec in [c for c in cams if c["eval"]][:n_views]:
        image, pid = _photo(scene, rec, scale)
        x = image.astype(np.float32) / 255.0
        crops, labels = [], []
        for k in np.unique(pid[pid >= 0]):
            m = pid == k
            if m.sum() >= MIN_PX * scale * scale:
                crops.append(prepare_crop(x, m))
                labels.append(phrases.index(query[int(k)]))
        classify("truth", crops, labels)
        for name, level in zip(
            ("s", "m", "l"), seg.segment(np.ascontiguousarray(image)), strict=True
        ):
            crops, labels = [], []
            for k in range(int(level.labels.max()) + 1):
                m = level.mask(k)
                under = pid[m]
                under = under[under >= 0]
                if m.sum() < MIN_PX * scale * scale or len(under) < 0.7 * m.sum():
                    continue
                major = int(np.bincount(under).argmax())
                if (under == major).mean() >= 0.8:
                    crops.append(prepare_crop(x, m))
                    labels.append(phrases.index(query[major]))
            classify(name, crops, labels)
    return {
        "scene": scene.name,
        "phrases": phrases,
        "rows": {
            k: {"n": len(v), "accuracy": float(np.mean(v)) if v else None}
            for k, v in hits.items()
        },  # fmt: skip
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("--views", type=int, default=6, help="evaluation views to read")
    ap.add_argument("--segmenter", default="hier")
    ap.add_argument("--scale", type=int, default=1, help="render the views at S x side")
    args = ap.parse_args()
    out = measure(args.scene, args.views, args.segmenter, args.scale)
    print(f"{out['scene']}: {len(out['phrases'])} phrases (chance "
          f"{1 / len(out['phrases']):.0%})")  # fmt: skip
    for k, r in out["rows"].items():
        acc = "-" if r["accuracy"] is None else f"{r['accuracy']:.2f}"
        print(f"  {k:6s} n={r['n']:4d}  top-1 {acc}")


if __name__ == "__main__":
    main()
