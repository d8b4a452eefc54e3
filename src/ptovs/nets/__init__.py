"""Networks shared by stages: the in-the-wild appearance networks (f_α, f_β, f_γ)."""

from __future__ import annotations

from ptovs.nets.wild import (
    PRESETS,
    AppearanceEncoder,
    ColorNet,
    NetPreset,
    TransientNet,
    WildNets,
    positional_encoding,
)

__all__ = [
    "PRESETS",
    "AppearanceEncoder",
    "ColorNet",
    "NetPreset",
    "TransientNet",
    "WildNets",
    "positional_encoding",
]
