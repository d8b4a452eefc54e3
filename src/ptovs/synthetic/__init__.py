"""Synthetic landmark scenes with exact ground truth (docs/synthetic.md).

from ptovs.synthetic import generate_scene
scene_dir = generate_scene(Path("data/synth"), preset="tiny", seed=0)
"""

from __future__ import annotations

from ptovs.synthetic.generate import PRESETS, Preset, generate_scene

__all__ = ["PRESETS", "Preset", "generate_scene"]
