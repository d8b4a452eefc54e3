"""Real photos through `ptovs reconstruct` from images alone (`--real DIR`, default data/real).

python bench/real.py                                   # both sets, as they are (6 MP)
python bench/real.py --sets fountain_p11 --megapixels 12   # resized to 12 MP first
python bench/real.py --iterations 400                  # a shorter budget

For each set: the photos (optionally resized to `--megapixels`, JPEG q95) are copied
to a folder of their own and `ptovs reconstruct --data FOLDER` runs with the default
config (SfM first, cached). Reported: registered photos, the chosen downscale and
working size, SfM and training time, the process's peak RSS, PSNR on train and
held-out photos (the split SfM leaves), and the pose error against the set's
ground-truth cameras after a Sim3 alignment of the camera centres. A picture of
each held-out photo beside its render goes to docs/img/real_<set>.jpg.

Results go to <work>/bench_real.json and print as markdown rows.
"""

from __future__ import annotations

import argparse
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import (  # noqa: E402  (same folder)
    ROOT,
    Results,
    camera_pose,
    pose_error,
    print_header,
    run_ptovs,
)

REAL = ROOT / "data" / "real"  # herzjesu_p8/, fountain_p11/: images/ + COLMAP model


def copy_photos(src: Path, dst: Path, megapixels: float) -> tuple[int, int]:
    """The set's photos under dst/images, resized to `megapixels` if > 0; the
    (width, height) they have there."""
    if dst.exists():
        shutil.rmtree(dst)
    (dst / "images").mkdir(parents=True)
    size = (0, 0)
    for path in sorted((src / "images").glob("*.jpg")):
        if megapixels <= 0:
            shutil.copy2(path, dst / "images" / path.name)
            h, w = cv2.imread(str(path), cv2.IMREAD_REDUCED_GRAYSCALE_8).shape
            size = (w * 8, h * 8)
            continue
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        s = np.sqrt(megapixels * 1e6 / (img.shape[0] * img.shape[1]))
        img = cv2.resize(img, None, fx=s, fy=s, interpolation=cv2.INTER_CUBIC)
        cv2.imwrite(
            str(dst / "images" / path.name), img, [cv2.IMWRITE_JPEG_QUALITY, 95]
        )
        size = (img.shape[1], img.shape[0])
    return size


def truth_cameras(src: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{photo name: (R camera-to-world, centre)} from gt_dense_cameras."""
    out = {}
    for path in sorted((src / "gt_dense_cameras").glob("*.camera")):
        rows = [
            [float(x) for x in line.split()] for line in path.read_text().split("\n")
        ]
        rows = [r for r in rows if r]
        out[path.name.removesuffix(".camera")] = (
            np.array(rows[4:7]),
            np.array(rows[7]),
        )
    return out


def picture(art_path: Path, scene, out: Path) -> list[float]:
    """Held-out photos beside their renders (own embedding), one row each."""
    import torch

    from ptovs.artifacts import Artifact
    from ptovs.field.losses import psnr
    from ptovs.field.render import WildField
    from ptovs.raster import Camera

    rows, values = [], []
    with Artifact(art_path) as art, torch.no_grad():
        field = WildField.from_artifact(art)
        for v in scene.test_views():
            img = scene.load_image(v)
            emb = field.embeddings_of([v.name]) if field.wild else None
            rgb = field.render(Camera.from_view(v), emb)[0].clamp(0, 1).numpy()
            values.append(float(psnr(rgb, img)))
            rows.append(np.concatenate([img, rgb], axis=1))
    grid = (np.concatenate(rows, axis=0) * 255).round().astype(np.uint8)
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(
        str(out), cv2.cvtColor(grid, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 88]
    )
    return values


def run_set(args: argparse.Namespace, name: str) -> dict:
    from ptovs.artifacts import Artifact, read_json_dataset
    from ptovs.scene import load_scene

    src = args.real / name
    tag = f"{name}_{args.megapixels:g}mp" if args.megapixels > 0 else name
    folder = args.work / "photos" / tag
    size = copy_photos(src, folder, args.megapixels)
    work = args.work / "runs"
    sets = (
        [f"--set=reconstruct.iterations={args.iterations}"] if args.iterations else []
    ) + [f"--set={kv}" for kv in args.set]
    wall, rss, stdout = run_ptovs(work, *sets, "reconstruct", "--data", str(folder))
    art = Path(stdout.strip().splitlines()[-1].split(": ", 1)[1])
    posed = next((work / tag / "sfm").glob("*/sparse")).parent
    scene = load_scene(posed)
    with Artifact(art) as a:
        m = read_json_dataset(a.root()["metrics_json"])
    n_photos = len(list((folder / "images").glob("*.jpg")))
    v0 = scene.views[0]
    res = dict(
        photos=n_photos,
        photo_size=list(size),
        registered=len(scene.views),
        unregistered=sorted(
            {p.name for p in (folder / "images").glob("*.jpg")}
            - {v.name for v in scene.views}
        ),
        downscale=scene.downscale,
        working_size=[v0.width, v0.height],
        wall_s=round(wall, 1),
        train_s=m.get("train_seconds"),
        s_per_iteration=m.get("seconds_per_iteration"),
        peak_rss_mb=round(rss),
        psnr_train=m.get("psnr_train"),
        psnr_test=m.get("psnr_test"),
        gaussians=m.get("gaussians"),
        test_views=[v.name for v in scene.test_views()],
    )
    est = {v.name: camera_pose(v.cam_from_world) for v in scene.views}
    res.update(pose_error(est, truth_cameras(src)))
    # the docs' picture is the default config's; runs with --set keep theirs in work
    pic = (
        ROOT / "docs" / "img" / f"real_{tag}.jpg"
        if not args.set
        else args.work / f"real_{tag}_set.jpg"
    )
    res["picture"] = str(pic)
    picture(art, scene, pic)
    return res


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sets", nargs="+", default=["fountain_p11", "herzjesu_p8"])
    p.add_argument(
        "--real",
        type=Path,
        default=REAL,
        help="folder of real photo sets (default data/real)",
    )
    p.add_argument("--megapixels", type=float, default=0.0, help="resize first (0: no)")
    p.add_argument("--iterations", type=int, default=0, help="0: the default")
    p.add_argument("--work", type=Path, default=ROOT / "work" / "real")
    p.add_argument(
        "--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
        help="a config override for ptovs reconstruct (repeatable)",
    )  # fmt: skip
    args = p.parse_args()
    res = Results(args.work / "bench_real.json")
    print_header(
        "set", "photos", "registered", "r, working size", "SfM + train wall (s)",
        "s/it", "peak RSS (MB)", "PSNR train / held-out", "rotation median (°)",
    )  # fmt: skip
    for name in args.sets:
        r = run_set(args, name)
        key = f"{name}/{args.megapixels:g}mp/{args.iterations or 'default'}" + "".join(
            f"/{kv}" for kv in args.set
        )
        res[key] = r
        res.save()
        print(
            f"| {name} {r['photo_size'][0]}×{r['photo_size'][1]} | {r['photos']} | "
            f"{r['registered']} | {r['downscale']}, {r['working_size'][0]}×"
            f"{r['working_size'][1]} | {r['wall_s']} | {r['s_per_iteration']} | "
            f"{r['peak_rss_mb']} | {r['psnr_train']} / {r['psnr_test']} | "
            f"{r['rot_median_deg']:.2f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
