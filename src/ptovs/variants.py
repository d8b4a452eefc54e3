"""Named recipes: bundles of per-stage config values (`ptovs train --variant NAME`).

- `male` (default): the paper's MALE-GS on the in-the-wild field.
- `langsplat`: LangSplat's recipe (one appearance, the original images' features,
  no uncertainty) on plain-3DGS geometry (`reconstruct.wild = false`).
- `langsplat-wild`: the same recipe on the in-the-wild geometry, so that geometry
  and language effects can be told apart.

The LangSplat recipes extract features of the original photos only
(`extract-features.images = "orig"`), which depend on the photos alone: both
share one extract-features and one train-ae artifact.
"""

from __future__ import annotations

VARIANTS: dict[str, dict[str, list[str]]] = {
    "male": {},
    "langsplat": {
        "reconstruct": ["wild=false"],
        "extract-features": ["images=orig"],
        "train-ae": ["weighting=none", "tau_u=1.0"],
        "train-male": ["appearances=orig", "use_ut=false", "use_ua=false"],
    },
    "langsplat-wild": {
        "extract-features": ["images=orig"],
        "train-ae": ["weighting=none", "tau_u=1.0"],
        "train-male": ["appearances=orig", "use_ut=false", "use_ua=false"],
    },
}


def variant_sets(
    name: str, user: dict[str, list[str]] | None = None
) -> dict[str, list[str]]:
    """The variant's `--set` items per stage, followed by the user's (which win)."""
    if name not in VARIANTS:
        raise KeyError(f"unknown variant {name!r}; choose from {', '.join(VARIANTS)}")
    out = {stage: list(items) for stage, items in VARIANTS[name].items()}
    for stage, items in (user or {}).items():
        out.setdefault(stage, []).extend(items)
    return out


__all__ = ["VARIANTS", "variant_sets"]
