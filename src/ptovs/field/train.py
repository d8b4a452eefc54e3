"""Training of the in-the-wild Gaussian field (docs/method.md §2), checkpointed.

One random train view per iteration (a seeded permutation per epoch, so the order
does not depend on where a run was resumed):

    M = f_β(I)            (skipped when wild = false)
    l = f_α(I ⊕ M)
    c = SH + f_γ(SH, μ, l) → render → Ĩ
    L = (1−λ)·L1(w⊙Ĩ, w⊙I) + λ·(1 − SSIM(w⊙Ĩ, w⊙I)) + β·mean(M),  w = 1 − M

with w = 1 and no β term during the mask warm-up. Densify, prune and opacity reset
follow 3DGS on an iteration schedule given in the config.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch.nn import functional as F  # noqa: N812
from tqdm import tqdm

from ptovs.field.losses import psnr, ssim
from ptovs.field.model import APP_EMBED, GaussianModel, LearningRates
from ptovs.field.render import composite_background, gaussian_colors, in_frustum
from ptovs.nets import WildNets
from ptovs.progress import CHECKPOINT_S, Heartbeat
from ptovs.raster import Camera, kernels_only_parallel, render

log = logging.getLogger(__name__)

LOG_EVERY = 25


@dataclass
class TrainState:
    """Everything a run needs to continue, and what it produced."""

    model: GaussianModel
    nets: WildNets | None
    nets_opt: torch.optim.Optimizer | None
    background: torch.Tensor  # [3] logits of the constant background (plain mode)
    bg_opt: torch.optim.Optimizer
    step: int = 0
    grad_accum: torch.Tensor = field(default_factory=lambda: torch.zeros(0))
    grad_denom: torch.Tensor = field(default_factory=lambda: torch.zeros(0))
    history: dict[str, list[float]] = field(
        default_factory=lambda: {"step": [], "loss": [], "psnr": [], "n": [], "sec": []}
    )
    seconds: float = 0.0
    # the adaptive budget: L1 summed since the last densification round, one
    # [step, Gaussians, mean L1] record per round, and [step, Gaussians] once
    # growth has stopped (for good)
    window: list[float] = field(default_factory=lambda: [0.0, 0.0])
    # the Gaussian count densification may grow to (gaussian_budget; 0: the
    # config's max_gaussians; not saved: recomputed from the config and photos)
    budget: int = 0
    rounds: list[list[float]] = field(default_factory=list)
    stopped: list[int] = field(default_factory=list)
    # the plateau stop (`stop = "plateau"`): the loss summed over the current
    # window [sum, steps], [best window mean, windows without progress], and the
    # step training ended at (0: not ended early)
    plateau_window: list[float] = field(default_factory=lambda: [0.0, 0.0])
    plateau: list[float] = field(default_factory=lambda: [float("inf"), 0.0])
    ended: int = 0

    @property
    def growing(self) -> bool:
        return not self.stopped

    def to_dict(self) -> dict[str, Any]:
        """Tensors and plain containers only (loadable with weights_only=True)."""
        return {
            "step": self.step,
            "params": {k: v.detach().clone() for k, v in self.model.params.items()},
            "opt": self.model.opt.state_dict(),
            "nets": None if self.nets is None else self.nets.state_dict(),
            "nets_opt": None if self.nets_opt is None else self.nets_opt.state_dict(),
            "background": self.background.detach().clone(),
            "bg_opt": self.bg_opt.state_dict(),
            "grad_accum": self.grad_accum.clone(),
            "grad_denom": self.grad_denom.clone(),
            "history": {k: list(v) for k, v in self.history.items()},
            "seconds": self.seconds,
            "window": list(self.window),
            "rounds": [list(r) for r in self.rounds],
            "stopped": list(self.stopped),
            "plateau_window": list(self.plateau_window),
            "plateau": list(self.plateau),
            "ended": self.ended,
        }


def scene_extent(cams: list[Camera]) -> tuple[np.ndarray, float]:
    """Centre and radius (x 1.1) of the camera centres, as 3DGS normalises scenes."""
    centers = np.stack(
        [(-c.cam_from_world[:3, :3].T @ c.cam_from_world[:3, 3]).numpy() for c in cams]
    )
    center = centers.mean(0)
    radius = float(np.linalg.norm(centers - center, axis=1).max()) * 1.1
    return center, max(radius, 1e-3)


def _new_state(
    cfg: Any, points: tuple[np.ndarray, np.ndarray], extent: float
) -> TrainState:
    lr = LearningRates()
    nets, nets_opt = None, None
    if cfg.wild:
        nets = WildNets(
            cfg.preset,
            (cfg.sh_degree + 1) ** 2,
            mask_concat=cfg.mask_concat,
            delta_scale=cfg.delta_sh_scale,
            appearance=cfg.appearance,
            color_map=cfg.color_map,
            stats=cfg.image_stats,
            learned=cfg.wild != "colour",
            sky_stride=cfg.sky_stride,
        )
    model = GaussianModel.from_points(
        points[0],
        points[1],
        cfg.sh_degree,
        lr,
        extent,
        embed_dim=nets.gauss_dim if nets is not None else 0,
    )
    if nets is not None:
        groups = [
            (nets.f_alpha, cfg.lr_alpha),
            (nets.f_beta, cfg.lr_beta),
            (nets.f_gamma, cfg.lr_gamma),
            (nets.sky, cfg.lr_alpha),
        ]  # the colour rung has the sky and the map alone
        nets_opt = torch.optim.Adam(
            [{"params": m.parameters(), "lr": lr} for m, lr in groups if m is not None]
            + (
                [{"params": nets.map_parameters(), "lr": cfg.lr_gamma}]
                if nets.f_map is not None
                else []
            ),
            fused=True,  # the nets' ~60 small tensors in one kernel, not a loop
        )
    background = torch.zeros(3, requires_grad=True)
    bg_opt = torch.optim.Adam([background], lr=1e-2)
    n = len(model)
    return TrainState(
        model,
        nets,
        nets_opt,
        background,
        bg_opt,
        grad_accum=torch.zeros(n),
        grad_denom=torch.zeros(n),
    )


def _restore(state: TrainState, saved: dict[str, Any]) -> None:
    m = state.model
    m.params = {k: v.clone().requires_grad_(True) for k, v in saved["params"].items()}
    for g in m.opt.param_groups:
        g["params"] = [m.params[g["name"]]]
    m.opt.state.clear()
    m.opt.load_state_dict(saved["opt"])
    if state.nets is not None:
        state.nets.load_state_dict(saved["nets"])
        state.nets_opt.load_state_dict(saved["nets_opt"])
    with torch.no_grad():
        state.background.copy_(saved["background"])
    state.bg_opt.load_state_dict(saved["bg_opt"])
    state.step = int(saved["step"])
    state.grad_accum = saved["grad_accum"].clone()
    state.grad_denom = saved["grad_denom"].clone()
    state.history = {k: list(v) for k, v in saved["history"].items()}
    state.seconds = float(saved["seconds"])
    state.window = list(saved.get("window", [0.0, 0.0]))
    state.rounds = [list(r) for r in saved.get("rounds", [])]
    state.stopped = [int(x) for x in saved.get("stopped", [])]
    state.plateau_window = list(saved.get("plateau_window", [0.0, 0.0]))
    state.plateau = list(saved.get("plateau", [float("inf"), 0.0]))
    state.ended = int(saved.get("ended", 0))


def gaussian_budget(cfg: Any, images: list[np.ndarray]) -> int:
    """How many Gaussians densification may grow to: `gaussians_per_mpx` per
    million train pixels, never above `max_gaussians` (the hard ceiling); 0 per
    Mpx means the ceiling alone. Deterministic: photo sizes only."""
    per_mpx = float(getattr(cfg, "gaussians_per_mpx", 0.0) or 0.0)
    if per_mpx <= 0:
        return int(cfg.max_gaussians)
    shapes = getattr(images, "shapes", None) or [im.shape for im in images]
    mpx = sum(int(h) * int(w) for h, w, *_ in shapes) / 1e6
    budget = int(min(cfg.max_gaussians, max(1, round(per_mpx * mpx))))
    if budget < cfg.max_gaussians:
        log.info(
            "Gaussian budget %d (%g per Mpx x %.2f Mpx of train photos; ceiling %d)",
            budget,
            per_mpx,
            mpx,
            cfg.max_gaussians,
        )
    return budget


def view_order(step: int, n: int, seed: int) -> int:
    """The view of a step: a seeded permutation per epoch (resume-independent)."""
    epoch, pos = divmod(step, n)
    gen = torch.Generator().manual_seed(seed * 1_000_003 + epoch)
    return int(torch.randperm(n, generator=gen)[pos])


# the same field at any --threads: torch's share of a step (networks, losses, Adam)
# on one thread, the compiled rasterizer on all (ptovs.raster.kernels_only_parallel)
@kernels_only_parallel()
def train(
    cfg: Any,
    images: Sequence[np.ndarray],  # train images [H, W, 3] float32 on access
    cams: list[Camera],
    points: tuple[np.ndarray, np.ndarray],  # xyz [P, 3], rgb [P, 3] uint8
    *,
    load: Callable[[], dict | None] = lambda: None,
    save: Callable[[dict], None] = lambda state: None,
    desc: str = "reconstruct",
) -> TrainState:
    """Train the field; resume from `load()`, call `save(state)` every checkpoint.

    Args:
        cfg: the reconstruct stage config (iterations, schedule, losses, nets).
        images: the train images at working size.
        cams: their cameras.
        points: the sparse cloud that initialises the Gaussians.
        load: returns a saved state dict, or None to start fresh.
        save: stores a state dict (tensors and plain containers).
        desc: progress bar label.

    Returns:
        The final TrainState.
    """
    torch.manual_seed(cfg.seed)
    _, extent = scene_extent(cams)
    if len(points[0]) == 0:
        raise ValueError("the scene has no 3D points to initialise the Gaussians")
    state = _new_state(cfg, points, extent)
    saved = load()
    if saved is not None:
        _restore(state, saved)
        log.info("resumed at iteration %d of %d", state.step, cfg.iterations)
    state.budget = gaussian_budget(cfg, images)
    model, nets = state.model, state.nets
    prepared = [nets.prepare(im) for im in images] if nets is not None else []
    n_views = len(images)
    bar = tqdm(
        total=cfg.iterations,
        initial=state.step,
        desc=desc,
        unit="it",
        disable=None,
        leave=False,
    )
    t_start = time.perf_counter() - state.seconds
    recent: list[tuple[float, float]] = []
    beat = Heartbeat(desc, cfg.iterations, state.step)  # log lines when no bar shows
    last_save = time.monotonic()
    figures: dict[str, str] = {}
    while state.step < cfg.iterations and not state.ended:
        step = state.step
        i = view_order(step, n_views, cfg.seed)
        # one photo as float32 at a time (`images` may be a 16-bit PhotoStack)
        cam, gt = cams[i], torch.from_numpy(np.ascontiguousarray(images[i]))
        model.set_means_lr(step, cfg.iterations)
        degree = min(cfg.sh_degree, step // cfg.sh_increase_every)
        masked = nets is not None and step >= cfg.mask_warmup

        emb, mask_lo = None, None
        if nets is not None:
            a_in, b_in = prepared[i]
            mask_lo = nets.transient(b_in[None])  # [1, 1, s, s]; None: no f_β
            emb = nets.embed(a_in[None], None if mask_lo is None else mask_lo.detach())[
                0
            ]
        g = model.gaussians()
        cols = gaussian_colors(
            g.means,
            model.sh,
            degree,
            cam,
            nets,
            emb,
            visible_only=cfg.visible_only,
            gauss=model.params.get(APP_EMBED),
        )
        bg = torch.sigmoid(state.background) if nets is None else None
        out = render(g, cam, cols, background=bg, backend=cfg.backend, depth=False)
        out.means2d.retain_grad()
        pred = out.image
        if nets is not None:
            pred = nets.map_colors(
                composite_background(pred, out.alpha, cam, nets, emb), emb
            )
        loss = _photo_loss(cfg, pred, gt, mask_lo if masked else None)
        if not torch.isfinite(loss):
            raise FloatingPointError(f"non-finite loss at iteration {step} (view {i})")
        loss.backward()

        _accumulate_grads(state, out.means2d.grad, out.radii, cam)
        if cfg.growth_elasticity > 0:  # the adaptive budget's loss record
            state.window[0] += float((pred.detach() - gt).abs().mean())
            state.window[1] += 1.0
        for opt in (model.opt, state.nets_opt if nets is not None else state.bg_opt):
            opt.step()
            opt.zero_grad(set_to_none=True)

        state.step = step = step + 1
        _densify_schedule(cfg, state, step)
        if getattr(cfg, "stop", "fixed") == "plateau":
            _plateau_check(cfg, state, step, float(loss.detach()), n_views)
        recent.append((float(loss.detach()), psnr(pred.detach().clamp(0, 1), gt)))
        if step % LOG_EVERY == 0 or step == cfg.iterations or state.ended:
            lo, ps = np.mean([r[0] for r in recent]), np.mean([r[1] for r in recent])
            recent.clear()
            state.seconds = time.perf_counter() - t_start
            for k, v in zip(
                ("step", "loss", "psnr", "n", "sec"),
                (step, lo, ps, len(model), state.seconds),
                strict=True,
            ):
                state.history[k].append(float(v))
            figures = dict(loss=f"{lo:.4f}", psnr=f"{ps:.2f}", gaussians=len(model))
            bar.set_postfix(**figures)
        bar.update(1)
        beat(step, **figures)
        # checkpoint every `checkpoint_every` steps, and after CHECKPOINT_S seconds
        # without one (a slow or busy machine would otherwise lose much)
        if (
            step < cfg.iterations
            and not state.ended
            and (
                step % cfg.checkpoint_every == 0
                or time.monotonic() - last_save > CHECKPOINT_S
            )
        ):
            state.seconds = time.perf_counter() - t_start
            save(state.to_dict())
            last_save = time.monotonic()
    bar.close()
    state.seconds = time.perf_counter() - t_start
    return state


def _photo_loss(
    cfg: Any, pred: torch.Tensor, gt: torch.Tensor, mask_lo: torch.Tensor | None
) -> torch.Tensor:
    """(1 - λ) L1 + λ (1 - SSIM), both weighted by 1 - M once the transient mask
    `mask_lo` [1, 1, s, s] is on (None before its warm-up), plus its regulariser."""
    if mask_lo is not None:
        h, w_ = pred.shape[:2]  # the camera's size
        m = F.interpolate(mask_lo, size=(h, w_), mode="bilinear")
        w = (1.0 - m[0, 0])[..., None]
        l1 = ((pred - gt) * w).abs().mean()
        return (
            (1 - cfg.ssim_lambda) * l1
            + cfg.ssim_lambda * (1 - ssim(pred * w, gt * w))
            + cfg.mask_reg * mask_lo.mean()
        )
    l1 = (pred - gt).abs().mean()
    return (1 - cfg.ssim_lambda) * l1 + cfg.ssim_lambda * (1 - ssim(pred, gt))


@torch.no_grad()
def _accumulate_grads(
    state: TrainState, g2: torch.Tensor | None, radii: torch.Tensor, cam: Camera
) -> None:
    """Densification statistics: the screen-space gradient in 3DGS's NDC units."""
    seen = (radii > 0).any(1)
    if g2 is not None:
        gn = torch.sqrt(
            (g2[:, 0] * cam.width * 0.5) ** 2 + (g2[:, 1] * cam.height * 0.5) ** 2
        )
        # masked adds, not boolean indexing: two scatters of N rows cost ~4 ms
        state.grad_accum += torch.where(seen, gn, 0.0)
        state.grad_denom += seen


def _densify_schedule(cfg: Any, state: TrainState, step: int) -> None:
    model = state.model
    until = densify_end(cfg)
    if until <= step or step < cfg.densify_from:
        return
    if step % cfg.densify_every == 0:
        _growth_check(cfg, state, step)
        grads = state.grad_accum / state.grad_denom.clamp_min(1)
        gen = torch.Generator().manual_seed(cfg.seed * 7_919 + step)
        n0 = len(model)
        cloned, split = model.densify(
            grads,
            cfg.densify_grad,
            cfg.percent_dense,
            gen,
            (state.budget or cfg.max_gaussians) if state.growing else n0,
        )
        with torch.no_grad():
            opac = torch.sigmoid(model.params["opacity_logits"])
            big = (
                torch.exp(model.params["log_scales"]).max(1).values > 0.1 * model.extent
            )
            prune = (opac < cfg.prune_opacity) | big
            if prune.all():  # never prune everything
                prune[:] = False
        model.keep(~prune)
        log.debug(
            "step %d: %d -> %d Gaussians (+%d cloned, +%d split, -%d pruned)",
            step,
            n0,
            len(model),
            cloned,
            split,
            int(prune.sum()),
        )
        state.grad_accum = torch.zeros(len(model))
        state.grad_denom = torch.zeros(len(model))
    if step % cfg.opacity_reset_every == 0:
        model.reset_opacity()


def densify_end(cfg: Any) -> int:
    """The step densification ends at: `densify_until`, and by 60 % of the run at
    the latest (with the opacity reset that goes with it), so the last iterations
    always refine a settled set."""
    return min(cfg.densify_until, int(0.6 * cfg.iterations))


PLATEAU_WINDOW = (50, 200)
"""The plateau stop's window: one pass over the train photos, at least 50 and at
most 200 steps (a window's mean loss then covers the same photos each time, up to
200 photos)."""


def plateau_window(n_views: int) -> int:
    """Steps in one window of the plateau stop for `n_views` train photos."""
    return int(min(max(n_views, PLATEAU_WINDOW[0]), PLATEAU_WINDOW[1]))


def _plateau_check(
    cfg: Any, state: TrainState, step: int, loss: float, n_views: int
) -> None:
    """The plateau stop: once densification is over (the Gaussians are settled),
    the training loss is averaged over windows of `plateau_window` steps; a
    window whose mean does not beat the best by the factor (1 − `stop_rel`) is a
    window without progress, and after `stop_patience` of them in a row training
    ends (`state.ended`). Reads losses only: deterministic, and resumable from the
    state's counters."""
    until = densify_end(cfg)
    if step <= until:
        return
    state.plateau_window[0] += loss
    state.plateau_window[1] += 1.0
    if (step - until) % plateau_window(n_views):
        return
    mean = state.plateau_window[0] / max(state.plateau_window[1], 1.0)
    state.plateau_window = [0.0, 0.0]
    best, bad = state.plateau
    if mean < best * (1.0 - cfg.stop_rel):
        state.plateau = [mean, 0.0]
        return
    state.plateau = [best, bad + 1.0]
    if bad + 1 >= cfg.stop_patience:
        state.ended = step
        log.info(
            "step %d: the loss has stopped improving (window mean %.5f, best %.5f, "
            "%d windows of %d steps without a %.1f %% gain): training ends",
            step, mean, best, cfg.stop_patience, plateau_window(n_views),
            100 * cfg.stop_rel,
        )  # fmt: skip


GROWTH_SPAN = 1.25  # compare rounds at least this factor apart in Gaussian count


def _growth_check(cfg: Any, state: TrainState, step: int) -> None:
    """The adaptive budget: stop growing when growth no longer pays.

    Each densification round records the mean L1 of the photos since the round
    before. Against the latest earlier round with at most 1/GROWTH_SPAN of
    today's Gaussians (and no opacity reset or mask start in between), the loss
    elasticity e = −Δln L / Δln N says what the added Gaussians bought; below
    `cfg.growth_elasticity` growth stops for the rest of the run (pruning goes
    on). `max_gaussians` stays the hard ceiling either way. Deterministic: it
    reads losses only.
    """
    total, count = state.window
    state.window = [0.0, 0.0]
    if count == 0:
        return
    n, loss = len(state.model), total / count
    state.rounds.append([float(step), float(n), loss])
    if not state.growing or cfg.growth_elasticity <= 0:
        return
    breaks = [cfg.mask_warmup] + list(
        range(cfg.opacity_reset_every, step + 1, cfg.opacity_reset_every)
    )
    for s_j, n_j, l_j in reversed(state.rounds[:-1]):
        window_start = s_j - 2 * cfg.densify_every  # the round after a break is off too
        if any(window_start < b <= step for b in breaks if b > 0):
            return  # a reset or the mask start lies between: not comparable
        if n_j * GROWTH_SPAN <= n:
            e = -(np.log(loss) - np.log(l_j)) / (np.log(n) - np.log(n_j))
            if e < cfg.growth_elasticity:
                state.stopped = [step, n]
                log.info(
                    "step %d: growth stops at %d Gaussians (loss elasticity %.3f "
                    "< %.3f since step %d, %d Gaussians)",
                    step,
                    n,
                    e,
                    cfg.growth_elasticity,
                    int(s_j),
                    int(n_j),
                )
            return


@torch.no_grad()
def visibility(
    model: GaussianModel, cams: list[Camera], backend: str = "auto"
) -> torch.Tensor:
    """[N] total blend weight (sum over pixels of alpha*T) over the given views."""
    g = model.gaussians()
    g = type(g)(*(t.detach() for t in (g.means, g.quats, g.scales, g.opacities)))
    total = torch.zeros(len(model))
    for cam in cams:
        ones = torch.ones(len(model), 1, requires_grad=True)
        with torch.enable_grad():
            out = render(g, cam, ones, backend=backend, depth=False)
            out.image.sum().backward()
        total += ones.grad[:, 0]
    return total


__all__ = ["TrainState", "in_frustum", "scene_extent", "train", "visibility"]
