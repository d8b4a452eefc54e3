"""The in-the-wild Gaussian radiance field: model, training, rendering, PLY, import."""

from __future__ import annotations

from ptovs.field.render import WildField, gaussian_colors, in_frustum

__all__ = ["WildField", "gaussian_colors", "in_frustum"]
