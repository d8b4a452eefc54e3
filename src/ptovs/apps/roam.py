"""A roaming video through the scene with a query's region highlighted.

    ptovs roam --data data/bench_s0 "Rose Window" --out tour.mp4 [--frames 90]

The path: the train cameras ordered by azimuth around the scene (about the mean
"up" of the cameras), `--keyframes` of them evenly spaced in that order, camera
centres on a Catmull-Rom spline through the keyframes and rotations slerped
between them (pycolmap's pose interpolation), intrinsics from the median field
of view at the chosen frame size. Each frame renders the field under one
appearance (an image's embedding or the neutral mean) and highlights the text:
"select" (default) renders the 3-D selection of `ptovs select` as a mask, so the
region is the same object in every frame; "query" answers the text per frame
like `ptovs query` (its relative threshold always marks something). The mask is
tinted and its Canny edges drawn at α = 0.5 (docs/method.md §10), the text in a
bar under the frame. Written with OpenCV's VideoWriter (mp4v), atomically.
"""

from __future__ import annotations

import json
import os
import time
from contextlib import ExitStack
from pathlib import Path

import click
import cv2
import numpy as np
import torch

from ptovs.apps import close_inputs, trained_chain
from ptovs.errors import InputError
from ptovs.options import chain_options
from ptovs.outputs import (
    OutputError,
    check_outputs,
    output_file,
    require_suffix,
    write_text_output,
)
from ptovs.raster import Camera
from ptovs.settings import RunContext

EDGE_BGR = (0, 230, 255)
FILL_BGR = (40, 80, 255)


def _centre(view) -> np.ndarray:
    T = np.asarray(view.cam_from_world, float)  # noqa: N806
    return -T[:3, :3].T @ T[:3, 3]


def pick_keyframes(views: list, k: int, target: np.ndarray) -> list:
    """`k` views evenly spaced in azimuth order around `target`."""
    if len(views) < 2:
        raise InputError("roam: the scene needs at least two train views")
    up = -np.mean([np.asarray(v.cam_from_world)[1, :3] for v in views], 0)
    up /= np.linalg.norm(up) + 1e-12
    e1 = np.cross(up, [1.0, 0.0, 0.0])
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(up, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    rel = np.stack([_centre(v) - target for v in views])
    az = np.arctan2(rel @ e2, rel @ e1)
    order = [views[i] for i in np.argsort(az, kind="stable")]
    k = max(2, min(k, len(order)))
    return [order[i] for i in np.round(np.linspace(0, len(order) - 1, k)).astype(int)]


def _catmull_rom(p: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Points at parameters s ∈ [0, len(p) − 1] on the uniform Catmull-Rom spline
    through p (ends extended by reflection)."""
    q = np.concatenate([2 * p[:1] - p[1:2], p, 2 * p[-1:] - p[-2:-1]])
    i = np.minimum(np.floor(s).astype(int), len(p) - 2)
    t = (s - i)[:, None]
    p0, p1, p2, p3 = q[i], q[i + 1], q[i + 2], q[i + 3]
    return 0.5 * (
        2 * p1
        + (p2 - p0) * t
        + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t**2
        + (3 * p1 - p0 - 3 * p2 + p3) * t**3
    )


def camera_path(keys: list, frames: int, width: int, height: int) -> list[Camera]:
    """`frames` cameras along the keyframes (see the module doc)."""
    import pycolmap

    if frames < 1:
        raise InputError("roam: --frames must be at least 1")
    s = np.linspace(0.0, len(keys) - 1, frames)
    centres = _catmull_rom(np.stack([_centre(v) for v in keys]), s)
    poses = [
        pycolmap.Rigid3d(
            pycolmap.Rotation3d(np.asarray(v.cam_from_world)[:3, :3]),
            np.asarray(v.cam_from_world)[:3, 3],
        )
        for v in keys
    ]
    fov_x = np.median([v.K[0, 0] / v.width for v in keys])
    fov_y = np.median([v.K[1, 1] / v.height for v in keys])
    f = 0.5 * (fov_x * width + fov_y * height)
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], float)  # noqa: N806
    cams = []
    for si, c in zip(s, centres, strict=True):
        i = min(int(np.floor(si)), len(keys) - 2)
        pose = pycolmap.interpolate_camera_poses(poses[i], poses[i + 1], float(si - i))
        R = np.asarray(pose.rotation.matrix())  # noqa: N806
        T = np.eye(4)  # noqa: N806
        T[:3, :3], T[:3, 3] = R, -R @ c
        cams.append(
            Camera(
                cam_from_world=torch.tensor(T, dtype=torch.float32),
                K=torch.tensor(K, dtype=torch.float32),
                width=int(width),
                height=int(height),
            )
        )
    return cams


def highlight(rgb: np.ndarray, mask: np.ndarray, text: str, bar: int) -> np.ndarray:
    """BGR uint8 frame: the region tinted, its Canny edges blended at α = 0.5, and
    the text in a bar under the frame."""
    img = cv2.cvtColor(
        (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR
    )
    m = mask.astype(bool)
    if m.any():
        f = img.astype(np.float32)
        f[m] = 0.7 * f[m] + 0.3 * np.asarray(FILL_BGR, np.float32)
        edges = cv2.Canny(m.astype(np.uint8) * 255, 100, 200) > 0
        edges = cv2.dilate(edges.astype(np.uint8), np.ones((2, 2), np.uint8)) > 0
        f[edges] = 0.5 * f[edges] + 0.5 * np.asarray(EDGE_BGR, np.float32)
        img = f.astype(np.uint8)
    strip = np.full((bar, img.shape[1], 3), 24, np.uint8)
    fs = max(0.35, bar / 40)
    cv2.putText(strip, text, (6, bar - 7), cv2.FONT_HERSHEY_SIMPLEX, fs,
                (255, 255, 255), 1, cv2.LINE_AA)  # fmt: skip
    return np.vstack((img, strip))


@torch.no_grad()
def roam_frames(
    chain,
    text: str,
    cams: list[Camera],
    image: str | None = None,
    mode: str = "select",
    progress: bool = True,
):
    """Yield (rgb [H, W, 3] float, mask [H, W] bool) per camera."""
    from tqdm import tqdm

    from ptovs.field.export import appearance_embedding, baked_sh
    from ptovs.field.query import Querier
    from ptovs.field.render import gaussian_colors, ray_dirs
    from ptovs.raster import render

    inputs = chain.inputs("query")
    try:
        querier = Querier(inputs, chain.config("query"), [text])
        field = querier.field
        emb = None
        if field.wild and field.embeddings:
            emb = appearance_embedding(field, image)
        chosen = None
        if mode == "select":
            sel = querier.select(text)
            if not sel.mask.any():
                raise InputError(
                    f"roam: {text!r} selects no Gaussian; try --highlight query"
                )
            chosen = torch.from_numpy(sel.mask.astype(np.float32))[:, None]
        elif mode != "query":
            raise ValueError(f"highlight must be select or query, got {mode!r}")
        # ΔSH = f_γ(SH, μ, l) does not depend on the view: bake it once
        baked = baked_sh(field, image)
        g = field.gaussians
        for cam in tqdm(cams, desc="roam", unit="frame", disable=not progress):
            cols = gaussian_colors(g.means, baked, field.sh_degree, cam)
            if chosen is not None:  # the selection as a 4th channel, same pass
                cols = torch.cat([cols, chosen], 1)
            out = render(g, cam, cols, depth=False)
            alpha = out.alpha[..., 0]
            rgb = out.image[..., :3]
            if field.wild and field.nets.sky is not None and emb is not None:
                sky = field.nets.map_colors(
                    field.nets.background(ray_dirs(cam), emb), emb
                )
                rgb = rgb + (1.0 - alpha)[..., None] * sky
            elif field.background is not None:
                rgb = rgb + (1.0 - alpha)[..., None] * field.background
            if chosen is not None:
                share = out.image[..., 3] / alpha.clamp_min(1e-6)
                mask = ((share > 0.5) & (alpha > 0.5)).numpy()
            else:
                mask = querier.answer_view(cam)[0].mask
            yield rgb.clamp(0, 1).numpy(), mask
    finally:
        close_inputs(inputs)


MAX_SIDE = 8192  # pixels a side of a frame (--size)
MAX_FRAMES = 100_000  # --frames: over an hour at 25 frames/s
# bytes of memory per frame pixel while rendering and highlighting, generous:
# the selection renders 4 channels; a 2-D query per frame decodes every level
# and appearance at every pixel
BYTES_PER_PIXEL = {"select": 256, "query": 4096}
VIDEO_BYTES_PER_PIXEL = 0.5  # mp4v at OpenCV's default quality, generous
VIDEO_SUFFIXES = (".mp4", ".avi")  # what the mp4v writer opens everywhere


def check_frame_size(width: int, height: int, frames: int, mode: str) -> None:
    """Refuse sizes that cannot be rendered here, before any work: each side at
    most MAX_SIDE, frames at most MAX_FRAMES, the frame's working memory within
    half of the memory available now."""
    if max(width, height) > MAX_SIDE:
        raise click.BadParameter(f"{width}x{height}: each side at most {MAX_SIDE} "
                                 "pixels", param_hint="--size")  # fmt: skip
    if frames > MAX_FRAMES:
        raise click.BadParameter(
            f"{frames}: at most {MAX_FRAMES}", param_hint="--frames"
        )
    need = width * height * BYTES_PER_PIXEL[mode]
    try:
        avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):  # pragma: no cover (not POSIX)
        return
    if need > avail // 2:
        raise click.BadParameter(
            f"{width}x{height} needs about {need / 2**30:.1f} GB to render "
            f"({BYTES_PER_PIXEL[mode]} bytes a pixel with --highlight {mode}); "
            f"{avail / 2**30:.1f} GB is available, so at most half of that is used. "
            "Choose a smaller size",
            param_hint="--size",
        )


def write_video(path: Path, frames, fps: float) -> int:
    """Write BGR frames to `path` (mp4v) through a temporary file, read it back
    (frame count and size: OpenCV does not report failed writes, so a full disk
    would leave a truncated video), then rename it into place; returns the count."""
    written = {"n": 0, "size": (0, 0)}

    def verify(tmp: Path) -> None:
        cap = cv2.VideoCapture(str(tmp))
        got, size = 0, None
        try:
            while True:
                ok, frame = cap.read()
                if not ok:
                    break
                got, size = got + 1, tuple(frame.shape[1::-1])
        finally:
            cap.release()
        if got != written["n"] or size != written["size"]:
            raise OutputError(
                f"{path}: the video written reads back as {got} of {written['n']} "
                "frames; is the disk full? Free space or write elsewhere"
            )

    writer = None
    with ExitStack() as stack:
        try:
            for frame in frames:
                if writer is None:
                    h, w = frame.shape[:2]
                    written["size"] = (w, h)
                    tmp = stack.enter_context(output_file(path, verify))
                    fourcc = cv2.VideoWriter_fourcc(*"mp4v")
                    writer = cv2.VideoWriter(str(tmp), fourcc, fps, (w, h))
                    if not writer.isOpened():
                        raise OutputError(
                            f"roam: OpenCV cannot open a {path.suffix or 'suffix-less'} "
                            f"video at {path}; check the folder is writable, or try "
                            "an .mp4 or .avi name"
                        )
                writer.write(frame)
                written["n"] += 1
        finally:
            if writer is not None:
                writer.release()  # before output_file verifies and renames
        if writer is None:
            raise InputError("roam: no frames rendered")
    return written["n"]


@click.command(name="roam")
@click.argument("text")
@chain_options(variant="one", force=None)
@click.option("--out", type=click.Path(path_type=Path), required=True,
              help="Video file (.mp4 or .avi).")  # fmt: skip
@click.option("--frames", type=click.IntRange(1), default=90, show_default=True)
@click.option("--fps", type=click.FloatRange(1.0), default=15.0, show_default=True)
@click.option("--size", default="320x240", show_default=True, metavar="WxH",
              help="Frame size in pixels (the text bar is added below).")  # fmt: skip
@click.option("--keyframes", type=click.IntRange(2), default=8, show_default=True,
              help="Train cameras the path passes through.")  # fmt: skip
@click.option("--image", default=None,
              help="Render under this image's appearance (default: neutral).")  # fmt: skip
@click.option("--highlight", "mode", type=click.Choice(["select", "query"]),
              default="select", show_default=True,
              help="select: the 3-D selection, rendered; query: a 2-D query per frame.")  # fmt: skip
@click.pass_obj
def command(
    obj: RunContext,
    text: str,
    scene_name: str | None,
    data: Path | None,
    out: Path,
    frames: int,
    fps: float,
    size: str,
    keyframes: int,
    image: str | None,
    mode: str,
    variant: str,
    sets: tuple[str, ...],
) -> None:
    """Render a video along a smooth path through the train cameras, TEXT highlighted.

    Runs any missing stage of the chain first; writes the video and <out>.json
    (frames, size, frames per second of rendering).
    """
    try:
        width, height = (int(x) for x in size.lower().split("x"))
        if width < 8 or height < 8:
            raise ValueError
    except ValueError:
        raise click.BadParameter(f"{size!r}: write WIDTHxHEIGHT, e.g. 320x240",
                                 param_hint="--size") from None  # fmt: skip
    check_frame_size(width, height, frames, mode)
    record_path = out.with_suffix(".json")
    check_outputs({"--out": out, f"the record beside --out ({record_path.name})": record_path},
                  need_bytes=int(width * height * frames * VIDEO_BYTES_PER_PIXEL),
                  suffix=".mp4")  # fmt: skip
    require_suffix("--out", out, VIDEO_SUFFIXES)  # a .gif was once blamed on the disk
    chain, ref = trained_chain(obj, scene_name, data, variant, sets)
    scene = ref.load()
    target = np.median(scene.points_xyz, 0) if len(scene.points_xyz) else np.zeros(3)
    keys = pick_keyframes(scene.train_views(), keyframes, target)
    cams = camera_path(keys, frames, width, height)
    bar = max(18, height // 10)
    label = f"{text}  ({ref.name})"
    stamps: list[float] = [time.perf_counter()]  # start, then after each frame

    def frames():
        for rgb, m in roam_frames(chain, text, cams, image, mode):
            yield highlight(rgb, m, label, bar)
            stamps.append(time.perf_counter())

    n = write_video(out, frames(), fps)
    seconds = stamps[-1] - stamps[0]
    # frames per second once set up (the first frame carries loading the field,
    # the text embeddings, the decoder table and the selection)
    steady = (n - 1) / (stamps[-1] - stamps[1]) if n > 1 else n / seconds
    record = {
        "scene": ref.name, "text": text, "frames": n, "width": width,
        "height": height + bar, "fps": fps, "highlight": mode,
        "keyframes": [v.name for v in keys], "seconds": round(seconds, 2),
        "setup_s": round(stamps[1] - stamps[0], 2), "render_fps": round(steady, 2),
        "video": str(out),
    }  # fmt: skip
    write_text_output(record_path, json.dumps(record, indent=1))
    click.echo(f"roam {text!r}: {n} frames {width}x{height + bar}, {steady:.1f} frames/s "
               f"after {record['setup_s']:.1f} s of setup -> {out}")  # fmt: skip
