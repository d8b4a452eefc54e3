"""OpenCLIP ViT-B-16 on the CPU: its cost per photo, and what brings it down
without changing its answer (issue 43 item 6).

    python bench/openclip_cpu.py --photos 3 --threads 1 2 --batch 1 16 64 \
        --repeats 3 --out work/openclip_cpu.json
    python bench/openclip_cpu.py --photos 1 --threads 1 --batch 8 --repeats 1 \
        --max-crops 16 --out /tmp/oc_try.json        # a smoke trial

The encoder is ptovs's own (`ptovs.encoders.openclip.OpenClipEncoder`, built with
`random_weights=True` after `torch.manual_seed(--seed)`: nothing can be downloaded
here, so the arithmetic is the trained model's, the features are not). Its
`encode_images` is what is timed: CLIP's normalisation, batches of `batch_size`
crops, L2-normalised rows.

The crops are real: `--photos` photos of the real photo sets (`--real`, default
data/real; round robin over the sets), resized to a long side of `--long-side` px
(700: a PT-OVS working size), segmented by extract-features' default segmenter
(`build_segmenter(Config())`: "hier", levels s, m, l) and cut as the stage cuts
them (`prepare_crop`, 224 px). `--max-crops` keeps an evenly spaced subset of a
photo's segments (trials only: a photo's cost is then not its full cost).

Per configuration, seconds per photo = the median over `--repeats` runs (after one
warm-up batch) of the time to encode every kept crop of every photo, divided by
the photos; on each of `--threads` (torch.set_num_threads) and `--batch` sizes:

- fp32: the reference (ptovs's CPU path);
- bf16: the same with torch.autocast("cpu", dtype=torch.bfloat16) (the issue's
  recipe; autocast turns off nn.MultiheadAttention's inference fast path);
- bf16w: a bf16 copy of the model (weights and activations bf16, the input cast
  to bf16, the output back to fp32): the fast path stays on;
- int8: torch.ao.quantization.quantize_dynamic on the nn.Linear layers (qint8;
  the attention's in/out projections are not nn.Linear modules and stay fp32);
  an error is recorded instead if this torch build refuses.

bf16, bf16w and int8 report each crop's cosine to its fp32 feature (median, p1, min);
"kept" = min cosine >= 0.99 (the issue's rule). Random weights give every crop
nearly the same feature (fp32_pairwise_cos_median: the median cosine between two
crops), so the rule is weak here; the centred cosines (each set of features less
its mean over the crops) measure the error against what tells crops apart, and
"kept_centred" applies the rule to them. Even so the cosines test the number
formats on this network's shapes and the real crops, not a trained model's
outlier features: rerun with a trained checkpoint before adopting one.

Dense pass (`--dense-sizes`, `--dense-modes`): one forward of the whole photo
resized to S x S (448: positional embedding interpolated bicubically from 14x14
to 28x28); the patch tokens after the last block go through ln_post and proj; a
segment's feature is the mean of the patch features under its mask, each patch
weighted by the fraction of its area inside the mask. Modes: "tokens" (the last
block as it is) and "value" (MaskCLIP: the last block's attention replaced by
each token's own value, out_proj(v)). Its answer differs by design: reported is
the cosine of each segment's dense feature to its fp32 crop feature (median,
p10, min; raw and centred), not a kept flag, beside the median cosine to another
segment's crop feature (the chance level).

Also: fp32's crops/s at its best batch and thread count, and the projected
seconds for a 763-photo collection with 5 images a photo (original, 3 novel
renders, self render): 763 x 5 x seconds per photo, at the photos' segment count.
Results go to --out (JSON, written atomically after every configuration) and print
as a markdown table.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

REAL = ROOT / "data" / "real"  # the real photo sets (README: `REAL=`), as bench/real.py
VARIANTS = ("fp32", "bf16", "bf16w", "int8")
KEEP_COS = 0.99
COLLECTION = (763, 5)  # photos, images a photo (orig + 3 novel + self)


def machine(threads: list[int]) -> dict:
    import os
    import platform

    cpu = ""
    flags: list[str] = []
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") and not cpu:
                cpu = line.split(":", 1)[1].strip()
            if line.startswith("flags") and not flags:
                want = ("avx2", "avx512f", "avx512_bf16", "avx512_vnni", "amx")
                flags = [f for f in line.split(":", 1)[1].split() if f.startswith(want)]
    except OSError:
        pass
    return dict(
        cpu=cpu,
        cpu_flags=flags,
        cpus=os.cpu_count(),
        platform=platform.platform(),
        torch=torch.__version__,
        cpu_capability=torch.backends.cpu.get_cpu_capability(),
        quantized_engine=torch.backends.quantized.engine,
        threads=threads,
        date=time.strftime("%Y-%m-%d %H:%M"),
    )


def real_dir(arg: Path | None) -> Path:
    path = arg if arg is not None else REAL
    if not path.is_dir():
        raise FileNotFoundError(
            f"no real photo sets at {path}; pass --real DIR (the folder holding "
            "fountain_p11/ and herzjesu_p8/)"
        )
    return path


def pick_photos(real: Path, n: int) -> list[Path]:
    """n photos, round robin over the sets (sorted by name)."""
    sets = [sorted((d / "images").glob("*.jpg")) for d in sorted(real.iterdir())]
    sets = [s for s in sets if s]
    out: list[Path] = []
    i = 0
    while len(out) < n and any(i < len(s) for s in sets):
        out += [s[i] for s in sets if i < len(s)]
        i += 1
    if len(out) < n:
        raise ValueError(f"{real} holds {len(out)} photos, fewer than {n}")
    return out[:n]


def load(path: Path, long_side: int) -> np.ndarray:
    import cv2

    img = cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    s = long_side / max(img.shape[:2])
    if s < 1:
        img = cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(img)


def prepare(paths: list[Path], long_side: int, max_crops: int) -> list[dict]:
    """Per photo: the image, its levels, the kept segments (level, id) and crops."""
    from ptovs.crop import prepare_crop
    from ptovs.stages.extract_features import Config, build_segmenter

    seg = build_segmenter(Config())
    photos = []
    for path in paths:
        img = load(path, long_side)
        t0 = time.perf_counter()
        levels = seg.segment(img)
        t_seg = time.perf_counter() - t0
        ids = [(li, k) for li, lv in enumerate(levels) for k in range(lv.n)]
        if max_crops and len(ids) > max_crops:
            keep = np.unique(
                np.linspace(0, len(ids) - 1, max_crops).round().astype(int)
            )
            ids = [ids[i] for i in keep]
        t0 = time.perf_counter()
        crops = np.stack([prepare_crop(img, levels[li].mask(k), 224) for li, k in ids])
        t_crop = time.perf_counter() - t0
        photos.append(dict(path=path, image=img, levels=levels, ids=ids,
                           crops=crops, segment_s=t_seg, crop_s=t_crop))  # fmt: skip
        print(f"{path.parent.parent.name}/{path.name} {img.shape[1]}x{img.shape[0]}: "
              f"{[lv.n for lv in levels]} segments (s, m, l), {len(ids)} crops kept; "
              f"segment {t_seg:.2f} s, crops {t_crop:.2f} s", flush=True)  # fmt: skip
    return photos


def centred(a: np.ndarray) -> np.ndarray:
    """Rows less their mean: what sets one crop's feature apart from the others'."""
    return a - a.mean(axis=0, keepdims=True)


def pairwise_median(a: np.ndarray) -> float:
    """Median cosine between two different rows of unit rows a."""
    c = a @ a.T
    return float(np.median(c[np.triu_indices(len(a), 1)])) if len(a) > 1 else 1.0


def cos_stats(a: np.ndarray, b: np.ndarray, low: float = 1.0) -> dict:
    """Row cosines of unit rows a, b: median, the `low` percentile, min."""
    c = np.sum(a * b, axis=1) / (
        np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1) + 1e-12
    )
    return {"median": float(np.median(c)), f"p{low:g}": float(np.percentile(c, low)),
            "min": float(c.min())}  # fmt: skip


# --- the dense pass --------------------------------------------------------------


class Dense:
    """MaskCLIP-style dense features of ptovs's OpenCLIP visual tower."""

    def __init__(self, enc, size: int, mode: str):
        v = enc.net.visual
        self.v, self.enc, self.size, self.mode = v, enc, int(size), mode
        patch = v.conv1.kernel_size[0]
        if self.size % patch:
            raise ValueError(f"dense size {size} is not a multiple of {patch}")
        self.grid = self.size // patch
        pos = v.positional_embedding.detach()  # [1 + G0², w]
        g0 = round((pos.shape[0] - 1) ** 0.5)
        if self.grid != g0:
            grid = pos[1:].reshape(1, g0, g0, -1).permute(0, 3, 1, 2)
            grid = torch.nn.functional.interpolate(
                grid, size=(self.grid, self.grid), mode="bicubic", align_corners=False
            )
            pos = torch.cat(
                [pos[:1], grid.permute(0, 2, 3, 1).reshape(-1, pos.shape[1])]
            )
        self.pos = pos

    def _last_block(self, r, x: torch.Tensor) -> torch.Tensor:
        if self.mode == "tokens":
            return r(x)
        a = r.attn  # value path only: each token attends to itself (MaskCLIP)
        w = a.embed_dim
        y = r.ln_1(x)
        val = torch.nn.functional.linear(
            y, a.in_proj_weight[2 * w :], a.in_proj_bias[2 * w :]
        )
        x = x + r.ls_1(a.out_proj(val))
        return x + r.ls_2(r.mlp(r.ln_2(x)))

    @torch.inference_mode()
    def patches(self, image: np.ndarray) -> torch.Tensor:
        """[G*G, dim] patch features (projected, not normalised) of one photo."""
        import cv2

        v, s = self.v, self.size
        img = cv2.resize(image, (s, s), interpolation=cv2.INTER_AREA)
        x = torch.from_numpy(img).float().div_(255.0).permute(2, 0, 1)[None]
        x = (x - self.enc._mean) / self.enc._std
        t = v.conv1(x).flatten(2).transpose(1, 2)  # [1, G², w]
        cls = v.class_embedding.to(t.dtype).expand(1, 1, -1)
        t = v.ln_pre(torch.cat([cls, t], dim=1) + self.pos)
        blocks = v.transformer.resblocks
        for r in blocks[:-1]:
            t = r(t)
        t = self._last_block(blocks[-1], t)
        return v.ln_post(t[0, 1:]) @ v.proj

    def weights(self, level, h: int, w: int) -> np.ndarray:
        """[n, G²] fraction of each patch's area inside each segment's mask."""
        g = self.grid
        cy = (np.arange(h) * g) // h
        cx = (np.arange(w) * g) // w
        cell = (cy[:, None] * g + cx[None, :]).ravel()
        area = np.bincount(cell, minlength=g * g).astype(np.float32)
        if level.masks is None:
            lab = level.labels.ravel()
            ok = lab >= 0
            cnt = np.bincount(lab[ok].astype(np.int64) * g * g + cell[ok],
                              minlength=level.n * g * g)  # fmt: skip
            return cnt.reshape(level.n, g * g).astype(np.float32) / area
        return np.stack([np.bincount(cell, weights=level.mask(k).ravel().astype(np.float32),
                                     minlength=g * g) / area
                         for k in range(level.n)]).astype(np.float32)  # fmt: skip

    def features(self, photo: dict) -> np.ndarray:
        """[len(photo ids), dim] unit rows: each kept segment's pooled feature
        (every segment of the photo is pooled, as a real pass would)."""
        p = self.patches(photo["image"]).float().numpy()
        h, w = photo["image"].shape[:2]
        rows = []
        for lv in photo["levels"]:
            wt = self.weights(lv, h, w)
            f = (wt @ p) / np.maximum(wt.sum(1, keepdims=True), 1e-12)
            rows.append(f / np.maximum(np.linalg.norm(f, axis=1, keepdims=True), 1e-12))
        return np.stack([rows[li][k] for li, k in photo["ids"]])


# --- timing -------------------------------------------------------------------------


def time_config(run, photos: list[dict], warm, repeats: int):
    """(median seconds per photo, all per-photo times, the last run's outputs)."""
    warm()
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = [run(p) for p in photos]
        times.append((time.perf_counter() - t0) / len(photos))
    return statistics.median(times), times, out


class Bf16Net:
    """What OpenClipEncoder calls (`encode_image`), on a bf16 copy of the model."""

    def __init__(self, net):
        import copy

        self.net = copy.deepcopy(net).to(torch.bfloat16).eval()

    def encode_image(self, x: torch.Tensor) -> torch.Tensor:
        return self.net.encode_image(x.to(torch.bfloat16)).float()


def set_variant(enc, base_net, variant: str) -> dict:
    """Point ptovs's encoder at the variant; facts about it."""
    enc.net = base_net
    enc._autocast = lambda: torch.autocast("cpu", enabled=False)
    if variant == "bf16":
        enc._autocast = lambda: torch.autocast("cpu", dtype=torch.bfloat16)
        return {}
    if variant == "bf16w":
        enc.net = Bf16Net(base_net)
        return {}
    if variant == "int8":
        q = torch.ao.quantization.quantize_dynamic(
            base_net, {torch.nn.Linear}, dtype=torch.qint8
        )
        dyn = torch.ao.nn.quantized.dynamic.Linear
        n = sum(isinstance(m, dyn) for m in q.visual.modules())
        enc.net = q.eval()
        return {"quantized_linear_modules_visual": n}
    return {}


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--photos", type=int, default=3)
    ap.add_argument("--real", type=Path, default=None,
                    help="folder of real photo sets (default data/real)")  # fmt: skip
    ap.add_argument("--long-side", type=int, default=700)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--batch", type=int, nargs="+", default=[1, 16, 64])
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    ap.add_argument("--dense-sizes", type=int, nargs="*", default=[224, 448])
    ap.add_argument("--dense-modes", nargs="*", default=["tokens", "value"],
                    choices=["tokens", "value"])  # fmt: skip
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--max-crops", type=int, default=0,
                    help="keep at most this many crops a photo (0: all; trials)")  # fmt: skip
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--model", default="ViT-B-16")
    ap.add_argument("--out", type=Path, default=Path("work/openclip_cpu.json"))
    args = ap.parse_args()

    from ptovs.atomic import atomic_file
    from ptovs.encoders.openclip import OpenClipEncoder

    def save() -> None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        with atomic_file(args.out, keep_suffix=False) as tmp:
            tmp.write_text(json.dumps(res, indent=1))

    # fp32 first: the reference of every cosine
    variants = ["fp32"] + [v for v in args.variants if v != "fp32"]
    res: dict = {"machine": machine(args.threads), "args": {
        k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}}  # fmt: skip
    torch.manual_seed(args.seed)
    t0 = time.perf_counter()
    enc = OpenClipEncoder(args.model, random_weights=True)
    base = enc.net
    vis = base.visual
    res["model"] = dict(name=args.model, weights=f"random (torch.manual_seed({args.seed}))",
                        build_s=time.perf_counter() - t0,
                        visual_params=sum(p.numel() for p in vis.parameters()))  # fmt: skip

    real = real_dir(args.real)
    photos = prepare(pick_photos(real, args.photos), args.long_side, args.max_crops)
    res["photos"] = [dict(photo=f"{p['path'].parent.parent.name}/{p['path'].name}",
                          size=list(p["image"].shape[1::-1]),
                          segments=[lv.n for lv in p["levels"]],
                          crops_kept=len(p["ids"]), segment_s=p["segment_s"],
                          crop_s=p["crop_s"]) for p in photos]  # fmt: skip
    crops_per_photo = statistics.mean(len(p["ids"]) for p in photos)
    res["rows"] = rows = []
    ref: np.ndarray | None = None
    save()

    for variant in variants:
        try:
            facts = set_variant(enc, base, variant)
        except Exception as exc:  # noqa: BLE001 - recorded: this build refuses it
            rows.append(dict(variant=variant, error=f"{type(exc).__name__}: {exc}"))
            print(f"{variant}: {type(exc).__name__}: {exc}", flush=True)
            save()
            continue
        for t in args.threads:
            torch.set_num_threads(t)
            for b in args.batch:
                enc.batch_size = b
                row = dict(variant=variant, threads=t, batch=b, **facts)
                try:
                    s, times, out = time_config(
                        lambda p: enc.encode_images(p["crops"]),
                        photos,
                        lambda b=b: enc.encode_images(photos[0]["crops"][:b]),
                        args.repeats,
                    )
                except Exception as exc:  # noqa: BLE001 - recorded
                    row["error"] = f"{type(exc).__name__}: {exc}"
                    rows.append(row)
                    print(f"{variant} t{t} b{b}: {row['error']}", flush=True)
                    save()
                    continue
                feats = np.concatenate(out)
                if ref is None:
                    ref = feats
                    res["fp32_pairwise_cos_median"] = pairwise_median(ref)
                row.update(s_per_photo=s, times=times, crops_per_s=crops_per_photo / s,
                           cos=cos_stats(feats, ref),
                           cos_centred=cos_stats(centred(feats), centred(ref)))  # fmt: skip
                if variant != "fp32":
                    row["kept"] = row["cos"]["min"] >= KEEP_COS
                    row["kept_centred"] = row["cos_centred"]["min"] >= KEEP_COS
                rows.append(row)
                print(f"{variant} t{t} b{b}: {s:.2f} s/photo, "
                      f"{crops_per_photo / s:.2f} crops/s, cos min {row['cos']['min']:.4f}",
                      flush=True)  # fmt: skip
                save()
    set_variant(enc, base, "fp32")

    for size in args.dense_sizes:
        for mode in args.dense_modes:
            try:
                dense = Dense(enc, size, mode)
            except Exception as exc:  # noqa: BLE001 - recorded
                rows.append(dict(variant=f"dense{size}-{mode}", error=str(exc)))
                continue
            for t in args.threads:
                torch.set_num_threads(t)
                row = dict(
                    variant=f"dense{size}-{mode}", threads=t, batch=1, grid=dense.grid
                )
                s, times, out = time_config(
                    dense.features, photos, lambda d=dense: d.patches(photos[0]["image"]),
                    args.repeats,
                )  # fmt: skip
                row.update(s_per_photo=s, times=times, crops_per_s=crops_per_photo / s)
                if ref is not None:
                    dense_f = np.concatenate(out)
                    row["cos"] = cos_stats(dense_f, ref, low=10)
                    row["cos_centred"] = cos_stats(
                        centred(dense_f), centred(ref), low=10
                    )
                    # chance level: each dense feature against another segment's crop
                    other = np.roll(ref, 1, axis=0)
                    row["cos_other_segment_median"] = cos_stats(dense_f, other)[
                        "median"
                    ]
                    row["cos_centred_other_segment_median"] = cos_stats(
                        centred(dense_f), centred(other)
                    )["median"]
                rows.append(row)
                print(f"dense {size} {mode} t{t}: {s:.2f} s/photo, cos median "
                      f"{row.get('cos', {}).get('median', float('nan')):.3f} (another "
                      f"segment's: {row.get('cos_other_segment_median', float('nan')):.3f})",
                      flush=True)  # fmt: skip
                save()

    ok = [r for r in rows if "s_per_photo" in r]
    n_img = COLLECTION[0] * COLLECTION[1]
    for r in ok:
        r["projected_collection_s"] = n_img * r["s_per_photo"]
    fp32 = [r for r in ok if r["variant"] == "fp32"]
    if fp32:
        best = min(fp32, key=lambda r: r["s_per_photo"])
        res["fp32_best"] = dict(threads=best["threads"], batch=best["batch"],
                                s_per_photo=best["s_per_photo"],
                                crops_per_s=best["crops_per_s"],
                                crops_per_photo=crops_per_photo,
                                projected_collection_s=best["projected_collection_s"],
                                collection=f"{COLLECTION[0]} photos x {COLLECTION[1]} images")  # fmt: skip
    save()

    print(f"\n{len(photos)} photo(s), {crops_per_photo:.1f} crops a photo; "
          f"projected = {COLLECTION[0]} x {COLLECTION[1]} x s/photo\n")  # fmt: skip
    print("| variant | threads | batch | s/photo | crops/s | cos median | cos low "
          "| cos min | centred cos median | centred cos min | kept (cos, centred) "
          "| projected (h) |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---:|")
    for r in rows:
        if "error" in r:
            print(f"| {r['variant']} | {r.get('threads', '')} | {r.get('batch', '')} "
                  f"| error: {r['error'][:80]} | | | | | | | | |")  # fmt: skip
            continue
        c = r.get("cos", {})
        low = next((v for k, v in c.items() if k.startswith("p")), float("nan"))
        lowk = next((k for k in c if k.startswith("p")), "")
        cc = r.get("cos_centred", {})
        yn = {True: "yes", False: "no"}
        kept = (f"{yn[r['kept']]}, {yn[r['kept_centred']]}" if "kept" in r
                else "ref" if r["variant"] == "fp32" else "-")  # fmt: skip
        print(f"| {r['variant']} | {r['threads']} | {r['batch']} | {r['s_per_photo']:.2f} "
              f"| {r['crops_per_s']:.2f} | {c.get('median', float('nan')):.4f} "
              f"| {low:.4f} ({lowk}) | {c.get('min', float('nan')):.4f} "
              f"| {cc.get('median', float('nan')):.4f} | {cc.get('min', float('nan')):.4f} "
              f"| {kept} "
              f"| {r['projected_collection_s'] / 3600:.1f} |")  # fmt: skip
    for r in rows:
        if "cos_other_segment_median" in r:
            print(f"{r['variant']} t{r['threads']}: chance level (median cosine to "
                  f"another segment's crop feature) {r['cos_other_segment_median']:.4f}, "
                  f"centred {r['cos_centred_other_segment_median']:.4f}")  # fmt: skip
    if "fp32_pairwise_cos_median" in res:
        print(f"fp32 crop features, median cosine between two crops: "
              f"{res['fp32_pairwise_cos_median']:.4f} (random weights: one common "
              "direction; the centred cosines remove it)")  # fmt: skip
    if fp32:
        b = res["fp32_best"]
        print(f"\nfp32 best: {b['threads']} thread(s), batch {b['batch']}: "
              f"{b['crops_per_s']:.2f} crops/s, {b['s_per_photo']:.2f} s/photo, "
              f"{b['projected_collection_s'] / 3600:.1f} h for {b['collection']}")  # fmt: skip
    print(f"results: {args.out}")


if __name__ == "__main__":
    main()
