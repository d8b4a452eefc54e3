# ptovs: set up, demo, test, benchmark; and run the pipeline over DATA/* scenes.
#   make demo          fresh machine → venv, tiny synthetic scene, every stage, masks, metrics, a PLY
#   make test          the test suite (what CI runs)
#   make -j3 scenes    every scene under DATA in parallel, stages in order
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
DATA   ?= data
WORK   ?= work
CONFIG ?= configs/default.toml
# scene folders under DATA (the PT-OVS `label` folder is not a scene)
SCENES ?= $(filter-out label,$(notdir $(patsubst %/,%,$(wildcard $(DATA)/*/))))
# implemented stages, in pipeline order (each issue adds its own)
STAGES := reconstruct render-appearances extract-features uncertainty train-ae train-male query evaluate
PTOVS  := $(BIN)/ptovs --work-dir $(WORK) --config $(CONFIG)

.PHONY: setup demo test lint format bench scenes status clean-work $(SCENES)

setup: $(VENV)/.installed
$(VENV)/.installed: pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q torch==2.13.0        # the CPU wheel; never an unpinned torch
	$(BIN)/pip install -q torchvision==0.28.0  # matches torch 2.13 (for the extras)
	$(BIN)/pip install -q -e '.[dev,clip,sam]'  # the extras' tests run in CI
	touch $@

demo: setup
	$(BIN)/ptovs synth-scene $(DATA) --preset tiny --seed 0
	@for s in $(STAGES); do $(PTOVS) $$s --data $(DATA)/tiny_s0 || exit 1; done
	$(PTOVS) export-ply --data $(DATA)/tiny_s0 --out $(WORK)/tiny_s0/tiny_s0.ply
	$(PTOVS) status --data $(DATA)/tiny_s0
	@echo "masks, heatmaps, overlays: $(WORK)/tiny_s0/query-out/male/; metrics: $(WORK)/tiny_s0/evaluate.md"

test: setup
	$(BIN)/python -m pytest -q

lint: setup
	$(BIN)/ruff format --check . && $(BIN)/ruff check .

format: setup
	$(BIN)/ruff format . && $(BIN)/ruff check --fix .

bench: setup
	$(BIN)/python bench/raster.py
	$(BIN)/python bench/synth_timing.py
	$(BIN)/python bench/encoder_calibration.py --seeds 0 1 2 --out $(WORK)/synthetic
	$(BIN)/python bench/reconstruct.py --seeds 0 1 2 --data $(DATA) --work $(WORK)/bench
	$(BIN)/python bench/extract.py --seeds 0 1 2 --data $(DATA) --work $(WORK)/bench
	$(BIN)/python bench/train.py --seeds 0 1 2 --data $(DATA) --work $(WORK)/bench
	$(BIN)/python bench/query.py --seeds 0 1 2 --data $(DATA) --work $(WORK)/bench

scenes: $(SCENES)
$(SCENES): setup
	@for s in $(STAGES); do $(PTOVS) $$s --scene $@ --data $(DATA)/$@ || exit 1; done
	@$(PTOVS) status --scene $@ --data $(DATA)/$@

status: setup
	@for sc in $(SCENES); do $(PTOVS) status --scene $$sc --data $(DATA)/$$sc; done

clean-work:
	rm -rf $(WORK)
