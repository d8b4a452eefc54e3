"""Reconstruct beside OpenSplat on a CPU: the same photos, poses and iterations.

python bench/peers.py --opensplat-src DIR                  # build, then every scene
python bench/peers.py --opensplat-src DIR --fetchcontent DEPS --scenes herzjesu_p8 \
    --iterations 500                                       # what the figures used

OpenSplat (C++ on libtorch; https://github.com/pierotofy/OpenSplat, AGPL-3.0) is
built from a source tree you give (`--opensplat-src`; nothing of it is in this
repository) against this environment's torch and the system's OpenCV (Debian: `apt
install libopencv-dev`), with `-DGPU_RUNTIME=CPU`, into `<work>/build/<id>/` (reused
once built). Without a network, `--fetchcontent DEPS` holds the sources of its CMake
downloads as `DEPS/nlohmann_json`, `DEPS/nanoflann` and `DEPS/cxxopts`.

Scenes (`--scenes`; default `herzjesu_p8 fountain_p11 bench:0`): a real set from
`--real DIR`, posed once by `ptovs sfm` (every 10th photo held out), or `bench:SEED`,
a bench-preset synthetic scene. Both tools start from that one COLMAP model at the
same working size: OpenSplat gets a project of the train photos (`-d 1
--num-downscales 0 --keep-crs`). Each tool: the same iterations, `--threads` threads,
one job at a time, under GNU time.

Parts (`--parts`):
  check  OpenSplat trains 20 steps and renders a held-out photo itself
         (`--val-render`); its PLY drawn in depth order (any 3DGS viewer) and by
         `opensplat_draw` (our reading of its CPU renderer, whose sort key is not
         the depth) against that render (and again after --iterations)
  same   both tools at --iterations: wall time, s a step, peak RSS, Gaussians,
         held-out PSNR (OpenSplat's PLY both ways, every pixel; ptovs's stage
         figures), OpenSplat's PSNR curve (a PLY every tenth of the run), and ptovs
         plain 3DGS (`wild=false`), OpenSplat's like-for-like peer
  reach  whole ptovs runs at 0.1, 0.2, 0.4 and 0.6 of --iterations: each variant's
         time to OpenSplat's best held-out PSNR, linear between measured points

Results: <work>/peers.json (a part finished at these --iterations is kept; a run
cut off goes on), then markdown tables.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import (  # noqa: E402  (same folder)
    ROOT,
    Results,
    bench_scene,
    cpu_model,
    run_ptovs,
    thread_env,
)

REACH = (0.1, 0.2, 0.4, 0.6)  # ptovs's shorter runs, as fractions of --iterations
VARIANTS = {"ptovs": (), "ptovs_plain": ("wild=false",)}  # record key: its --set's

FETCHED = ("nlohmann_json", "nanoflann", "cxxopts")
"""The FetchContent names of OpenSplat's CMakeLists.txt, as `--fetchcontent` holds them."""
BACKGROUND = (0.6130, 0.0101, 0.3984)
"""OpenSplat's background colour (nerfstudio's default; fixed: its PLY does not carry
it, and no optimiser steps it)."""


# ------------------------------------------------------------------------ build
def source_id(src: Path) -> str:
    """The source tree's git commit, or (not a git checkout) a digest of its files."""
    git = subprocess.run(["git", "-C", str(src), "rev-parse", "HEAD"],
                         capture_output=True, text=True)  # fmt: skip
    if git.returncode == 0 and (src / ".git").exists():
        dirty = subprocess.run(["git", "-C", str(src), "status", "--porcelain"],
                               capture_output=True, text=True).stdout.strip()  # fmt: skip
        return git.stdout.strip() + ("-dirty" if dirty else "")
    h = hashlib.sha256()
    for path in sorted(src.rglob("*")):
        if path.is_file() and ".git" not in path.parts and "build" not in path.parts:
            h.update(str(path.relative_to(src)).encode())
            h.update(path.read_bytes())
    return "content-" + h.hexdigest()[:16]


def build_opensplat(src: Path, cache: Path, deps: Path | None, jobs: int) -> dict:
    """Configure and build OpenSplat (CPU) from `src` into a cache folder; the
    record: its binary, the source id, torch's version, the time it took. A failure
    raises RuntimeError naming the step (configure or build) and the log's end."""
    import torch

    src = src.resolve()
    if not (src / "CMakeLists.txt").is_file() or not (src / "opensplat.cpp").is_file():
        raise SystemExit(f"--opensplat-src {src}: not an OpenSplat source tree "
                         "(no CMakeLists.txt and opensplat.cpp)")  # fmt: skip
    sid = source_id(src)
    options = ["-DGPU_RUNTIME=CPU", "-DCMAKE_BUILD_TYPE=Release",
               f"-DCMAKE_PREFIX_PATH={torch.utils.cmake_prefix_path}"]  # fmt: skip
    if deps is not None:
        missing = [n for n in FETCHED if not (deps / n / "CMakeLists.txt").is_file()]
        if missing:
            raise SystemExit(f"--fetchcontent {deps}: no source of {', '.join(missing)} "
                             f"(want {deps}/<name>/CMakeLists.txt for {FETCHED})")  # fmt: skip
        options.append("-DFETCHCONTENT_FULLY_DISCONNECTED=ON")
        options += [f"-DFETCHCONTENT_SOURCE_DIR_{n.upper()}={(deps / n).resolve()}"
                    for n in FETCHED]  # fmt: skip
    key = hashlib.sha256(json.dumps([sid, torch.__version__, options[:2]]).encode())
    out = cache / key.hexdigest()[:12]
    binary = out / "opensplat"
    record = {"source": str(src), "source_id": sid, "torch": torch.__version__,
              "options": options, "binary": str(binary)}  # fmt: skip
    if binary.is_file() and (out / "record.json").is_file():
        return json.loads((out / "record.json").read_text())
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    gen = ["-G", "Ninja"] if shutil.which("ninja") else []
    steps = (
        ("configure", ["cmake", "-S", str(src), "-B", str(out), *gen, *options]),
        ("build", ["cmake", "--build", str(out), "--target", "opensplat",
                   "-j", str(jobs)]),
    )  # fmt: skip
    for step, cmd in steps:
        log = out / f"{step}.log"
        with log.open("w") as fo:
            proc = subprocess.run(cmd, stdout=fo, stderr=subprocess.STDOUT)
        if proc.returncode != 0:
            tail = log.read_text(errors="replace")[-4000:]
            raise RuntimeError(f"OpenSplat {step} failed ({log}):\n{tail}")
    if not binary.is_file():
        raise RuntimeError(f"OpenSplat built, but {binary} is not there")
    record["build_s"] = round(time.perf_counter() - t0, 1)
    version = subprocess.run([str(binary), "--version"], capture_output=True, text=True)
    record["version"] = (version.stdout or version.stderr).strip()
    (out / "record.json").write_text(json.dumps(record, indent=1))
    return record


# ----------------------------------------------------------------------- scenes
def prepare_scene(args: argparse.Namespace, spec: str) -> Path:
    """The posed scene folder of `spec` (a real set's name, or bench:SEED)."""
    if spec.startswith("bench:"):
        return bench_scene(args.work / "data", int(spec.split(":", 1)[1]))
    from real import copy_photos  # noqa: PLC0415  (same folder; cv2 only)

    src = args.real / spec
    if not (src / "images").is_dir():
        raise SystemExit(f"--scenes {spec}: no {src}/images (give --real DIR)")
    folder = args.work / "photos" / spec
    if not (folder / "images").is_dir():
        copy_photos(src, folder, 0)
    run_ptovs(args.work / "runs", "sfm", "--data", str(folder))  # cached after once
    return next((args.work / "runs" / spec / "sfm").glob("*/sparse")).parent


def export_project(scene, proj: Path, val) -> dict:
    """OpenSplat's COLMAP project for `scene`: its train photos at ptovs's working
    size (PNG, from ptovs's own loader, so both tools see the same pixels) and a
    sparse/0 model of them with every point of the scene's cloud, plus `val` (one
    held-out view) for OpenSplat's `--val-image`, which it withholds from training."""
    import cv2
    import numpy as np
    import pycolmap

    if proj.exists():
        shutil.rmtree(proj)
    (proj / "images").mkdir(parents=True)
    sparse = proj / "sparse" / "0"
    sparse.mkdir(parents=True)
    rec = pycolmap.Reconstruction()
    views = [*scene.train_views(), *([val] if val is not None else [])]
    for i, v in enumerate(views, 1):
        img = scene.load_image(v)
        png = np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)[..., ::-1]
        cv2.imwrite(str(proj / "images" / f"{v.stem}.png"), png)
        K = v.K
        rec.add_camera_with_trivial_rig(pycolmap.Camera(
            model="PINHOLE", width=v.width, height=v.height,
            params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], camera_id=i))  # fmt: skip
        m = np.asarray(v.cam_from_world, np.float64)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(m[:3, :3].copy()), m[:3, 3].copy())
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=f"{v.stem}.png", camera_id=i, image_id=i), pose
        )
    for xyz, rgb in zip(scene.points_xyz, scene.points_rgb, strict=True):
        rec.add_point3D(np.asarray(xyz, np.float64), pycolmap.Track(), rgb)
    rec.write_binary(str(sparse))
    return {"train": len(scene.train_views()), "points": len(scene.points_xyz),
            "val_image": f"{val.stem}.png" if val is not None else None}  # fmt: skip


# ------------------------------------------------------------------------- runs
def timed(cmd: list[str], env: dict, log: Path) -> tuple[float, float, list, dict]:
    """Run `cmd` under GNU time; (wall s, peak RSS MB, [(seconds, stdout line)], and
    how quiet the machine was: its CPU seconds and the 1-min load before and after),
    each stdout line timestamped as it arrives (OpenSplat prints a line a step)."""
    gnu_time = shutil.which("time") or "/usr/bin/time"
    full = [gnu_time, "-f", "PEERS_PEAK_KB %M %U %S", *cmd]
    lines: list[tuple[float, str]] = []
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    with log.open("w") as fo:
        proc = subprocess.Popen(full, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                text=True, env=env)  # fmt: skip
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append((time.perf_counter() - t0, line.rstrip()))
            fo.write(line)
        proc.wait()
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        tail = "\n".join(text for _, text in lines[-30:])
        raise RuntimeError(f"{' '.join(cmd)} failed ({log}):\n{tail}")
    peak = [t.split() for _, t in lines if t.startswith("PEERS_PEAK_KB ")]
    rss = float(peak[-1][1]) / 1024.0 if peak else float("nan")
    cpu = float(peak[-1][2]) + float(peak[-1][3]) if peak else float("nan")
    quiet = {"cpu_s": round(cpu, 1),
             "load": [round(load0, 2), round(os.getloadavg()[0], 2)]}  # fmt: skip
    return wall, rss, lines, quiet


def run_opensplat(binary: str, proj: Path, out: Path, iterations: int, threads: int,
                  val: str | None, every: int = 0, val_render: bool = False,
                  resume: Path | None = None) -> dict:  # fmt: skip
    """OpenSplat --cpu on `proj` at its working size (no coarse-to-fine), its PLY in
    the model's frame. `every` > 0 also saves a PLY every that many steps; `resume`
    goes on from a PLY it saved (to step `iterations`)."""
    out.mkdir(parents=True, exist_ok=True)
    cmd = [binary, str(proj), "--cpu", "-n", str(iterations), "-d", "1",
           "--num-downscales", "0", "--keep-crs", "-o", str(out / "splat.ply")]  # fmt: skip
    if val:
        cmd += ["--val", "--val-image", val]
        if val_render:
            cmd += ["--val-render", str(out / "val")]
    if every > 0:
        cmd += ["-s", str(every)]
    if resume is not None:
        cmd += ["--resume", str(resume)]
    wall, rss, lines, quiet = timed(cmd, thread_env(threads), out / "opensplat.log")
    steps = [(t, int(x.split()[1].rstrip(":"))) for t, x in lines
             if x.startswith("Step ")]  # fmt: skip
    # the training loop's own pace: the first to the last step line
    rate = ((steps[-1][0] - steps[0][0]) / (steps[-1][1] - steps[0][1])
            if len(steps) > 1 and steps[-1][1] > steps[0][1] else float("nan"))  # fmt: skip
    return {"wall_s": round(wall, 1), "peak_rss_mb": round(rss), **quiet,
            "s_per_iteration": round(rate, 4), "iterations": iterations,
            "step_times": {str(k): round(t, 2) for t, k in steps
                           if every > 0 and k % every == 0},
            "ply": str(out / "splat.ply")}  # fmt: skip


def run_ours(args: argparse.Namespace, scene_dir: Path, iterations: int, tag: str,
             *sets: str) -> dict:  # fmt: skip
    """ptovs reconstruct on the scene (a fresh work folder), its stage's figures."""
    from ptovs.artifacts import Artifact, read_json_dataset

    work = args.work / "ours" / tag
    shutil.rmtree(work, ignore_errors=True)
    cmd = [sys.executable, "-m", "ptovs", "-q", "--threads", str(args.threads),
           "--work-dir", str(work), f"--set=reconstruct.iterations={iterations}",
           *(f"--set=reconstruct.{kv}" for kv in sets),
           "reconstruct", "--data", str(scene_dir)]  # fmt: skip
    work.mkdir(parents=True)
    wall, rss, lines, quiet = timed(
        cmd, thread_env(args.threads), work / "reconstruct.log"
    )
    art = Path([x for _, x in lines if ": " in x and x.endswith(".h5")][-1]
               .split(": ", 1)[1])  # fmt: skip
    with Artifact(art) as a:
        m = read_json_dataset(a.root_item("metrics_json"))
    return {"wall_s": round(wall, 1), "peak_rss_mb": round(rss), **quiet,
            "s_per_iteration": m.get("seconds_per_iteration"), "iterations": iterations,
            "train_s": m.get("train_seconds"), "gaussians": m.get("gaussians"),
            "psnr_test": m.get("psnr_test"), "psnr_test_nerfw": m.get("psnr_test_nerfw"),
            "psnr_test_clean": m.get("psnr_test_clean"), "artifact": str(art)}  # fmt: skip


# ------------------------------------------------------------------- evaluation
def ply_field(path: Path):
    """OpenSplat's PLY as ptovs Gaussians and SH (its activations: exp scales,
    sigmoid opacity, normalised quaternions)."""
    import numpy as np
    import torch

    from ptovs.field.ply import read_ply, sh_degree_of
    from ptovs.raster import Gaussians

    p = read_ply(path)
    g = Gaussians(
        means=torch.from_numpy(p["means"]).float(),
        quats=torch.nn.functional.normalize(
            torch.from_numpy(p["quats"]).float(), dim=-1
        ),
        scales=torch.exp(torch.from_numpy(p["log_scales"]).float()),
        opacities=torch.sigmoid(torch.from_numpy(p["opacity_logits"]).float()),
    )
    sh = torch.from_numpy(np.ascontiguousarray(p["sh"])).float()
    return g, sh, sh_degree_of(p["sh"])


def render_ply(field, view):
    """OpenSplat's field rendered by ptovs's rasterizer at a view, [H, W, 3] in [0, 1]."""
    import torch

    from ptovs.field.render import gaussian_colors
    from ptovs.raster import Camera, render

    g, sh, degree = field
    cam = Camera.from_view(view)
    with torch.no_grad():
        colors = gaussian_colors(g.means, sh, degree, cam)  # max(SH + 0.5, 0)
        out = render(g, cam, colors, background=torch.tensor(BACKGROUND), depth=False)
    return out.image.clamp(0, 1).numpy()


def opensplat_frame(views) -> tuple:
    """OpenSplat's normalisation of a COLMAP project (its autoScaleAndCenterPoses):
    the mean camera centre, and 1 / the largest centre coordinate about it."""
    import numpy as np

    centres = np.stack([-v.cam_from_world[:3, :3].T @ v.cam_from_world[:3, 3]
                        for v in views]).astype(np.float32)  # fmt: skip
    mean = centres.mean(0)
    return mean, float(1.0 / np.abs(centres - mean).max())


def opensplat_draw(ply: dict, view, frame: tuple, step: int):
    """A view as OpenSplat's CPU renderer draws its PLY: our own NumPy reading of its
    image formation (projection, EWA with 0.3 px dilation, 3σ boxes, alpha ≤ 0.999,
    its fixed background), with one difference from a standard 3DGS renderer that
    matters: it orders the Gaussians by a key read from a stride-3 view of their
    NDC coordinates as if it were contiguous, so Gaussian a's key is the (2 + a)-th
    number of the [N, 3] array (a depth for a ≡ 0 mod 3, another Gaussian's x or y
    otherwise). This reproduces its own `--val-render` images to 53 dB (8-bit files;
    `check`), where a depth-ordered render of the same PLY agrees to 27-34 dB.
    SH degree min(step // 1000, 3), as its forward uses at that step."""
    import numpy as np
    import torch

    from ptovs.raster._sh import eval_sh

    p = ply  # read_ply's dict, read once by the caller for every view
    mean, sc = frame
    means = (p["means"] - mean) * sc
    scales = np.exp(p["log_scales"]) * sc
    m = np.asarray(view.cam_from_world, np.float32)
    R = m[:3, :3]
    centre = (-R.T @ m[:3, 3] - mean) * sc
    t = -R @ centre
    q = p["quats"] / np.linalg.norm(p["quats"], axis=1, keepdims=True)
    w, x, y, z = q.T
    rot = np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)  # fmt: skip
    M = rot * scales[:, None, :]
    cov3 = M @ M.transpose(0, 2, 1)
    pv = means @ R.T + t
    W, H = view.width, view.height
    fx, fy = float(view.K[0, 0]), float(view.K[1, 1])
    tanx, tany = 0.5 * W / fx, 0.5 * H / fy
    zc = pv[:, 2]
    tx = zc * np.clip(pv[:, 0] / zc, -1.3 * tanx, 1.3 * tanx)
    ty = zc * np.clip(pv[:, 1] / zc, -1.3 * tany, 1.3 * tany)
    J = np.zeros((len(means), 2, 3), np.float32)
    J[:, 0, 0], J[:, 0, 2] = fx / zc, -fx * tx / zc**2
    J[:, 1, 1], J[:, 1, 2] = fy / zc, -fy * ty / zc**2
    T = J @ R
    cov2 = T @ cov3 @ T.transpose(0, 2, 1)
    cov2[:, 0, 0] += 0.3
    cov2[:, 1, 1] += 0.3
    det = np.maximum(cov2[:, 0, 0] * cov2[:, 1, 1] - cov2[:, 0, 1] ** 2, 1e-6)
    A, B, C = cov2[:, 1, 1] / det, -cov2[:, 0, 1] / det, cov2[:, 0, 0] / det
    n, f = 0.001, 1000.0
    rw = 1.0 / np.maximum(zc, 1e-6)
    ndc = np.stack([pv[:, 0] / tanx * rw, pv[:, 1] / tany * rw,
                    ((f + n) / (f - n) * zc - f * n / (f - n)) * rw], -1)  # fmt: skip
    u = 0.5 * ((ndc[:, 0] + 1) * W - 1)
    v = 0.5 * ((ndc[:, 1] + 1) * H - 1)
    flat = ndc.astype(np.float32).ravel()
    key = np.concatenate([flat[2:], np.full(2, np.inf, np.float32)])[: len(means)]
    order = np.argsort(key, kind="stable")
    with torch.no_grad():
        dirs = torch.from_numpy(means - centre)
        colors = eval_sh(min(step // 1000, 3), torch.from_numpy(p["sh"]), dirs).numpy()
    opac = 1.0 / (1.0 + np.exp(-p["opacity_logits"]))
    sqx, sqy = 3 * np.sqrt(cov2[:, 0, 0]), 3 * np.sqrt(cov2[:, 1, 1])
    out = np.zeros((H, W, 3), np.float32)
    trans = np.ones((H, W), np.float32)
    done = np.zeros((H, W), bool)
    for g in order:
        if not (np.isfinite(u[g]) and np.isfinite(v[g])):
            continue
        y0 = max(0, int(np.floor(v[g] - sqy[g])) - 2)
        y1 = min(H, int(np.ceil(v[g] + sqy[g])) + 2)
        x0 = max(0, int(np.floor(u[g] - sqx[g])) - 2)
        x1 = min(W, int(np.ceil(u[g] + sqx[g])) + 2)
        if y0 >= y1 or x0 >= x1:
            continue
        xc = u[g] - np.arange(x0, x1)[None, :]
        yc = v[g] - np.arange(y0, y1)[:, None]
        sig = 0.5 * (A[g] * xc * xc + C[g] * yc * yc) + B[g] * xc * yc
        a = np.minimum(0.999, opac[g] * np.exp(-sig))
        box = (slice(y0, y1), slice(x0, x1))
        ok = (sig >= 0) & (a >= 1 / 255) & ~done[box]
        tb = trans[box]
        nt = tb * (1 - a)
        fin = ok & (nt <= 1e-4)
        done[box] |= fin
        ok &= ~fin
        out[box] += np.where(ok, a * tb, 0)[..., None] * colors[g]
        trans[box] = np.where(ok, nt, tb)
    out += trans[..., None] * np.asarray(BACKGROUND, np.float32)
    return np.clip(out, 0.0, 1.0)


def ply_psnr(path: Path, scene, frame: tuple | None = None, step: int = 0) -> dict:
    """Held-out PSNR of an OpenSplat PLY, every pixel of each test view, averaged:
    drawn as any 3DGS viewer draws it (depth order; `psnr_test`) and, given
    OpenSplat's frame, as its own CPU renderer draws it (`psnr_test_own`)."""
    import numpy as np

    from ptovs.field.losses import psnr

    field = ply_field(path)
    tests = scene.test_views()
    vals = [psnr(render_ply(field, v), scene.load_image(v)) for v in tests]
    out = {"psnr_test": round(float(np.mean(vals)), 3),
           "gaussians": int(field[0].means.shape[0])}  # fmt: skip
    if frame is not None:
        from ptovs.field.ply import read_ply

        ply = read_ply(path)
        own = [psnr(opensplat_draw(ply, v, frame, step), scene.load_image(v))
               for v in tests]  # fmt: skip
        out["psnr_test_own"] = round(float(np.mean(own)), 3)
    return out


def curve(out: Path, run: dict, scene, frame: tuple) -> list[dict]:
    """OpenSplat's held-out PSNR at each saved step: [{step, s, psnr_test, ...}]."""
    pts = []
    for k, t in sorted(run["step_times"].items(), key=lambda kv: int(kv[0])):
        ply = out / f"splat_{k}.ply"
        if ply.is_file():
            pts.append({"step": int(k), "s": t,
                        **ply_psnr(ply, scene, frame, int(k))})  # fmt: skip
    return pts


def time_to(points: list[dict], target: float, key: str = "psnr_test") -> float | None:
    """The first time a curve of {s, key} points (by step) reaches `target` dB, linear
    between points; its first point's time when that one already does; None when it
    never does."""
    prev = None
    for pt in points:
        if pt[key] >= target:
            if prev is None or pt[key] == prev[key]:
                return pt["s"]
            f = (target - prev[key]) / (pt[key] - prev[key])
            return prev["s"] + f * (pt["s"] - prev["s"])
        prev = pt
    return None


def reach(ours: list[dict], theirs: list[dict], key: str) -> dict:
    """ptovs's time to OpenSplat's best held-out PSNR (its `key` reading) against
    OpenSplat's own time to it. `ours`: whole ptovs runs at several step counts,
    {step, s: wall time, psnr_test}; `theirs`: OpenSplat's curve. When ptovs's shortest
    run already passes the target, its time is an upper bound and the speedup a lower
    one (`bound`: true)."""
    ours = sorted(ours, key=lambda pt: pt["step"])
    target = max(pt[key] for pt in theirs)
    os_s, our_s = time_to(theirs, target, key), time_to(ours, target)
    return {"target_psnr": target, "opensplat_s": os_s,
            "ptovs_s": None if our_s is None else round(our_s, 1),
            "speedup": None if our_s is None else round(os_s / our_s, 2),
            "bound": bool(ours) and ours[0]["psnr_test"] >= target}  # fmt: skip


def reach_table(rec: dict, n: int) -> dict:
    """Each ptovs variant's time to OpenSplat's best, from a scene record's whole ptovs
    runs at these --iterations `n` (the reach runs and the same-steps one):
    {variant: {reading: reach(...)}}."""
    out: dict = {"for_iterations": n}
    for key in VARIANTS:
        pts = [{"step": r["iterations"], "s": r["wall_s"], "psnr_test": r["psnr_test"]}
               for k, r in rec.items()
               if (k == key or k.startswith(f"{key}_reach_"))
               and isinstance(r, dict) and "wall_s" in r
               and r.get("for_iterations") == n]  # fmt: skip
        if pts and "opensplat" in rec:
            out[key] = {reading: reach(pts, rec["opensplat"]["curve"], reading)
                        for reading in ("psnr_test", "psnr_test_own")}  # fmt: skip
    return out


def check_render(binary: str, proj: Path, out: Path, scene, val, threads: int,
                 frame: tuple, start: Path | None = None,
                 start_step: int = 0) -> dict:  # fmt: skip
    """Our readings of a PLY against OpenSplat's own render, at one withheld view:
    OpenSplat trains 20 steps (from scratch, or on from the PLY `start` saved at step
    `start_step`, a multiple of 10) and renders the view itself (`--val-render`);
    we draw the PLY it saved then in depth order (ptovs's rasterizer) and as its CPU
    renderer does (`opensplat_draw`). Each one's PSNR to its image and to the photo."""
    import cv2

    from ptovs.field.losses import psnr

    last = start_step + 20
    run_opensplat(binary, proj, out, last, threads, f"{val.stem}.png",
                  val_render=True, resume=start)  # fmt: skip
    theirs = cv2.imread(str(out / "val" / f"{last}.png"), cv2.IMREAD_COLOR)
    if theirs is None:
        return {"failed": f"OpenSplat wrote no {out / 'val' / f'{last}.png'}"}
    theirs = theirs[..., ::-1].astype("float32") / 255.0
    ours = render_ply(ply_field(out / "splat.ply"), val)
    from ptovs.field.ply import read_ply

    own = opensplat_draw(read_ply(out / "splat.ply"), val, frame, last)
    if ours.shape != theirs.shape:
        return {
            "failed": f"sizes differ: ours {ours.shape}, OpenSplat's {theirs.shape}"
        }
    photo = scene.load_image(val)
    return {"step": last,
            "psnr_depth_order_vs_theirs": round(psnr(ours, theirs), 2),
            "psnr_own_reading_vs_theirs": round(psnr(own, theirs), 2),
            "psnr_to_photo": {"theirs": round(psnr(theirs, photo), 3),
                              "depth_order": round(psnr(ours, photo), 3),
                              "own_reading": round(psnr(own, photo), 3)}}  # fmt: skip


def run_scene(args: argparse.Namespace, build: dict, spec: str, rec: dict,
              save) -> None:  # fmt: skip
    from ptovs.scene import load_scene

    scene_dir = prepare_scene(args, spec)
    scene = load_scene(scene_dir)
    tests = scene.test_views()
    if not tests:
        raise SystemExit(f"{spec}: {scene_dir} has no held-out views")
    tag = spec.replace(":", "_s")
    proj = args.work / "projects" / tag
    info = export_project(scene, proj, tests[0])
    frame = opensplat_frame([*scene.train_views(), tests[0]])
    v0 = scene.train_views()[0]
    rec["scene"] = {**info, "dir": str(scene_dir), "test": len(tests),
                    "downscale": scene.downscale,
                    "working_size": [v0.width, v0.height]}  # fmt: skip
    n, t = args.iterations, args.threads
    binary = build["binary"]

    def once(key: str, make) -> dict:
        """A part's record: kept from an earlier run at these iterations (a run cut
        off goes on where it stopped), else made and saved."""
        old = rec.get(key)
        done = old and ("wall_s" in old or "psnr_depth_order_vs_theirs" in old)
        if done and old.get("for_iterations") == n:
            print(f"{spec}: {key} kept from {old.get('date')}", file=sys.stderr)
            return old
        new = make()
        new.update(for_iterations=n, date=time.strftime("%Y-%m-%d %H:%M"))
        rec[key] = new
        save()
        return new

    if "check" in args.parts:
        once("check", lambda: check_render(
            binary, proj, args.work / "os" / tag / "check", scene, tests[0], t, frame))  # fmt: skip
    if "same" in args.parts:
        out = args.work / "os" / tag / "same"
        every = max(1, n // 10)

        def opensplat() -> dict:
            run = run_opensplat(binary, proj, out, n, t, info["val_image"], every=every)
            run.update(ply_psnr(Path(run["ply"]), scene, frame, n))
            run["curve"] = curve(out, run, scene, frame)
            return run

        run = once("opensplat", opensplat)
        if "check" in args.parts and n % 10 == 0:  # the check again, trained
            once("check_trained", lambda: check_render(
                binary, proj, args.work / "os" / tag / "check_trained", scene,
                tests[0], t, frame, start=Path(run["ply"]), start_step=n))  # fmt: skip
        once("ptovs", lambda: run_ours(args, scene_dir, n, f"{tag}_wild"))
        once("ptovs_plain", lambda: run_ours(args, scene_dir, n, f"{tag}_plain",
                                             *VARIANTS["ptovs_plain"]))  # fmt: skip

    if "reach" in args.parts and "opensplat" in rec:
        steps = sorted({max(1, round(n * f)) for f in REACH})
        for key, sets in VARIANTS.items():
            for k in (k for k in steps if k < n):
                once(f"{key}_reach_{k}",
                     lambda k=k, sets=sets: run_ours(args, scene_dir, k,
                                                     f"{tag}_reach", *sets))  # fmt: skip
        rec["reach"] = reach_table(rec, n)
        save()


def table(results: dict) -> str:
    rows = ["| scene | tool | iterations | wall s | s/iteration | peak RSS MB | "
            "Gaussians | held-out PSNR dB |", "|---|---|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    names = {"opensplat": "OpenSplat --cpu", "ptovs": "ptovs (in the wild)",
             "ptovs_plain": "ptovs, plain 3DGS (wild=false)"}  # fmt: skip
    for spec, rec in results.get("scenes", {}).items():
        reach_runs = sorted(((k, v) for v in VARIANTS for k in rec
                             if k.startswith(f"{v}_reach_")),
                            key=lambda kv: (kv[1], int(kv[0].rsplit("_", 1)[1])))  # fmt: skip
        fewer = ((k, f"{names[v]}, fewer steps") for k, v in reach_runs)
        for key, label in [*names.items(), *fewer]:
            r = rec.get(key)
            if not r or "wall_s" not in r:
                continue
            psnr = f"{r['psnr_test']:.2f}"
            if r.get("psnr_test_own") is not None:
                psnr += f" (its own renderer's order {r['psnr_test_own']:.2f})"
            if r.get("psnr_test_nerfw") is not None:
                psnr += f" (NeRF-W protocol {r['psnr_test_nerfw']:.2f})"
            rows.append(f"| {spec} | {label} | {r['iterations']} | {r['wall_s']} | "
                        f"{r.get('s_per_iteration')} | {r['peak_rss_mb']} | "
                        f"{r.get('gaussians')} | {psnr} |")  # fmt: skip
    reach_rows = ["", "| scene | ptovs | OpenSplat reading | its best dB | "
                  "OpenSplat s | ptovs s | speedup |",
                  "|---|---|---|---:|---:|---:|---:|"]  # fmt: skip
    for spec, rec in results.get("scenes", {}).items():
        for variant in VARIANTS:
            for reading, label in (("psnr_test", "PLY, depth order"),
                                   ("psnr_test_own", "its own renderer")):  # fmt: skip
                r = rec.get("reach", {}).get(variant, {}).get(reading)
                if not r:
                    continue
                ge = "≥ " if r["bound"] else ""
                sp = f"{ge}{r['speedup']}×" if r["speedup"] else "not in its runs"
                reach_rows.append(f"| {spec} | {names[variant]} | {label} | "
                                  f"{r['target_psnr']:.2f} | {r['opensplat_s']} | "
                                  f"{r['ptovs_s']} | {sp} |")  # fmt: skip
    return "\n".join(rows + (reach_rows if len(reach_rows) > 3 else []))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--opensplat-src", type=Path, required=True, metavar="DIR",
                   help="an OpenSplat source tree (git clone of pierotofy/OpenSplat)")  # fmt: skip
    p.add_argument("--fetchcontent", type=Path, default=None, metavar="DEPS",
                   help="offline sources of its CMake downloads: DEPS/{nlohmann_json,"
                   "nanoflann,cxxopts}")  # fmt: skip
    p.add_argument("--work", type=Path, default=ROOT / "work" / "peers")
    p.add_argument("--real", type=Path, default=ROOT / "data" / "real", metavar="DIR",
                   help="the real photo sets (herzjesu_p8/, fountain_p11/)")  # fmt: skip
    p.add_argument("--scenes", nargs="+",
                   default=["herzjesu_p8", "fountain_p11", "bench:0"],
                   help="real set names and bench:SEED")  # fmt: skip
    p.add_argument("--parts", nargs="+", default=["check", "same", "reach"],
                   choices=["check", "same", "reach"])  # fmt: skip
    p.add_argument("--iterations", type=int, default=2500)
    p.add_argument("--threads", type=int, default=2)
    args = p.parse_args()
    results = Results(args.work / "peers.json")
    try:
        build = build_opensplat(args.opensplat_src, args.work / "build",
                                args.fetchcontent, os.cpu_count() or 1)  # fmt: skip
    except RuntimeError as exc:
        results["build"] = {"failed": str(exc)[-2000:]}
        results.save()
        raise SystemExit(str(exc)) from None
    results["build"] = build
    results["cpu"] = cpu_model()
    results.save()
    print(f"OpenSplat {build.get('version', '')} ({build['source_id']}): "
          f"{build['binary']}")  # fmt: skip
    for spec in args.scenes:
        rec = results.setdefault("scenes", {}).setdefault(spec, {})
        rec["date"] = time.strftime("%Y-%m-%d %H:%M")
        run_scene(args, build, spec, rec, results.save)
    print(table(results))


if __name__ == "__main__":
    main()
