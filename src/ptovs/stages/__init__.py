"""Pipeline stages, one module per subcommand.

`STAGE_MODULES` maps each implemented stage's subcommand to its module; the CLI
imports a module only when its command runs (or for `ptovs status`). A stage is
added here when it exists, never before.
"""

from __future__ import annotations

STAGE_MODULES: dict[str, str] = {
    "reconstruct": "ptovs.stages.reconstruct",
    "render-appearances": "ptovs.stages.render_appearances",
    "extract-features": "ptovs.stages.extract_features",
    "uncertainty": "ptovs.stages.uncertainty",
    "train-ae": "ptovs.stages.train_ae",
    "train-male": "ptovs.stages.train_male",
    "query": "ptovs.stages.query",
    "evaluate": "ptovs.stages.evaluate",
}
