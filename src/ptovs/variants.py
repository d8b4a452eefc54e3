"""Named recipes: bundles of per-stage config values (`ptovs train --variant NAME`).

- `male` (default): the paper's MALE-GS on the in-the-wild field, with two
  changes the accuracy benchmark chose: the authors' code's AE weighting
  (`train-ae.weighting = "loss_only"`) and the training-free lift in train-male
  (`train-male.mode = "lift"`: each Gaussian's weighted mean segment feature).
- `optimise`: `male` with train-male's optimiser (Adam to a plateau) instead.
- `paper`: the paper's text exactly: the optimiser and the AE trained on p·x
  (`train-ae.weighting = "input_and_target"`), the default before the lift.
- `langsplat`: LangSplat's recipe (one appearance, the original images' features,
  no uncertainty) on plain-3DGS geometry (`reconstruct.wild = false`).
- `langsplat-wild`: the same recipe on the in-the-wild geometry, so that geometry
  and language effects can be told apart.
- `lift`: the default's train-male spelt out (`train-male.mode = "lift"`);
  `lift-codes` takes the lift's mean over the 3-d target codes instead.

The LangSplat recipes extract features of the original photos only
(`extract-features.images = "orig"`), which depend on the photos alone: both
share one extract-features and one train-ae artifact.

The ablations of the paper's Table 3 (row numbers there) and iteration budgets
change one thing each against `male`; each reuses every artifact the change does
not touch (a query-only ablation retrains nothing). Table 3 row 2 ("w/o post
ensemble": appearances fused before the AE) is a different pipeline and is not
offered.
"""

from __future__ import annotations

VARIANTS: dict[str, dict[str, list[str]]] = {
    "male": {},
    # train-male's optimiser instead of the lift
    "optimise": {"train-male": ["mode=optimise"]},
    # the paper's text: the optimiser and the AE trained on p·x, D(E(p·x)) against
    # p·x (the default before the lift)
    "paper": {
        "train-ae": ["weighting=input_and_target"],
        "train-male": ["mode=optimise"],
    },
    # LangSplat optimises its field
    "langsplat": {
        "reconstruct": ["wild=false"],
        "extract-features": ["images=orig"],
        "train-ae": ["weighting=none", "tau_u=1.0"],
        "train-male": [
            "appearances=orig",
            "use_ut=false",
            "use_ua=false",
            "mode=optimise",
        ],
    },
    "langsplat-wild": {
        "extract-features": ["images=orig"],
        "train-ae": ["weighting=none", "tau_u=1.0"],
        "train-male": [
            "appearances=orig",
            "use_ut=false",
            "use_ua=false",
            "mode=optimise",
        ],
    },
    # the training-free lift (the default), spelt out
    "lift": {"train-male": ["mode=lift"]},
    # the same mean taken over the 3-d target codes
    "lift-codes": {"train-male": ["mode=lift-codes"]},
    # Table 3 ablations
    "no-multi-appearance": {"train-male": ["appearances=orig"]},  # row 1
    "no-uncertainty-ae": {"train-ae": ["weighting=none"]},  # row 3
    "tau-0.85": {"train-ae": ["tau_u=0.85"]},  # row 4
    "tau-0.95": {"train-ae": ["tau_u=0.95"]},  # row 5
    "no-tau-u": {"train-ae": ["tau_u=1.0"]},
    "no-tum-aum": {"train-male": ["use_ut=false", "use_ua=false"]},  # row 6
    "no-tum": {"train-male": ["use_ut=false"]},  # row 7
    "no-aum": {"train-male": ["use_ua=false"]},  # row 8
    "no-bg-filter": {"query": ["background_filter=off"]},  # row 9
    "imglvlmax": {"query": ["fusion=imglvlmax"]},  # row 10
    "pixmax": {"query": ["fusion=pixmax"]},  # row 11
    "pixavg": {"query": ["fusion=pixavg"]},  # row 12
    "pixweighted": {"query": ["fusion=pixweighted"]},  # row 13
    # iteration budgets of train-male's optimiser (`optimise` stops on a plateau)
    "budget-300": {"train-male": ["mode=optimise", "stop=fixed", "iterations=300"]},
    "budget-3k": {"train-male": ["mode=optimise", "stop=fixed", "iterations=3000"]},
}

TABLE3_ROWS = {
    "no-multi-appearance": 1,
    "no-uncertainty-ae": 3,
    "tau-0.85": 4,
    "tau-0.95": 5,
    "no-tum-aum": 6,
    "no-tum": 7,
    "no-aum": 8,
    "no-bg-filter": 9,
    "imglvlmax": 10,
    "pixmax": 11,
    "pixavg": 12,
    "pixweighted": 13,
    "male": 14,
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


__all__ = ["TABLE3_ROWS", "VARIANTS", "variant_sets"]
