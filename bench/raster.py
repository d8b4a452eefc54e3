"""Rasterizer benchmark: speed against error, per backend and for the fast path.

The scene recipe is docs/rasterizer.md §7 so the figures compare with its anchors:
camera at the origin looking down +z, fx = fy = W, principal point at the centre;
z ~ U[2, 6] with x, y inside the frustum; random quaternions; scales log-uniform in
[0.01, 0.06]; opacity ~ U[0.1, 0.9]; features ~ U[0, 1]. Loss <render, v> +
<alpha, v_a> with random v, backward to means, quats, scales, opacities and colours.

Every (configuration, method) runs in a fresh process (peak memory is that
process's RSS growth over its baseline); times are the median of --repeats runs
after one warm-up, on --threads threads. Errors are against the torch backend in
float64 on the same scene: max |x - ref| / max |ref| over the image and over each
gradient (the worst is reported). float32 against float64 flips a few elements where
alpha crosses 1/255 or T crosses 1e-4, so the 99.9th percentile and the count of
elements above 1e-5 are reported beside the maximum.

    python bench/raster.py                      # the full table (CI-sized: --quick)
    python bench/raster.py --quick              # only 1e4 x 128^2 x D=12
    python bench/raster.py --n 100000 --size 256 --d 12 --methods cpu fast
    python bench/raster.py --methods torch cuda cuda64   # a GPU: the torch backend
                                                         # there, float32 and float64
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

METHODS = ("torch", "cpu", "fast", "cuda", "cuda64")


def make_scene(n: int, size: int, d: int, seed: int = 0, dtype=None, device="cpu"):
    import torch

    from ptovs.raster import Camera, Gaussians

    dtype = dtype or torch.float32
    g = torch.Generator().manual_seed(seed)
    z = 2 + 4 * torch.rand(n, generator=g, dtype=torch.float64)
    uv = size * torch.rand(n, 2, generator=g, dtype=torch.float64)
    xy = (uv - size / 2) / size * z[:, None]
    means = torch.cat([xy, z[:, None]], 1)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    lo, hi = torch.log(torch.tensor(0.01)), torch.log(torch.tensor(0.06))
    scales = torch.exp(
        lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=torch.float64)
    )
    opac = 0.1 + 0.8 * torch.rand(n, generator=g, dtype=torch.float64)
    feats = torch.rand(n, d, generator=g, dtype=torch.float64)
    v = torch.randn(size, size, d, generator=g, dtype=torch.float64)
    va = torch.randn(size, size, 1, generator=g, dtype=torch.float64)
    K = torch.tensor([[size, 0, size / 2], [0, size, size / 2], [0, 0, 1]], dtype=dtype)
    cam = Camera(cam_from_world=torch.eye(4, dtype=dtype), K=K, width=size, height=size)
    cam = cam.to(device)
    leaves = [
        t.to(dtype=dtype, device=device).requires_grad_(True)
        for t in (means, quats, scales, opac, feats)
    ]
    gs = Gaussians(
        means=leaves[0], quats=leaves[1], scales=leaves[2], opacities=leaves[3]
    )
    return (
        gs,
        cam,
        leaves,
        v.to(dtype=dtype, device=device),
        va.to(dtype=dtype, device=device),
    )


def _rss_mb() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def worker(args: argparse.Namespace) -> dict:
    """One (config, method) in this process; returns timings, memory and errors."""
    import numpy as np
    import torch

    from ptovs.raster import blend_weights, render

    torch.set_num_threads(args.threads)
    n, size, d, method = args.n, args.size, args.d, args.method
    ref64 = args.method == "ref64"
    cuda = method.startswith("cuda")  # the torch backend on the GPU
    gs, cam, leaves, v, va = make_scene(
        n,
        size,
        d,
        dtype=torch.float64 if method in ("ref64", "cuda64") else None,
        device="cuda" if cuda else "cpu",
    )
    feats = leaves[4]
    backend = "torch" if method in ("torch", "ref64") or cuda else "cpu"
    base = _rss_mb()

    def sync():
        if cuda:
            torch.cuda.synchronize()

    def fwd():
        with torch.no_grad():
            return render(gs, cam, feats, backend=backend, tile=args.tile, depth=False)

    def fwd_bwd():
        for t in leaves:
            t.grad = None
        out = render(gs, cam, feats, backend=backend, tile=args.tile, depth=False)
        loss = (out.image * v).sum() + (out.alpha * va).sum()
        loss.backward()
        return out

    extra = {}
    if method == "fast":
        t0 = time.perf_counter()
        with torch.no_grad():
            bw = blend_weights(gs, cam, tile=args.tile, backend="cpu")
        extra["build_s"] = time.perf_counter() - t0
        extra["nnz"] = (
            int(bw.W._nnz()) if hasattr(bw.W, "_nnz") else int(bw.W.values().numel())
        )
        f = feats.detach().clone().requires_grad_(True)

        def fwd():  # noqa: F811 - the fast path's own forward
            with torch.no_grad():
                return bw.apply(f)

        def fwd_bwd():  # noqa: F811
            f.grad = None
            img = bw.apply(f)
            (img * v).sum().backward()
            return img

    times = {}
    for name, fn in (("fwd", fwd), ("fwd_bwd", fwd_bwd)):
        fn()  # warm-up (and the compiled backend's first-call build)
        sync()
        runs = []
        for _ in range(1 if ref64 else args.repeats):
            t0 = time.perf_counter()
            fn()
            sync()
            runs.append(time.perf_counter() - t0)
        times[name] = statistics.median(runs)
    # on the GPU: the device memory the allocator peaked at, not host RSS
    peak = torch.cuda.max_memory_allocated() / 2**20 if cuda else _peak_mb() - base

    out = fwd_bwd()
    if method == "fast":
        # alpha does not depend on colours, so g_colors compares with the full loss
        result = {"image": out.detach().numpy(), "g_colors": f.grad.numpy()}
    else:
        result = {
            "image": out.image.detach().cpu().numpy(),
            "alpha": out.alpha.detach().cpu().numpy(),
        }
        for key, t in zip(
            ("means", "quats", "scales", "opacities", "colors"), leaves, strict=True
        ):
            result[f"g_{key}"] = t.grad.cpu().numpy()
    if ref64:
        np.savez(args.ref, **result)
        return {}
    errors, p999, flips = {}, {}, 0
    with np.load(args.ref) as ref:
        for key, val in result.items():
            r = ref[key]
            scale = max(float(np.abs(r).max()), 1e-12)
            e = np.abs(val.astype(np.float64) - r) / scale
            errors[key] = float(e.max())
            p999[key] = float(np.quantile(e, 0.999))
            flips += int((e > 1e-5).sum())
    return dict(
        times,
        peak_mb=peak,
        err=max(errors.values()),
        p999=max(p999.values()),
        over=flips,
        errors=errors,
        **extra,
    )


def run_one(method: str, n: int, size: int, d: int, ref: Path, args) -> dict:
    cmd = [
        sys.executable,
        __file__,
        "--worker",
        "--method",
        method,
        "--n",
        str(n),
        "--size",
        str(size),
        "--d",
        str(d),
        "--ref",
        str(ref),
        "--tile",
        str(args.tile),
        "--threads",
        str(args.threads),
        "--repeats",
        str(args.repeats),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        return {"failed": proc.stderr.strip().splitlines()[-1] if proc.stderr else "?"}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--n", type=int, nargs="+", default=[1000, 10000, 100000])
    ap.add_argument("--size", type=int, nargs="+", default=[128, 256])
    ap.add_argument("--d", type=int, nargs="+", default=[3, 12])
    ap.add_argument("--methods", nargs="+", default=list(METHODS[:3]), choices=METHODS)
    ap.add_argument("--quick", action="store_true", help="only 1e4 x 128^2 x D=12")
    ap.add_argument("--tile", type=int, default=16)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json", type=Path, help="also write the rows as JSON here")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--method", help=argparse.SUPPRESS)
    ap.add_argument("--ref", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        args.n, args.size, args.d = args.n[0], args.size[0], args.d[0]
        print(json.dumps(worker(args)))
        return
    if args.quick:
        args.n, args.size, args.d = [10000], [128], [12]
    rows = []
    print(
        f"# {platform.processor() or platform.machine()}, {os.cpu_count()} cpus, "
        f"{args.threads} threads, tile {args.tile}, median of {args.repeats}",
        flush=True,
    )
    print(
        "| N | image | D | method | fwd (ms) | fwd+bwd (ms) | peak (MB; GPU: device) | max rel. err "
        "| p99.9 rel. err | elements > 1e-5 | note |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.n:
            for size in args.size:
                for d in args.d:
                    ref = Path(tmp) / f"ref_{n}_{size}_{d}.npz"
                    r = run_one("ref64", n, size, d, ref, args)
                    if "failed" in r:
                        print(
                            f"| {n} | {size}² | {d} | ref64 | failed: {r['failed']} |"
                        )
                        continue
                    for method in args.methods:
                        r = run_one(method, n, size, d, ref, args)
                        rows.append(dict(n=n, size=size, d=d, method=method, **r))
                        if "failed" in r:
                            print(
                                f"| {n:.0e} | {size}² | {d} | {method} | – | – | – | – "
                                f"| – | – | failed: {r['failed']} |",
                                flush=True,
                            )
                            continue
                        note = ""
                        if method == "fast":
                            note = (
                                f"build {r['build_s'] * 1e3:.0f} ms, nnz {r['nnz']:,}"
                            )
                        print(
                            f"| {n:.0e} | {size}² | {d} | {method} | "
                            f"{r['fwd'] * 1e3:.1f} | {r['fwd_bwd'] * 1e3:.1f} | "
                            f"{r['peak_mb']:.0f} | {r['err']:.1e} | {r['p999']:.1e} | "
                            f"{r['over']} | {note} |",
                            flush=True,
                        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
