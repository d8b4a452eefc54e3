"""Pipeline stages, one module per subcommand, each a leaf.

Stage NAME lives in `ptovs.stages.<name with _ for ->` and is listed, in order, in
`ptovs.pipeline.PIPELINE` (with `ptovs.registry.STAGE_MODULES`); the CLI imports a module only when
its command runs (or for `ptovs status`). A stage module imports the framework
(`ptovs.stage`, `ptovs.registry`) and the shared modules below them, never another stage or the CLI.
"""
