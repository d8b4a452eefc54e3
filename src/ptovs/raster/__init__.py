"""Differentiable Gaussian rasterizer (next issue). Stages import only from here."""

from __future__ import annotations

VERSION = 0
