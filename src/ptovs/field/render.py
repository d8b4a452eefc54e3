"""The in-the-wild radiance field as later stages use it: frozen Gaussians + f_γ.

```python
field = WildField.from_artifact(reconstruct_artifact)
rgb = field.render(camera, field.embeddings_of(["img_j.jpg", "img_k.jpg"]))  # [2, H, W, 3]
```

Colour of Gaussian k under embedding l: SH_k + f_γ(SH_k, μ_k, l), evaluated only for
the Gaussians inside a generous frustum of the view (the others are not drawn).
Several embeddings render in one rasterizer pass: their colours are stacked as
channels [N, 3E] over the same geometry (the compositing weights are shared).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from ptovs.artifacts import read_json_dataset
from ptovs.nets import WildNets
from ptovs.raster import Camera, Gaussians, eval_sh, render

VIEW_MARGIN = 0.5  # frustum margin for ΔSH, in image sizes beyond each edge


def camera_center(cam: Camera) -> Tensor:
    T = cam.cam_from_world.float()  # noqa: N806
    return -T[:3, :3].T @ T[:3, 3]


def ray_dirs(cam: Camera) -> Tensor:
    """Unit world-space ray directions through the pixel centres, [H, W, 3]."""
    T = cam.cam_from_world.float()  # noqa: N806
    K = cam.K.float()  # noqa: N806
    v, u = torch.meshgrid(
        torch.arange(cam.height, dtype=torch.float32) + 0.5,
        torch.arange(cam.width, dtype=torch.float32) + 0.5,
        indexing="ij",
    )
    x = (u - K[0, 2]) / K[0, 0]
    y = (v - K[1, 2]) / K[1, 1]
    d = torch.stack((x, y, torch.ones_like(x)), -1) @ T[:3, :3]  # R^T d_cam
    return torch.nn.functional.normalize(d, dim=-1)


def composite_background(
    image: Tensor, alpha: Tensor, cam: Camera, nets: WildNets, embedding: Tensor
) -> Tensor:
    """image + (1 - alpha) * sky(rays, l): the wild model's background."""
    return image + (1.0 - alpha) * nets.background(ray_dirs(cam), embedding)


def in_frustum(means: Tensor, cam: Camera, margin: float = VIEW_MARGIN) -> Tensor:
    """[N] bool: centre in front of the camera and within `margin` image sizes."""
    T = cam.cam_from_world.to(means)  # noqa: N806
    K = cam.K.to(means)  # noqa: N806
    pc = means @ T[:3, :3].T + T[:3, 3]
    z = pc[:, 2]
    zs = z.clamp_min(1e-6)
    u = K[0, 0] * pc[:, 0] / zs + K[0, 2]
    v = K[1, 1] * pc[:, 1] / zs + K[1, 2]
    w, h = cam.width, cam.height
    return (
        (z > 0.01)
        & (u > -margin * w)
        & (u < (1 + margin) * w)
        & (v > -margin * h)
        & (v < (1 + margin) * h)
    )


def gaussian_colors(
    means: Tensor,  # [N, 3]
    sh: Tensor,  # [N, K, 3]
    degree: int,
    cam: Camera,
    nets: WildNets | None = None,
    embedding: Tensor | None = None,  # [D]
    visible_only: bool = True,
    gauss: Tensor | None = None,  # [N, G] per-Gaussian embeddings (affine, shading)
) -> Tensor:
    """RGB [N, 3] of every Gaussian seen from `cam`, with ΔSH when nets are given."""
    if (
        nets is not None
        and nets.f_gamma is not None
        and embedding is not None
        and means.shape[0]
    ):
        # PE(μ) sees detached positions: ΔSH must not drag geometry around
        if visible_only:
            idx = torch.nonzero(in_frustum(means.detach(), cam)).squeeze(1)
            if idx.numel():
                # index_select: its backward is an index_add, where indexing's
                # is a slower accumulating index_put
                g_idx = None if gauss is None else gauss.index_select(0, idx)
                delta = nets.delta_sh(
                    sh.index_select(0, idx), means.detach()[idx], embedding, g_idx
                )
                sh = sh.index_add(0, idx, delta)
        else:
            sh = sh + nets.delta_sh(sh, means.detach(), embedding, gauss)
    dirs = means - camera_center(cam).to(means)
    return eval_sh(min(degree, 3), sh, dirs)


@dataclass
class WildField:
    """Frozen Gaussians (activated), SH, the appearance networks and embeddings."""

    gaussians: Gaussians
    sh: Tensor  # [N, K, 3]
    sh_degree: int
    nets: WildNets | None = None
    embeddings: dict[str, Tensor] = field(default_factory=dict)
    background: Tensor | None = None  # [3] constant (plain 3DGS); None = from nets
    metrics: dict = field(default_factory=dict)
    gauss_embed: Tensor | None = None  # [N, G] (affine and shading appearances)

    def __len__(self) -> int:
        return len(self.gaussians)

    def subset(self, keep: Tensor) -> WildField:
        """The field with only the Gaussians in `keep` (bool [N] or indices)."""
        g = self.gaussians
        cut = Gaussians(g.means[keep], g.quats[keep], g.scales[keep], g.opacities[keep])
        return WildField(
            cut,
            self.sh[keep],
            self.sh_degree,
            self.nets,
            self.embeddings,
            self.background,
            self.metrics,
            None if self.gauss_embed is None else self.gauss_embed[keep],
        )

    @property
    def wild(self) -> bool:
        return self.nets is not None

    def embeddings_of(self, names: list[str]) -> Tensor:
        """[E, D] stored embeddings of these images (names or stems)."""
        stems = {k.rsplit(".", 1)[0]: k for k in self.embeddings}
        out = []
        for name in names:
            key = name if name in self.embeddings else stems.get(name)
            if key is None:
                from ptovs.errors import UnknownImageError

                some = ", ".join(list(self.embeddings)[:4])
                raise UnknownImageError(
                    f"no train image {name!r} in this field (have e.g. {some}); "
                    "--image takes one of the scene's train image names"
                )
            out.append(self.embeddings[key])
        return torch.stack(out)

    def embed(self, image: np.ndarray) -> Tensor:
        """The embedding [D] of any RGB image [H, W, 3] in [0, 1] (f_α ∘ f_β)."""
        if self.nets is None:
            raise ValueError("a plain (not in-the-wild) field has no embeddings")
        return self.nets.embed_image(image)[0]

    @torch.no_grad()
    def render(
        self,
        cam: Camera,
        embeddings: Tensor | None = None,  # [E, D]
        *,
        backend: str = "auto",
    ) -> Tensor:
        """Render one view under E embeddings in one pass.

        Args:
            cam: the view.
            embeddings: [E, D]; None (or a plain field) renders the field's own
                colours once (E = 1).
            backend: rasterizer backend.

        Returns:
            RGB [E, H, W, 3] in [0, 1] (clamped), float32.
        """
        g = self.gaussians
        if self.nets is None or embeddings is None:
            cols = gaussian_colors(g.means, self.sh, self.sh_degree, cam)
            bg = self.background if self.background is not None else cols.new_zeros(3)
            out = render(g, cam, cols, background=bg, backend=backend, depth=False)
            return out.image.clamp(0, 1)[None]
        self.nets.eval()
        cols = [self._colors(cam, emb) for emb in embeddings]
        out = render(g, cam, torch.cat(cols, 1), backend=backend, depth=False)
        e = embeddings.shape[0]
        img = out.image.reshape(cam.height, cam.width, e, 3).permute(2, 0, 1, 3)
        return self._finish(img, out.alpha, cam, embeddings).clamp(0, 1).contiguous()

    def _colors(self, cam: Camera, emb: Tensor) -> Tensor:
        """RGB [N, 3] of every Gaussian from `cam` under one embedding [D]."""
        g = self.gaussians
        return gaussian_colors(
            g.means,
            self.sh,
            self.sh_degree,
            cam,
            self.nets,
            emb,
            gauss=self.gauss_embed,
        )

    def _finish(self, img: Tensor, alpha: Tensor, cam: Camera, embeddings: Tensor):
        """Sky behind [E, H, W, 3] composited images, then each colour map."""
        if self.nets.sky is not None:
            dirs = ray_dirs(cam)
            sky = torch.stack([self.nets.background(dirs, emb) for emb in embeddings])
            img = img + (1.0 - alpha)[None] * sky
        if self.nets.f_map is not None:
            img = torch.stack(
                [
                    self.nets.map_colors(im, emb)
                    for im, emb in zip(img, embeddings, strict=True)
                ]
            )
        return img

    def fit_embedding(
        self,
        cam: Camera,
        image: np.ndarray,  # [H, W, 3] in [0, 1]
        mask: np.ndarray | None = None,  # [H, W] bool: pixels to fit
        *,
        init: Tensor | None = None,  # [D]; default f_α's embedding of the image
        steps: int = 100,
        lr: float = 0.02,
        backend: str = "auto",
    ) -> Tensor:
        """The embedding [D] under which this view renders closest to `image`.

        Test-time appearance fitting (NeRF-W's protocol for held-out photos):
        f_α reads a photo it never trained on imperfectly, so the embedding is
        refined by Adam on the L1 error of the masked pixels, everything else
        frozen. Starts from f_α's embedding (or `init`); with no pixels to fit
        it returns the start unchanged. Deterministic for a given thread count.
        """
        if self.nets is None:
            raise ValueError("a plain (not in-the-wild) field has no embeddings")
        start = self.embed(image) if init is None else init.detach().reshape(-1)
        target = torch.from_numpy(np.ascontiguousarray(image, np.float32))
        keep = (
            torch.ones(target.shape[:2], dtype=torch.bool)
            if mask is None
            else torch.from_numpy(np.asarray(mask, bool))
        )
        if keep.shape != target.shape[:2]:
            raise ValueError(f"mask {tuple(keep.shape)} does not fit the image")
        if not bool(torch.isfinite(target).all()):
            raise ValueError("the image has NaN or infinite pixels")
        if steps <= 0 or not bool(keep.any()):
            return start.clone()
        self.nets.eval()
        frozen = [p for p in self.nets.parameters() if p.requires_grad]
        for p in frozen:
            p.requires_grad_(False)
        emb = start.clone().requires_grad_(True)
        opt = torch.optim.Adam([emb], lr=lr)
        g = self.gaussians
        try:
            for _ in range(steps):
                opt.zero_grad(set_to_none=True)
                out = render(
                    g, cam, self._colors(cam, emb), backend=backend, depth=False
                )
                img = self._finish(out.image[None], out.alpha, cam, emb[None])[0]
                loss = (img - target).abs()[keep].mean()
                loss.backward()
                opt.step()
        finally:
            for p in frozen:
                p.requires_grad_(True)
        return emb.detach()

    # ----------------------------------------------------------------- loading
    @classmethod
    def from_artifact(cls, art) -> WildField:
        """Load the field written by the `reconstruct` stage."""
        root = art.root()
        cfg = art.config
        sh = torch.from_numpy(root["sh"]).float()
        g = Gaussians(
            means=torch.from_numpy(root["means"]).float(),
            quats=torch.from_numpy(root["quats"]).float(),
            scales=torch.exp(torch.from_numpy(root["log_scales"]).float()),
            opacities=torch.sigmoid(torch.from_numpy(root["opacity_logits"]).float()),
        )
        degree = int(root["sh_degree"])
        nets = None
        state = {
            k[4:]: torch.as_tensor(np.asarray(v))
            for k, v in root.items()
            if k.startswith("net.")
        }
        if state:
            nets = WildNets(
                cfg.get("preset", "cpu"),
                sh.shape[1],
                mask_concat=cfg.get("mask_concat", "features"),
                background="sky.fc1.weight" in state,
                delta_scale=cfg.get("delta_sh_scale", 1.0)
                if not cfg.get("import_dir")
                else 1.0,
                appearance="delta-sh"
                if cfg.get("import_dir")
                else cfg.get("appearance", "delta-sh"),
                color_map="f_map.weight" in state,
                stats=bool(cfg.get("image_stats", False)) and not cfg.get("import_dir"),
                learned=any(k.startswith("f_alpha.") for k in state),
                sky_stride=int(cfg.get("sky_stride", 0)),  # as it was trained
            )
            nets.load_state_dict(state)
            nets.eval()
        embeddings = {}
        for name in art.names():
            view = art[name]
            if "embedding" in view:
                embeddings[name] = torch.from_numpy(view["embedding"]).float()
        bg = (
            torch.from_numpy(root["background"]).float()
            if "background" in root
            else None
        )
        metrics = (
            read_json_dataset(root["metrics_json"]) if "metrics_json" in root else {}
        )
        gauss = (
            torch.from_numpy(root["app_embed"]).float() if "app_embed" in root else None
        )
        return cls(g, sh, degree, nets, embeddings, bg, metrics, gauss)
