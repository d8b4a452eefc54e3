"""Multi-appearance language Gaussians (MALE-GS, docs/method.md §7): the trainable core.

Every Gaussian holds, per level ℓ and appearance slot a, a 3-d code; the codes are
stored as f [P, L·A·3] (level-major, then slot, then xyz) and every 3-chunk is
L2-normalised as x / (‖x‖ + 1e-9) before rendering (the authors' code; zero codes
stay zero and their gradient stays finite). Geometry is frozen, so a view renders
as a sparse product R_v = W_v · normalize(f) (`ptovs.raster.BlendWeights`);
`renderer = "raster"` rasterises instead (same values, ~10× slower).

Per view (`ViewData`, built once by `prepare_view`) only the pixels some Gaussian
covers are kept: W restricted to them, the targets G (float16) and the mask
weights (float16); the uncovered pixels render 0 whatever the codes, so their loss
is a per-level constant. The loss of one view is

    paper: Σ_{ℓ,a} mean_{HW·3} |m_a ⊙ (R_{ℓ,a} − G_{ℓ,a})|,  m_a = v_a (1−U_A)(1−U_T)
    code:  Σ_ℓ [ mean_{HW·3} |m_orig ⊙ (R − G)|_orig + mean_{HW·9} |v (1−U_T) ⊙ (R − G)|_novel ]

with v_a = "a segment of slot a covers the pixel at level ℓ"; `use_ut` / `use_ua`
off set their factor to 1. Levels share nothing but the Gaussians, so training all
levels in one product is exactly three independent trainings (Adam is elementwise).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from ptovs.artifacts import read_json_dataset
from ptovs.progress import CHECKPOINT_S, Heartbeat
from ptovs.raster import (
    BlendWeights,
    Camera,
    Gaussians,
    csr_matmul,
    kernels_only_parallel,
    render,
)

log = logging.getLogger(__name__)

NORM_EPS = 1e-9  # the authors' x / (‖x‖ + 1e-9)
CODE_DIM = 3


def normalize_chunks(f: Tensor, eps: float = NORM_EPS) -> Tensor:
    """Each consecutive 3-chunk of f [P, K·3] divided by (its norm + eps)."""
    v = f.reshape(f.shape[0], -1, CODE_DIM)
    return (v / (v.norm(dim=-1, keepdim=True) + eps)).reshape(f.shape)


@dataclass
class ViewData:
    """One view, ready to train: its blend weights and targets on covered pixels only.

    Pixels no Gaussian covers render 0 whatever the codes; their loss is a constant
    (`const`, per level) and they are dropped from everything else.
    """

    w: tuple[Tensor, Tensor, Tensor]  # CSR of W [n_act, P] (covered pixels)
    wt: tuple[Tensor, Tensor, Tensor]  # CSR of Wᵀ [P, n_act]
    rows: Tensor  # [n_act] int64 flat pixel ids of the covered pixels
    g: Tensor  # [n_act, L·A·3] float16 target codes
    m: Tensor  # [n_act, L·A] float16 mask weights in [0, 1]
    const: Tensor  # [L] float64 loss of the uncovered pixels
    shape: tuple[int, int, int, int]  # (H·W, L, A, P)

    ARRAYS = ("w0", "w1", "w2", "t0", "t1", "t2", "rows", "g", "m", "const")

    def arrays(self) -> dict[str, Tensor]:
        return dict(
            zip(
                self.ARRAYS,
                (*self.w, *self.wt, self.rows, self.g, self.m, self.const),
                strict=True,
            )
        )

    @classmethod
    def from_arrays(
        cls, a: dict[str, Tensor], shape: tuple[int, int, int, int]
    ) -> ViewData:
        return cls(
            (a["w0"], a["w1"], a["w2"]),
            (a["t0"], a["t1"], a["t2"]),
            a["rows"],
            a["g"],
            a["m"],
            a["const"],
            shape,
        )

    @property
    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in self.arrays().values())


def slot_scale(hw: int, n_levels: int, n_apps: int, loss_variant: str) -> Tensor:
    """[L·A] factor turning the mask into the loss's means (see the module doc)."""
    scale = torch.full((n_levels, n_apps), 1.0 / (hw * CODE_DIM))
    if loss_variant == "code" and n_apps > 1:  # novel block: a mean over HW·3·(A−1)
        scale[:, 1:] = 1.0 / (hw * CODE_DIM * (n_apps - 1))
    elif loss_variant not in ("paper", "code"):
        raise ValueError(
            f"loss_variant must be 'paper' or 'code', not {loss_variant!r}"
        )
    return scale.reshape(-1)


def mask_weights(
    valid: np.ndarray,  # [HW, L, A] bool: a segment of slot a covers the pixel
    u_t: np.ndarray | None,
    u_a: np.ndarray | None,
    loss_variant: str = "paper",
) -> np.ndarray:
    """m [HW, L, A] float32: v_a (1 − U_A)(1 − U_T), or the code's masks (module doc)."""
    hw = valid.shape[0]
    one = np.ones(hw, np.float32)
    wt = one if u_t is None else 1.0 - np.clip(u_t.astype(np.float32).ravel(), 0, 1)
    wa = one if u_a is None else 1.0 - np.clip(u_a.astype(np.float32).ravel(), 0, 1)
    m = valid * (wa * wt)[:, None, None]
    if loss_variant == "code":  # U_A on the original slot only
        m[:, :, 1:] = valid[:, :, 1:] * wt[:, None, None]
    return m.astype(np.float32)


def prepare_view(
    bw: BlendWeights,
    segs: Sequence[np.ndarray],  # per slot [L, H, W] int16 global rows (−1: none)
    codes: Sequence[np.ndarray],  # per slot [n_a, 3] train-ae codes
    u_t: np.ndarray | None,  # [H, W] normalised U_T (None: factor 1)
    u_a: np.ndarray | None,  # [H, W] normalised U_A (None: factor 1)
    loss_variant: str = "paper",
) -> ViewData:
    """Targets G = code_a[seg_a[ℓ]], masks and the compacted weights of one view."""
    n_lv, h, w = segs[0].shape
    n_app, hw, n = len(segs), h * w, bw.n_gaussians
    if (bw.height, bw.width) != (h, w):
        raise ValueError(
            f"segment maps are {w}x{h}, the view renders {bw.width}x{bw.height}"
        )
    offsets = np.cumsum([0] + [len(c) for c in codes])
    table = np.concatenate(
        [np.asarray(c, np.float32).reshape(-1, CODE_DIM) for c in codes]
        + [np.zeros((1, CODE_DIM), np.float32)]
    )
    if not np.isfinite(table).all():
        raise FloatingPointError("train-ae codes are not finite")
    if np.abs(table).max() > np.finfo(np.float16).max:  # targets are kept in float16
        raise FloatingPointError(
            f"train-ae codes reach {np.abs(table).max():.3g}, beyond float16; the "
            "autoencoder's codes are unit vectors: rerun train-ae"
        )
    idx = np.empty((hw, n_lv, n_app), np.int64)
    for a, seg in enumerate(segs):
        s = seg.reshape(n_lv, -1).astype(np.int64)
        idx[:, :, a] = np.where(s >= 0, s + offsets[a], offsets[-1]).T
    m = mask_weights(idx != offsets[-1], u_t, u_a, loss_variant)
    g = table[idx]  # [HW, L, A, 3]

    w_csr, t_csr = bw.csr()
    indptr = w_csr[0].long()
    active = torch.diff(indptr) > 0
    act = active.numpy()
    scale = slot_scale(hw, n_lv, n_app, loss_variant).numpy().reshape(n_lv, n_app)
    idle = np.abs(g[~act]).sum(-1) * m[~act] * scale  # R = 0 there
    const = torch.from_numpy(idle.sum((0, 2)).astype(np.float64))
    pixmap = torch.full((hw,), -1, dtype=torch.int64)
    rows = torch.nonzero(active).squeeze(1)
    pixmap[rows] = torch.arange(len(rows))
    w_new = (
        torch.cat((indptr[:1], indptr[1:][active])).to(torch.int32),
        w_csr[1].to(torch.int32),
        w_csr[2].float(),
    )
    t_new = (
        t_csr[0].to(torch.int32),
        pixmap[t_csr[1].long()].to(torch.int32),
        t_csr[2].float(),
    )
    return ViewData(
        w_new,
        t_new,
        rows,
        torch.from_numpy(
            g[act].reshape(len(rows), n_lv * n_app * CODE_DIM).astype(np.float16)
        ),
        torch.from_numpy(m[act].reshape(len(rows), n_lv * n_app).astype(np.float16)),
        const,
        (hw, n_lv, n_app, n),
    )


def masked_l1(r: Tensor, v: ViewData, scale: Tensor) -> tuple[Tensor, Tensor]:
    """(per-level loss [L], dLoss/dr [n_act, C]) of rendered codes r [n_act, C]."""
    _, n_lv, n_app, _ = v.shape
    k = n_lv * n_app
    d = r - v.g.float()
    m = v.m.float() * scale
    per = (
        (d.abs().reshape(-1, k, CODE_DIM).sum(-1) * m)
        .reshape(-1, n_lv, n_app)
        .sum((0, 2))
    )
    grad = torch.sign(d).reshape(-1, k, CODE_DIM).mul_(m[..., None]).reshape(d.shape)
    return per.double() + v.const, grad


class ViewStore:
    """Every view's `ViewData`: in RAM up to a byte budget, beyond it saved as `.npy`
    in a scratch folder and memory-mapped (copy-on-write: no RAM copy).

    `sample=True` keeps what fits the budget and drops the rest (counted in
    `dropped`): for a loss that is only reported, whose views need not all be kept
    (a landmark's views are 0.1-0.3 GB each: 763 of them would spill over 100 GB)."""

    def __init__(self, budget_bytes: int, scratch: Path | None, sample: bool = False):
        self.budget = budget_bytes
        self.scratch = scratch
        self.sample = sample
        self.items: list[ViewData | tuple[Path, tuple]] = []
        self.ram_bytes = 0
        self.disk_bytes = 0
        self.dropped = 0

    def add(self, v: ViewData) -> None:
        size = v.nbytes
        if self.ram_bytes + size <= self.budget or (
            self.scratch is None and not self.sample
        ):
            self.items.append(v)
            self.ram_bytes += size
            return
        if self.sample:
            self.dropped += 1
            return
        self.scratch.mkdir(parents=True, exist_ok=True)
        prefix = self.scratch / f"v{len(self.items):06d}"
        for k, t in v.arrays().items():
            np.save(f"{prefix}_{k}.npy", t.numpy())
        self.items.append((prefix, v.shape))
        self.disk_bytes += size

    def skip(self) -> None:
        """Count a view its caller did not build because the store is `full`."""
        self.dropped += 1

    @property
    def full(self) -> bool:
        """A sampling store that has dropped a view takes no more (its caller can
        skip building them)."""
        return self.sample and self.dropped > 0

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> ViewData:
        item = self.items[i]
        if isinstance(item, ViewData):
            return item
        prefix, shape = item
        arrays = {
            k: torch.from_numpy(np.load(f"{prefix}_{k}.npy", mmap_mode="c"))
            for k in ViewData.ARRAYS
        }
        return ViewData.from_arrays(arrays, shape)


@dataclass
class MaleConfig:
    """The training knobs `train_male` needs (a subset of the stage config)."""

    loss_variant: str = "paper"
    lr: float = 0.0025
    adam_eps: float = 1e-15
    iterations: int = 30000
    stop: str = "plateau"
    stop_rel: float = 1e-3
    stop_patience: int = 3
    renderer: str = "sparse"
    backend: str = "auto"
    seed: int = 0
    checkpoint_every: int = 1000
    init: str = "data"
    mode: str = "optimise"


def train_step(
    f: Tensor,
    v: ViewData,
    scale: Tensor,
    renderer: str = "sparse",
    gaussians: Gaussians | None = None,
    cam: Camera | None = None,
    backend: str = "auto",
) -> Tensor:
    """Loss [L] of one view at codes f; accumulates dLoss/df into f.grad.

    "sparse": R = W·normalize(f) and the gradient Wᵀ·(dL/dR) as sparse products,
    and the normalisation's backward written out (no autograd at all; checked
    against float64 autograd in the tests). "raster": R comes from `render()` and
    the gradient from autograd.
    """
    hw, n_lv, n_app, n = v.shape
    if renderer == "sparse":
        with torch.no_grad():
            x = f.detach().reshape(n, -1, CODE_DIM)
            norm = x.norm(dim=-1, keepdim=True)
            den = norm + NORM_EPS
            r = csr_matmul(v.w, n, (x / den).reshape(n, -1))
            per, grad = masked_l1(r, v, scale)
            g = csr_matmul(v.wt, len(v.rows), grad).reshape(x.shape)
            # d/dx of x/(|x|+eps) applied to g: (g − u (u·g) |x|/(|x|+eps)) / (|x|+eps),
            # u = x/|x| (0 at x = 0, where the Jacobian is I/eps)
            u = x / norm.clamp_min(1e-30)
            gx = (g - u * ((u * g).sum(-1, keepdim=True) * (norm / den))) / den
            gx = gx.reshape(f.shape)
        f.grad = gx if f.grad is None else f.grad + gx
        return per
    fn = normalize_chunks(f)
    if renderer == "raster":
        if gaussians is None or cam is None:
            raise ValueError("the raster renderer needs the Gaussians and the camera")
        img = render(
            gaussians, cam, fn, background=None, depth=False, backend=backend
        ).image
        r = img.reshape(hw, -1)[v.rows]
        per, grad = masked_l1(r.detach(), v, scale)
        r.backward(grad)
    else:
        raise ValueError(f"renderer must be 'sparse' or 'raster', not {renderer!r}")
    return per


@torch.no_grad()
def data_init(store: ViewStore, n_channels: int) -> Tensor:
    """Each Gaussian's mask- and blend-weighted mean target code, unit length: the
    code-space lift (`mode = "lift-codes"`) and the optimiser's start
    (`init = "data"`).

    Σ_v W_vᵀ (m ⊙ G) / Σ_v W_vᵀ m per 3-chunk, normalised (the positive denominator
    drops out of the normalisation, so only the numerator is formed); m carries the
    (1 − U_A)(1 − U_T) weights and the segment-validity mask. Gaussians no weighted
    pixel reaches stay zero. One sparse product per view.
    """
    hw, n_lv, n_app, n = store[0].shape
    k = n_lv * n_app
    num = torch.zeros(n, n_channels)
    for i in range(len(store)):
        v = store[i]
        m = v.m.float()
        wg = (v.g.float().reshape(-1, k, CODE_DIM) * m[..., None]).reshape(
            -1, n_channels
        )
        num += csr_matmul(v.wt, len(v.rows), wg)
    norm = num.reshape(n, k, CODE_DIM).norm(dim=-1, keepdim=True)
    unit = torch.where(
        norm > 0, num.reshape(n, k, CODE_DIM) / norm.clamp_min(1e-30), 0.0
    )
    return unit.reshape(n, n_channels)


def untrained(stop: str, seconds: float) -> tuple[dict, dict[str, list[float]]]:
    """(metrics, history) of codes set without the optimiser (the lifts), in the
    layout `train_male` returns."""
    metrics = {
        "iterations": 0,
        "epochs": 0.0,
        "stop": stop,
        "train_seconds": round(seconds, 2),
        "ms_per_iteration": 0.0,
    }
    return metrics, {"epoch_loss": [], "epoch_seconds": []}


@kernels_only_parallel()  # the same codes at any --threads
def train_male(
    store: ViewStore,
    n_channels: int,
    config: MaleConfig,
    gaussians: Gaussians | None = None,
    cams: Sequence[Camera] | None = None,
    load: Callable[[], dict | None] = lambda: None,
    save: Callable[[dict], None] = lambda s: None,
    desc: str = "train-male",
) -> tuple[Tensor, dict, dict[str, list[float]]]:
    """Optimise f [P, n_channels] with Adam, one view per step (shuffled stack).

    Stopping: `stop = "fixed"` runs `iterations`; `"plateau"` also ends when the
    epoch-mean loss (one pass over every view) has not dropped below
    (1 − stop_rel) × its best for `stop_patience` epochs in a row.

    Returns:
        (f, metrics, history): raw codes (not normalised), a summary and per-epoch
        mean losses.
    """
    n_views = len(store)
    if n_views == 0:
        raise ValueError("train-male: no training views")
    hw, n_lv, n_app, n = store[0].shape
    if config.mode == "lift-codes":
        t0 = time.perf_counter()
        f = data_init(store, n_channels)
        return f, *untrained(
            "lift-codes: blend-weighted mean target code per Gaussian",
            time.perf_counter() - t0,
        )
    if config.mode != "optimise":
        raise ValueError(
            f"mode must be 'optimise' or 'lift-codes' here, not {config.mode!r} "
            "('lift' lifts the 512-d features in the train-male stage)"
        )
    f0 = data_init(store, n_channels) if config.init == "data" else None
    f = torch.zeros(n, n_channels) if f0 is None else f0
    f.requires_grad_(True)
    opt = torch.optim.Adam([f], lr=config.lr, eps=config.adam_eps)
    hist: dict[str, list[float]] = {"epoch_loss": [], "epoch_seconds": []}
    step, best, bad, stop, epoch_sum, seconds = 0, math.inf, 0, "", 0.0, 0.0
    state = load()
    if state is not None and "f" in state:
        with torch.no_grad():
            f.copy_(state["f"])
        opt.load_state_dict(state["opt"])
        hist = {k: list(v) for k, v in state["hist"].items()}
        step, best, bad, stop = (
            state["step"],
            state["best"],
            state["bad"],
            state["stop"],
        )
        epoch_sum, seconds = state["epoch_sum"], state["seconds"]
        log.info("train-male: resuming at iteration %d", step)
    scales: dict[int, Tensor] = {}

    bar = tqdm(
        total=config.iterations,
        initial=step,
        desc=desc,
        unit="it",
        leave=False,
        disable=None,
    )
    t_start = time.perf_counter() - seconds
    beat = Heartbeat(desc, config.iterations, step)  # log lines when no bar shows
    last_save, shown = time.monotonic(), {}
    while step < config.iterations and not stop:
        epoch, pos = divmod(step, n_views)
        i = int(np.random.default_rng([config.seed, epoch]).permutation(n_views)[pos])
        v = store[i]
        if v.shape[0] not in scales:
            scales[v.shape[0]] = slot_scale(
                v.shape[0], n_lv, n_app, config.loss_variant
            )
        opt.zero_grad(set_to_none=True)
        per = train_step(
            f, v, scales[v.shape[0]], config.renderer, gaussians,
            cams[i] if cams is not None else None, config.backend,
        )  # fmt: skip
        loss = float(per.sum())
        if not math.isfinite(loss) or not torch.isfinite(f.grad).all():
            raise FloatingPointError(f"train-male: loss {loss} at iteration {step}")
        opt.step()
        epoch_sum += loss
        step += 1
        bar.update(1)
        if step % n_views == 0:  # an epoch ends: the stopping rule
            mean = epoch_sum / n_views
            hist["epoch_loss"].append(mean)
            hist["epoch_seconds"].append(time.perf_counter() - t_start)
            epoch_sum = 0.0
            shown = {"loss": f"{mean:.5f}"}
            bar.set_postfix(**shown)
            if mean < best * (1.0 - config.stop_rel):
                best, bad = mean, 0
            else:
                bad += 1
                if config.stop == "plateau" and bad >= config.stop_patience:
                    stop = f"epoch loss within {config.stop_rel:g} of its best for {bad} epochs"
        beat(step, **shown)
        if (
            step % config.checkpoint_every == 0
            or stop
            or step == config.iterations
            or time.monotonic() - last_save > CHECKPOINT_S
        ):
            last_save = time.monotonic()
            save(
                {
                    "step": step, "f": f.detach().clone(), "opt": opt.state_dict(), "hist": hist,
                    "best": best, "bad": bad, "stop": stop, "epoch_sum": epoch_sum,
                    "seconds": time.perf_counter() - t_start,
                }
            )  # fmt: skip
    bar.close()
    seconds = time.perf_counter() - t_start
    metrics = {
        "iterations": step,
        "epochs": round(step / n_views, 3),
        "stop": stop or f"reached {config.iterations} iterations",
        "train_seconds": round(seconds, 2),
        "ms_per_iteration": round(1e3 * seconds / max(step, 1), 3),
    }
    return f.detach(), metrics, hist


@torch.no_grad()
def evaluate_loss(
    f: Tensor, store: ViewStore, loss_variant: str
) -> tuple[float, list[float]]:
    """Mean per-view loss of codes f over every view: (total, per level)."""
    fn = normalize_chunks(f)
    total = None
    for i in range(len(store)):
        v = store[i]
        hw, n_lv, n_app, n = v.shape
        per, _ = masked_l1(
            csr_matmul(v.w, n, fn), v, slot_scale(hw, n_lv, n_app, loss_variant)
        )
        total = per if total is None else total + per
    if total is None:
        return 0.0, []
    total = total / len(store)
    return float(total.sum()), [float(x) for x in total]


def load_codes(art: Any) -> tuple[torch.Tensor, dict]:
    """Codes of every Gaussian [P, L, N, 3] float32 (zeros where unseen), and meta,
    from a train-male artifact (anything with `.root()`)."""
    root = art.root()
    meta = read_json_dataset(root["meta_json"])
    n = int(meta["gaussians"])
    seen = np.unpackbits(root["seen_bits"], count=n).astype(bool)
    codes = np.zeros((n, len(meta["levels"]), len(meta["apps"]), CODE_DIM), np.float32)
    codes[seen] = root["codes"].astype(np.float32).reshape(-1, *codes.shape[1:])
    return torch.from_numpy(codes), meta


__all__ = [
    "CODE_DIM",
    "MaleConfig",
    "ViewData",
    "ViewStore",
    "evaluate_loss",
    "load_codes",
    "mask_weights",
    "masked_l1",
    "normalize_chunks",
    "prepare_view",
    "slot_scale",
    "train_male",
    "train_step",
    "untrained",
]
