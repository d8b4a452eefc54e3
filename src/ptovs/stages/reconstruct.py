"""Reconstruct: photos -> in-the-wild Gaussian radiance field (docs/method.md §2).

Trains 3D Gaussians from the scene's points3D with the WE-GS appearance networks
(f_α embeds an image and its transient mask, f_β predicts the transient mask, f_γ
maps an embedding to each Gaussian's colour: by default a low-rank shading gain and
a per-photo colour matrix, or the paper's SH shift; by default the embedding also
carries 8 fixed colour statistics of the photo), or imports the authors' released
WE-GS model (`--set import_dir=DIR`). A folder of photos without a COLMAP model is
first posed with pycolmap SfM (`ptovs.sfm`), cached in the work dir.

Writes one artifact: Gaussians (raw 3DGS parameters), network weights, an
embedding for every image (train and test), a low-resolution transient mask per
train image (what the trained field, under the photo's own appearance, cannot
explain: the colour residual, not f_β's guess), the training log and metrics.
Training checkpoints every `checkpoint_every` iterations; a killed run resumes where
it stopped.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np
import torch
from tqdm import tqdm

from ptovs.artifacts import json_dataset
from ptovs.checkpoint import Checkpoint
from ptovs.field.losses import psnr
from ptovs.field.render import WildField
from ptovs.field.train import train, visibility
from ptovs.raster import VERSION as RASTER_VERSION
from ptovs.raster import Camera, Gaussians, kernels_only_parallel
from ptovs.registry import scene_input
from ptovs.scene import PhotoStack, Scene
from ptovs.stage import stage_command

log = logging.getLogger(__name__)

NAME = "reconstruct"
VERSION = 2 + 100 * RASTER_VERSION  # renders: the rasterizer's version is in the key
MASK_DIV = 4  # stored transient masks: working size / 4
RESIDUAL_HALF = 0.22
"""The colour residual (L2 over RGB in [0, 1]) that a stored transient mask scores 0.5;
between the two cuts with the best F1 on bench seed 0, 0.20 and 0.25 (docs/findings.md)."""


@dataclass(frozen=True)
class Config:
    wild: bool | Literal["colour", "auto"] = True
    """In-the-wild model (f_α, f_β, f_γ); false = plain 3DGS with the same budget;
    "colour": plain 3DGS with a photo-wide colour map and sky from each photo's
    colour statistics (exposure, tint, sky; no occluder masks, no per-Gaussian
    appearance; about plain's cost a step); "auto": decided from the photos
    (ptovs.fit)."""
    preset: Literal["cpu", "authors"] = "cpu"
    """Network sizes: "cpu" (64² inputs, narrow) or "authors" (their exact layers)."""
    mask_concat: Literal["features", "input"] = "features"
    """Where f_α sees the mask: the paper's "features" or the code's "input"."""
    appearance: Literal["delta-sh", "affine", "shading"] = "shading"
    """f_γ's form: "shading" (default: a per-channel gain exp(A(l) + g·B(l)),
    bilinear in a per-Gaussian embedding g and l; low-rank shading, no MLP), the
    paper's "delta-sh" (ΔSH from SH, PE(μ), l), or "affine" (a per-channel affine
    colour map from a per-Gaussian embedding, l and the base colour, as
    WildGaussians). With `color_map`, shading is 8-15 % faster than delta-sh at
    +0.1 to +0.5 dB test PSNR on bench seeds 0-2 (docs/findings.md)."""
    image_stats: bool = True
    """Append 8 fixed colour statistics of the photo (mean, spread, chroma, sky
    brightness) to f_α's learned embedding (+0.5 to +2.1 dB test PSNR on bench
    seeds 0-2, docs/findings.md); false = the paper's embedding alone."""
    color_map: bool = True
    """A per-image 3×3 colour matrix and offset from the embedding, applied to the
    rendered image (exposure, tint, black-and-white or sepia, which a per-channel
    gain cannot make; bakes exactly into SH)."""
    delta_sh_scale: float = 4.0
    """delta-sh: ΔSH = scale·tanh(·) (the authors' 1 limits the DC colour shift to
    ±0.28); shading: the factor on its linear map's output (its step size)."""
    sky_stride: int = 0
    """The sky head runs once per `sky_stride` × `sky_stride` pixels, bilinear
    between (a smooth function of the ray direction). 0: per pixel for the
    in-the-wild model, 4 for the colour rung."""
    sh_degree: int = 3
    iterations: int = 2500
    """Training steps (one photo each); the upper bound when `stop = "plateau"`."""
    stop: Literal["fixed", "plateau"] = "fixed"
    """"fixed": every iteration; "plateau": end once densification is over and
    the training loss, averaged over one pass over the photos (50 to 200 steps),
    has not improved by `stop_rel` for `stop_patience` passes in a row."""
    stop_rel: float = 0.005
    """Plateau: a pass counts as progress if its mean loss beats the best by this
    fraction."""
    stop_patience: int = 2
    """Plateau: passes without progress before training ends."""
    seed: int = 0
    ssim_lambda: float = 0.2
    mask_reg: float = 0.3
    """β in β·mean(M): without it the transient mask grows to 1 (docs/method.md
    §2 gives 0.15 for 30k iterations; at CPU budgets 0.15 let f_β mask whole hard
    photos early in training, measured on the bench preset)."""
    mask_warmup: int = 500
    """Iterations trained unmasked before the transient mask enters the loss."""
    lr_alpha: float = 1e-3
    lr_beta: float = 3e-4
    lr_gamma: float = 1e-3
    densify_from: int = 200
    densify_until: int = 1500
    densify_every: int = 100
    densify_grad: float = 1e-4
    """Mean screen-space gradient (3DGS's NDC units) that triggers clone/split;
    half the 3DGS value, because CPU budgets are ~10x shorter."""
    percent_dense: float = 0.01
    opacity_reset_every: int = 1000
    prune_opacity: float = 0.005
    max_gaussians: int = 25000
    """The hard ceiling: densification never adds past this count (memory and
    time per step grow with it), whatever the budget below says."""
    gaussians_per_mpx: float = 0.0
    """The budget that follows the scene: densification grows to at most this many
    Gaussians per million train-photo pixels (at working size), capped by
    max_gaussians; below the initial cloud there is no growth. 0 (default):
    max_gaussians alone. Measured (docs/findings.md): 2,700
    is the knee of bench's reconstruct (17k Gaussians, the PSNR of 25k, 3-12 % less
    time), but on bench seed 0 the whole chain's mIoU fell 0.448/0.399 -> 0.355/0.362
    and herzjesu_p8 lost 0.5 dB held-out, so it is not the default."""
    growth_elasticity: float = 0.0
    """The adaptive budget: growth stops once the loss elasticity −Δln L1 / Δln N
    of the photos (between densification rounds ≥ 25 % apart in count) falls
    below this; 0 = grow to the ceiling."""
    sh_increase_every: int = 400
    visible_only: bool = True
    """Evaluate ΔSH only for Gaussians inside the view's frustum (+50% margin)."""
    prune_unseen: float = 0.01
    """Remove Gaussians whose total blend weight over all train views is below this."""
    checkpoint_every: int = 250
    nerfw_steps: int = 50
    """Held-out photos are also scored under NeRF-W's protocol, the figure papers on
    photo collections report: the photo's embedding is fitted to its left half (Adam
    on the L1 error, this many steps, everything else frozen) and its right half is
    scored. 0 = skip that figure. 50 steps score within 0.04 dB of 100 in half the
    time (bench seed 1; docs/findings.md)."""
    backend: str = "auto"
    import_dir: str = ""
    """Folder with the authors' released WE-GS model; empty = train."""
    import_iteration: int = -1
    """Which chkpnt<iter> to import; -1 = the highest present."""


@dataclass(frozen=True)
class Inputs:
    scene: Any = scene_input()


def _views_and_images(scene):
    train_views = scene.train_views()
    if not train_views:
        raise ValueError(f"scene {scene.name} has no train views")
    # 16-bit in memory: the one store of this stage that grows with the collection
    images = PhotoStack(
        scene.load_image(v)
        for v in tqdm(
            train_views, desc=f"{NAME} {scene.name}: photos", unit="photo",
            disable=None, leave=False,
        )
    )  # fmt: skip
    cams = [Camera.from_view(v) for v in train_views]
    return train_views, images, cams


def _trained(
    scene: Scene,
    images: PhotoStack,
    cams: list[Camera],
    config: Config,
    ckpt: Checkpoint | None,
) -> tuple[dict[str, torch.Tensor], Any, dict | None, dict, torch.Tensor | None]:
    """Train the field (resuming from `ckpt`) and drop the Gaussians no train view
    sees. Returns the parameters, the nets, the history, the metrics and the
    constant background (plain 3DGS only)."""
    state = train(
        config,
        images,
        cams,
        (scene.points_xyz, scene.points_rgb),
        load=(ckpt.load if ckpt else lambda: None),
        save=(ckpt.save if ckpt else lambda s: None),
        desc=f"{NAME} {scene.name}",
    )
    if ckpt is not None:  # the final state: a crash while writing loses nothing
        ckpt.save(state.to_dict())
    model, nets = state.model, state.nets
    n_before = len(model)
    weights = visibility(model, cams, config.backend)
    unseen = weights < config.prune_unseen
    if unseen.all():
        raise ValueError(
            f"no Gaussian is seen by any train view of {scene.name}; the poses "
            "or points3D are inconsistent"
        )
    model.keep(~unseen)
    params = {k: v.detach() for k, v in model.params.items()}
    params["sh"] = torch.cat((params.pop("sh_dc"), params.pop("sh_rest")), 1)
    history = state.history
    metrics = {
        "gaussians_trained": n_before,
        "gaussians_unseen_removed": int(unseen.sum()),
        "gaussians": len(model),
        "gaussian_budget": state.budget,
        "train_seconds": round(state.seconds, 2),
        "seconds_per_iteration": round(state.seconds / max(state.step, 1), 4),
        "iterations": state.step,
    }
    if state.ended:  # the plateau stop ended training here
        metrics["stopped_early_at"] = state.ended
    if state.stopped:  # the adaptive budget stopped growth here
        metrics["growth_stopped_step"], metrics["growth_stopped_gaussians"] = (
            state.stopped
        )
    log.info(
        "%s: %d Gaussians (%d seen by no train view removed), %.1f s",
        scene.name,
        len(model),
        int(unseen.sum()),
        state.seconds,
    )
    background = torch.sigmoid(state.background.detach()) if nets is None else None
    return params, nets, history, metrics, background


def residual_mask(
    render: np.ndarray, photo: np.ndarray, size: tuple[int, int]
) -> np.ndarray:
    """A photo's transient mask from what the field cannot explain.

    The per-pixel colour residual r = ||render - photo|| (L2 over RGB), area-averaged
    to `size`, blurred (σ 1 px), scored 1 - 2^-(r / RESIDUAL_HALF)²: 0 where the field
    reproduces the photo, 0.5 at RESIDUAL_HALF, towards 1 on occluders. On bench
    seed 0 this ranks occluder pixels with AUROC 0.93 where f_β's own mask reaches
    0.77 (f_β still gates the training loss; this is the stored output).

    Args:
        render: [H, W, 3] the field's render under the photo's embedding.
        photo: [H, W, 3] the photo, float in [0, 1].
        size: (height, width) of the mask.

    Returns:
        [height, width] float16 in [0, 1]; non-finite residuals count as transient.
    """
    diff = render.astype(np.float32) - photo.astype(np.float32)
    with np.errstate(over="ignore", invalid="ignore"):  # huge renders: inf, then 1
        r = np.sqrt(np.square(diff).sum(-1))
    r = np.nan_to_num(r, nan=np.inf, posinf=np.inf)
    r = np.minimum(r, 4 * RESIDUAL_HALF)  # saturated: the score is 1 in float16
    r = cv2.resize(r, (size[1], size[0]), interpolation=cv2.INTER_AREA)
    r = cv2.GaussianBlur(r, (0, 0), 1.0)
    return (1 - np.exp2(-np.square(r / RESIDUAL_HALF))).astype(np.float16)


def nerfw_psnr(
    field: WildField, cam: Camera, image: np.ndarray, emb: torch.Tensor, config: Config
) -> float:
    """A held-out photo's PSNR under NeRF-W's protocol: its embedding (f_α's reading
    `emb` to start) fitted to the photo's left half, its right half scored. Every
    pixel counts (no labels needed); a photo too narrow to halve scores NaN."""
    half = image.shape[1] // 2
    if half == 0:
        return float("nan")
    left = np.zeros(image.shape[:2], bool)
    left[:, :half] = True
    fit = field.fit_embedding(
        cam, image, left, init=emb.reshape(-1), steps=config.nerfw_steps,
        backend=config.backend,
    )  # fmt: skip
    return psnr(field.render(cam, fit[None], backend=config.backend)[0], image, ~left)


def truth_occluders(scene: Scene, view, shape: tuple[int, int]) -> np.ndarray | None:
    """A synthetic scene's true occluder mask of `view` at working size `shape`
    (bool; None for a scene that is not synthetic or has no truth for the view).
    Used only to score: the trained field never sees it."""
    if not scene.synthetic:
        return None
    path = Path(scene.root) / "synthetic" / "truth" / f"{view.stem}.npz"
    if not path.is_file():
        return None
    with np.load(path) as z:  # allow_pickle stays False
        if "transient" not in z.files:
            return None
        mask = np.asarray(z["transient"]) > 0.5
    if mask.shape != tuple(shape):  # a downscaled scene: nearest, as labels are
        mask = cv2.resize(
            mask.astype(np.uint8), (shape[1], shape[0]),
            interpolation=cv2.INTER_NEAREST,
        ) > 0  # fmt: skip
    return mask


PSNR_FIGURES = (
    ("psnr_test", "as the photo is (f_α's reading of it)"),
    ("psnr_test_nerfw", "NeRF-W protocol: left half fitted, right half scored"),
    ("psnr_test_clean", "occluders excluded, synthetic truth"),
)
"""The held-out PSNRs reconstruct reports, each with what it is (docs/method.md §2)."""


def psnr_summary(metrics: dict) -> str | None:
    """The PSNR line of the log and of `ptovs status`: train, then each held-out
    figure the artifact has, labelled (None when it has none: an imported model)."""
    parts = [f"{metrics['psnr_train']:.2f} dB train"] if "psnr_train" in metrics else []
    parts += [
        f"{metrics[key]:.2f} dB held-out, {label}"
        for key, label in PSNR_FIGURES
        if metrics.get(key) is not None
    ]
    return ("PSNR " + "; ".join(parts)) if parts else None


def run(
    inputs: Inputs, config: Config, skip=frozenset(), ckpt: Checkpoint | None = None
) -> Iterator[tuple[str | None, dict]]:
    """Train (or import) the field, then yield per-view embeddings and masks."""
    # the same field, embeddings and held-out scores at any --threads
    # (ptovs.raster.kernels_only_parallel)
    with kernels_only_parallel():
        yield from _run(inputs, config, skip, ckpt)


def _run(
    inputs: Inputs, config: Config, skip=frozenset(), ckpt: Checkpoint | None = None
) -> Iterator[tuple[str | None, dict]]:
    scene = inputs.scene
    train_views, images, cams = _views_and_images(scene)
    if config.import_dir:
        from ptovs.field.authors import import_released

        field = import_released(config.import_dir, config.import_iteration)
        nets, metrics, history = field.nets, {"imported_from": config.import_dir}, None
        params = field.raw
        background = None
    else:
        params, nets, history, metrics, background = _trained(
            scene, images, cams, config, ckpt
        )

    for name, p in params.items():
        if not torch.isfinite(p).all():
            raise FloatingPointError(f"parameter {name} is not finite after training")
    sh_degree = config.sh_degree if not config.import_dir else field.sh_degree
    field_out = WildField(
        Gaussians(
            params["means"],
            params["quats"],
            torch.exp(params["log_scales"]),
            torch.sigmoid(params["opacity_logits"]),
        ),
        params["sh"],
        sh_degree,
        nets,
        background=background,
        gauss_embed=params.get("app_embed"),
    )
    if nets is not None:
        nets.eval()

    # per-view outputs: embeddings of every image, transient masks of train images
    by_name = {v.name: k for k, v in enumerate(train_views)}
    train_names = set(by_name)
    own_psnr: dict[str, list[float]] = {"train": [], "test": []}
    held_out: dict[str, list[float]] = {"nerfw": [], "clean": []}
    for view in scene.views:
        k = by_name.get(view.name)
        image = images[k] if k is not None else scene.load_image(view)
        cam = Camera.from_view(view)
        datasets: dict[str, Any] = {}
        if nets is not None:
            emb, _ = nets.embed_image(image)
            datasets["embedding"] = emb.numpy().astype(np.float32)
            rgb = field_out.render(cam, emb[None], backend=config.backend)[0]
            if view.name in train_names:
                size = (max(1, view.height // MASK_DIV), max(1, view.width // MASK_DIV))
                datasets["transient"] = residual_mask(rgb.numpy(), image, size)
        else:
            emb, rgb = None, field_out.render(cam, backend=config.backend)[0]
        own_psnr["train" if view.name in train_names else "test"].append(
            psnr(rgb, image)
        )
        if view.name not in train_names:
            if emb is not None and config.nerfw_steps > 0:
                held_out["nerfw"].append(nerfw_psnr(field_out, cam, image, emb, config))
            occluders = truth_occluders(scene, view, image.shape[:2])
            if occluders is not None and not occluders.all():
                held_out["clean"].append(psnr(rgb, image, ~occluders))
        if view.name not in skip:
            yield view.name, datasets

    for split, values in own_psnr.items():
        if values:
            metrics[f"psnr_{split}"] = round(float(np.mean(values)), 3)
    for kind, values in held_out.items():
        finite = [v for v in values if np.isfinite(v)]  # NaN never reaches the artifact
        if finite:
            metrics[f"psnr_test_{kind}"] = round(float(np.mean(finite)), 3)
    log.info("%s: %s", scene.name, psnr_summary(metrics))
    root: dict[str, Any] = {
        "means": params["means"].numpy(),
        "quats": params["quats"].numpy(),
        "log_scales": params["log_scales"].numpy(),
        "opacity_logits": params["opacity_logits"].numpy(),
        "sh": params["sh"].numpy(),
        "sh_degree": np.int64(sh_degree),
        "metrics_json": json_dataset(metrics),
    }
    if field_out.background is not None:
        root["background"] = field_out.background.numpy()
    if field_out.gauss_embed is not None:
        root["app_embed"] = field_out.gauss_embed.numpy()
    if nets is not None:
        for k, v in nets.state_dict().items():
            root[f"net.{k}"] = v.numpy()
    if history:
        for k, v in history.items():
            root[f"log_{k}"] = np.asarray(v, np.float64)
    yield None, root


def _count(inputs: Inputs, config: Config) -> int:
    return len(inputs.scene.views)


command = stage_command(
    NAME, VERSION, Config, Inputs, run, count=_count, summary=psnr_summary
)


__all__ = ["Config", "Inputs", "command", "run"]
