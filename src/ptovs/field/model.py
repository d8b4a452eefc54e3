"""Trainable 3D Gaussians: parameters, activations, optimiser, densify and prune.

Raw parameters follow 3DGS: means, unnormalised wxyz quaternions, log-scales,
opacity logits, SH as DC [N, 1, 3] plus rest [N, K-1, 3]. One Adam holds one
group per parameter, so densification edits the optimiser state in place
(rows appended with zero moments, rows removed with their moments).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ptovs.raster import SH_C0, Gaussians

NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")
APP_EMBED = "app_embed"  # optional per-Gaussian appearance embedding [N, G]


def rgb_to_sh(rgb: Tensor) -> Tensor:
    return (rgb - 0.5) / SH_C0


def inverse_sigmoid(x: Tensor) -> Tensor:
    x = x.clamp(1e-6, 1 - 1e-6)
    return torch.log(x / (1 - x))


def knn_mean_dist2(xyz: Tensor, k: int = 3, chunk: int = 2048) -> Tensor:
    """Mean squared distance to the k nearest other points ([N]); 3DGS's init scale."""
    n = xyz.shape[0]
    if n <= 1:
        return torch.ones(n, dtype=xyz.dtype)
    k = min(k, n - 1)
    out = torch.empty(n, dtype=xyz.dtype)
    for s in range(0, n, chunk):
        d2 = torch.cdist(xyz[s : s + chunk], xyz).square()
        d2[torch.arange(d2.shape[0]), torch.arange(s, s + d2.shape[0])] = math.inf
        out[s : s + chunk] = d2.topk(k, largest=False).values.mean(1)
    return out


@dataclass
class LearningRates:
    means: float = 1.6e-4  # times the scene extent, decays to means_final
    means_final: float = 1.6e-6
    sh_dc: float = 2.5e-3
    sh_rest: float = 2.5e-3 / 20
    opacity: float = 0.05
    scaling: float = 5e-3
    rotation: float = 1e-3
    app_embed: float = 5e-3


class GaussianModel:
    """Raw Gaussian parameters plus their Adam optimiser."""

    def __init__(
        self,
        params: dict[str, Tensor],
        sh_degree: int,
        lr: LearningRates,
        extent: float,
    ):
        self.sh_degree = sh_degree
        self.lr = lr
        self.extent = float(extent)
        names = NAMES + ((APP_EMBED,) if APP_EMBED in params else ())
        self.params = {
            k: params[k].detach().clone().float().requires_grad_(True) for k in names
        }
        lrs = {
            APP_EMBED: lr.app_embed,
            "means": lr.means * self.extent,
            "quats": lr.rotation,
            "log_scales": lr.scaling,
            "opacity_logits": lr.opacity,
            "sh_dc": lr.sh_dc,
            "sh_rest": lr.sh_rest,
        }
        self.opt = torch.optim.Adam(
            [{"params": [self.params[k]], "lr": lrs[k], "name": k} for k in names],
            lr=0.0,
            eps=1e-15,
            fused=True,  # one kernel per group: the loop version costs ~5 ms a step
        )

    # ------------------------------------------------------------ construction
    @classmethod
    def from_points(
        cls,
        xyz: np.ndarray,  # [P, 3]
        rgb: np.ndarray,  # [P, 3] uint8
        sh_degree: int,
        lr: LearningRates,
        extent: float,
        init_opacity: float = 0.1,
        embed_dim: int = 0,
    ) -> GaussianModel:
        """3DGS initialisation from a sparse point cloud; `embed_dim` > 0 adds a
        per-Gaussian appearance embedding, N(0, 0.1²) from torch's global RNG."""
        means = torch.as_tensor(np.asarray(xyz), dtype=torch.float32)
        n = means.shape[0]
        k = (sh_degree + 1) ** 2
        colors = torch.as_tensor(np.asarray(rgb), dtype=torch.float32) / 255.0
        dist2 = knn_mean_dist2(means).clamp_min(1e-7)
        params = {
            "means": means,
            "quats": torch.tensor([1.0, 0, 0, 0]).repeat(n, 1),
            "log_scales": torch.log(dist2.sqrt())[:, None].repeat(1, 3),
            "opacity_logits": inverse_sigmoid(torch.full((n,), init_opacity)),
            "sh_dc": rgb_to_sh(colors)[:, None, :],
            "sh_rest": torch.zeros(n, k - 1, 3),
        }
        if embed_dim:
            params[APP_EMBED] = 0.1 * torch.randn(n, embed_dim)
        return cls(params, sh_degree, lr, extent)

    def __len__(self) -> int:
        return self.params["means"].shape[0]

    # ---------------------------------------------------------------- activated
    @property
    def sh(self) -> Tensor:
        return torch.cat((self.params["sh_dc"], self.params["sh_rest"]), 1)

    def gaussians(self) -> Gaussians:
        p = self.params
        return Gaussians(
            means=p["means"],
            quats=p["quats"],
            scales=torch.exp(p["log_scales"]),
            opacities=torch.sigmoid(p["opacity_logits"]),
        )

    def set_means_lr(self, step: int, total: int) -> None:
        """Log-linear decay of the position learning rate (3DGS)."""
        t = min(max(step / max(total, 1), 0.0), 1.0)
        lr = math.exp(
            (1 - t) * math.log(self.lr.means) + t * math.log(self.lr.means_final)
        )
        for g in self.opt.param_groups:
            if g["name"] == "means":
                g["lr"] = lr * self.extent

    # ------------------------------------------------------------ densification
    def _edit(self, fn_param, fn_state) -> None:
        for g in self.opt.param_groups:
            old = g["params"][0]
            new = fn_param(g["name"], old.detach()).requires_grad_(True)
            state = self.opt.state.pop(old, None)
            if state:
                for s in ("exp_avg", "exp_avg_sq"):
                    state[s] = fn_state(state[s])
                self.opt.state[new] = state
            g["params"][0] = new
            self.params[g["name"]] = new

    def keep(self, mask: Tensor) -> None:
        """Keep only the Gaussians where mask is True (moments follow)."""
        self._edit(lambda _, x: x[mask].clone(), lambda s: s[mask].clone())

    def append(self, new: dict[str, Tensor]) -> None:
        """Append Gaussians (raw parameters); their Adam moments start at zero."""
        self._edit(
            lambda name, x: torch.cat((x, new[name].to(x.dtype))),
            lambda s: torch.cat(
                (s, s.new_zeros((new["means"].shape[0], *s.shape[1:])))
            ),
        )

    def reset_opacity(self, ceiling: float = 0.01) -> None:
        """opacity <- min(opacity, ceiling), moments of the logits cleared (3DGS)."""
        logits = self.params["opacity_logits"].detach()
        capped = torch.minimum(logits, inverse_sigmoid(torch.tensor(ceiling)))
        self._edit(
            lambda name, x: capped.clone() if name == "opacity_logits" else x,
            lambda s: s,
        )
        state = self.opt.state.get(self.params["opacity_logits"])
        if state:
            state["exp_avg"].zero_()
            state["exp_avg_sq"].zero_()

    def densify(
        self,
        grad2d: Tensor,  # [N] mean screen-space gradient norm
        threshold: float,
        percent_dense: float,
        generator: torch.Generator,
        max_gaussians: int,
    ) -> tuple[int, int]:
        """Clone small and split large Gaussians with a high gradient (3DGS).

        Returns:
            (cloned, split) counts.
        """
        p = {k: v.detach() for k, v in self.params.items()}
        scales = torch.exp(p["log_scales"])
        big = scales.max(1).values > percent_dense * self.extent
        hot = grad2d >= threshold
        room = max(max_gaussians - len(self), 0)
        clone = hot & ~big
        split = hot & big
        # over budget: keep the hottest candidates only
        n_new = int(clone.sum()) + int(split.sum())
        if n_new > room:
            cand = torch.nonzero(hot).squeeze(1)
            order = torch.argsort(grad2d[cand], descending=True)
            chosen = torch.zeros_like(hot)
            chosen[cand[order[:room]]] = True
            clone &= chosen
            split &= chosen
        n_clone, n_split = int(clone.sum()), int(split.sum())
        new = {k: v[clone] for k, v in p.items()}
        if n_split:
            s = scales[split].repeat(2, 1)
            noise = torch.randn(s.shape, generator=generator) * s
            q = torch.nn.functional.normalize(p["quats"][split], dim=1).repeat(2, 1)
            offset = _rotate(q, noise)
            children = {
                k: v[split].repeat(2, *([1] * (v.ndim - 1))) for k, v in p.items()
            }
            children["means"] = children["means"] + offset
            children["log_scales"] = torch.log(s / 1.6)
            new = {k: torch.cat((new[k], children[k])) for k in new}
        if n_clone or n_split:
            self.append(new)
        if n_split:  # the split parents go
            n = len(self)
            drop = torch.zeros(n, dtype=torch.bool)
            drop[: split.shape[0]] = split
            self.keep(~drop)
        return n_clone, n_split


def _rotate(q: Tensor, v: Tensor) -> Tensor:
    """Rotate vectors v [n, 3] by unit wxyz quaternions q [n, 4]."""
    w, xyz = q[:, :1], q[:, 1:]
    t = 2.0 * torch.cross(xyz, v, dim=1)
    return v + w * t + torch.cross(xyz, t, dim=1)
