"""Export a reconstructed field as a standard 3DGS PLY with one appearance baked in."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ptovs.field.model import SH_C0
from ptovs.field.ply import write_ply
from ptovs.field.render import WildField


def appearance_embedding(field: WildField, image: str | None = None) -> torch.Tensor:
    """[D]: `image`'s embedding, or the neutral one (the mean embedding of the
    images the field knows). Only for a wild field with embeddings."""
    if image is not None:
        return field.embeddings_of([image])[0]
    return torch.stack(list(field.embeddings.values())).mean(0)


def baked_sh(field: WildField, image: str | None = None) -> torch.Tensor:
    """SH [N, K, 3] with the appearance of `image`'s embedding (or the neutral one)
    baked in: ΔSH (the affine map is one too), then the colour map if any.

    A plain field (no networks) returns its SH unchanged.
    """
    if field.nets is None or not field.embeddings:
        return field.sh
    emb = appearance_embedding(field, image)
    with torch.no_grad():
        field.nets.eval()
        sh = field.sh + field.nets.delta_sh(
            field.sh, field.gaussians.means, emb, field.gauss_embed
        )
        mt = field.nets.color_matrix(emb)
        if mt is not None:  # colour = SH·basis + 1/2 -> M·colour + t, exactly
            m, t = mt
            sh = sh @ m.T
            sh[:, 0] += (m @ torch.full((3,), 0.5) + t - 0.5) / SH_C0
        return sh


def export_field_ply(
    art,
    out: str | Path,
    image: str | None = None,
    index: np.ndarray | None = None,
    field: WildField | None = None,
) -> int:
    """Write the reconstruct artifact's Gaussians (or those in `index`) to `out`.

    Args:
        art: the reconstruct artifact.
        out: the PLY path (written atomically).
        image: bake this image's appearance (None: the neutral one).
        index: a bool mask [N] or integer indices of the Gaussians to write
            (None: all), e.g. a `ptovs select` result.
        field: the field loaded from `art` already (saves loading it again).

    Returns:
        The number of Gaussians written.
    """
    field = field or WildField.from_artifact(art)
    root = art.root()
    sh = baked_sh(field, image)[:, :16].numpy()  # viewers draw up to degree 3
    cols = [sh, root["opacity_logits"], root["log_scales"], root["quats"]]
    means = root["means"]
    if index is not None:
        idx = np.asarray(index)
        idx = np.flatnonzero(idx) if idx.dtype == bool else idx
        means, cols = means[idx], [c[idx] for c in cols]
    write_ply(out, means, *cols)
    return len(means)
