"""The accuracy instrument's labels (bench/accuracy.py): what each one measures,
as a ptovs.variants name and the --set items it adds per stage, which the default
run leaves out, and the groups the report reads (the 2-D ceilings, the chain from
the photo's features to the fused field).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from common import ROOT  # noqa: E402  (same folder)

TRUTH_EACH = ["segmenter=truth", "segment=each"]  # each image's own truth parts
# label -> (ptovs.variants name, extra --set items per stage); the order is the
# order a seed computes them in (the full method's chain first: most reuse it)
CHAIN_LABELS: dict[str, tuple[str, dict[str, list[str]]]] = {
    "male": ("male", {}),
    "paper": ("paper", {}),
    "optimise": ("optimise", {}),
    **{
        f"slot-{a}": ("male", {"query": [f'appearances=["{a}"]']})
        for a in ("orig", "nov1", "nov2", "nov3")
    },
    **{
        v: (v, {})
        for v in (
            "no-bg-filter",
            "imglvlmax",
            "pixmax",
            "pixavg",
            "pixweighted",
            "no-multi-appearance",
            "no-tum-aum",
            "no-tum",
            "no-aum",
            "budget-300",
            "budget-3k",
            "langsplat-wild",
            "langsplat",
        )
    },
    "oracle": ("male", {}),  # + the clean features' import_dir (`import_features`)
    # Table 3 rows with perfect segments: the synthetic truth's part masks of each
    # image (`segmenter = "truth"`, `segment = "each"`: the paper's own SAM setting
    # as an upper bound)
    **{
        f"{v}-truth": (v, {"extract-features": TRUTH_EACH})
        for v in ("male", "langsplat", "no-multi-appearance")
    },
}
# Table 4 on truth segments: `male-truth` with one change of render-appearances
# (the same appearance in every novel slot; random targets), so that the paired
# difference is the selection's alone
CHAIN_LABELS.update({
    f"{k}-truth": ("male", {"render-appearances": [item],
                            "extract-features": TRUTH_EACH})
    for k, item in (("same-appearance", "targets=same"),
                    ("select-random", "selection=random"))
})  # fmt: skip
# extract-features' segments and economies, each against `male` (one segmentation
# per view, from the photo): every image segmented (the paper's), one segmentation
# from the self render, and no crops under 16 or 32 px
CHAIN_LABELS.update({
    "male-segment-each": ("male", {"extract-features": ["segment=each"]}),
    "male-segment-once-self": ("male", {"extract-features": ["segment_from=self"]}),
    **{f"male-min-crop-{px}": ("male", {"extract-features": [f"min_crop_px={px}"]})
       for px in (16, 32)},
})  # fmt: skip


# the recipes of the speed-against-error front (bench/speed_error.py): the
# scene-fitted recipe (configs/auto.toml's values over this instrument's config),
# the full method on plain-3DGS geometry, and two Gaussian budgets
def _auto_sets() -> dict[str, list[str]]:
    import tomllib

    with open(ROOT / "configs" / "auto.toml", "rb") as f:
        auto = tomllib.load(f)
    return {stage: [f"{k}={json.dumps(v)}" for k, v in items.items()]
            for stage, items in auto.items() if stage != "scene"}  # fmt: skip


CHAIN_LABELS.update({
    "auto": ("male", _auto_sets()),
    "plain": ("male", {"reconstruct": ["wild=false"]}),
    **{f"gauss-{k}k": ("male", {"reconstruct": [f"max_gaussians={k * 1000}"]})
       for k in (3, 5)},
})  # fmt: skip
# the steadier query rules, each against `male` (query only: the chain's artifacts
# are shared): a soft level choice, a robust peak, the cut where the area is steadiest
STEADY_QUERY = {
    "level-soft": ["level_softness=0.02"],
    "level-soft-05": ["level_softness=0.05"],
    "level-soft-10": ["level_softness=0.1"],
    "peak-q": ["peak_quantile=0.995"],
    "thr-stable": ["threshold_mode=stable"],
}
CHAIN_LABELS.update({k: ("male", {"query": v}) for k, v in STEADY_QUERY.items()})
# the novel targets drawn in a name-hashed order (render-appearances.order)
CHAIN_LABELS["order-names"] = ("male", {"render-appearances": ["order=names"]})
CHAIN_LABELS["names-stable"] = (
    "male",
    {"render-appearances": ["order=names"], "query": ["threshold_mode=stable"]},
)
CHAIN_LABELS["no-multi-appearance-stable"] = (
    "no-multi-appearance", {"query": ["threshold_mode=stable"]})  # fmt: skip
# measured only when asked for (--labels), kept out of the default run so that
# `make bench-accuracy` stays within its time: Table 3 row 3, the code-space lift,
# and Table 3 and 4 rows under truth segments (`make bench-multiapp`)
OPTIONAL_LABELS = (
    "no-uncertainty-ae", "lift-codes", "male-truth", "langsplat-truth",
    "no-multi-appearance-truth", "same-appearance-truth", "select-random-truth",
    "male-segment-each", "male-segment-once-self", "male-min-crop-16",
    "male-min-crop-32", "auto", "plain", "gauss-3k", "gauss-5k", *STEADY_QUERY,
    "order-names", "names-stable", "no-multi-appearance-stable",
)  # fmt: skip
CHAIN_LABELS.update({v: (v, {}) for v in ("no-uncertainty-ae", "lift-codes")})
FEATURE_LABELS = ("2d", "2d-ae", "2d-nosmooth", "2d-best", "2d-truth")
TRUTH_SEGMENTS = ["images=orig", "segmenter=truth"]  # extract-features, for 2d-truth
ALL_LABELS = ("male", *FEATURE_LABELS, *(k for k in CHAIN_LABELS if k != "male"))
LABELS = tuple(k for k in ALL_LABELS if k not in OPTIONAL_LABELS)  # the default run
CHAIN_LOSS = (  # the chain from the photo's features to the fused field
    "2d-truth", "2d-best", "2d-nosmooth", "2d", "2d-ae",
    "slot-orig", "slot-nov1", "slot-nov2", "slot-nov3",
    "male", "imglvlmax", "pixmax", "pixavg", "pixweighted",
)  # fmt: skip
CEILINGS = ("oracle", "2d")
ANSWERED = 0.1  # a cluster some method answers has a mean IoU of at least this
