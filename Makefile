# ptovs: set up, demo, test, benchmark; and run the pipeline over DATA/* scenes.
#   make demo          fresh machine → venv, the demo synthetic scene, every stage, masks, metrics, a PLY
#   make view          after make demo: roam the demo scene and ask it things in the browser (open the printed URL)
#   make test          the test suite (what CI runs)
#   make bench         the rasterizer, each stage on bench scenes, the real photo sets,
#                      then bench-growth
#   make bench-accuracy  the accuracy instrument: 18 seeds, every variant, CIs (~2 h)
#   make bench-standin   the stand-in's failure profile against CLIP's (calibration seeds)
#   make bench-multiapp  the paper's multi-appearance claim in stand-in 5's world (fresh seeds)
#   make bench-real-chain  the real-class chain end to end, 100 landmark photos (~1.5 h)
#   make bench-growth  each stage's time, memory and quality at 100-763 photos (landmark)
#   make -j3 all       every scene under DATA in parallel, stages in order, then the
#                      per-scene table (a failing scene is marked, the others go on)
#   make cluster       the same through Snakemake: PROFILE=local (default) or slurm
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
DATA   ?= data
WORK   ?= work
CONFIG ?= configs/default.toml
# the real photo sets with cameras (Strecha et al.'s herzjesu_p8 and fountain_p11,
# each a folder of images/ and a COLMAP model; bench/real.py, segment pictures):
# put them under data/real or pass REAL=DIR
REAL   ?= $(ROOT)/data/real
# $(call q,TEXT): TEXT as one single-quoted shell word, whatever it holds (paths in
# recipes go through it: a space, quote or ; in DATA or WORK stays in its argument)
q       = '$(subst ','\'',$(1))'
QDATA   = $(call q,$(DATA))
QWORK   = $(call q,$(WORK))
# the scene folders under DATA and the stages in order: one list (src/ptovs/pipeline.py)
# for this Makefile and the cluster workflow (workflow/Snakefile); stdlib Python, so it
# answers before the venv exists. Scene names go into shell commands: a folder under
# DATA whose name is not allowed (pipeline.SCENE_NAME: letters, digits, . _ -), or
# such a name in SCENES=..., stops make here, before any recipe, with the script's
# message on stderr ($(shell) alone would not stop make: .SHELLSTATUS, make >= 4.2;
# an older make runs no scene then, the list being empty, and `ptovs table` refuses)
ROOT   := $(patsubst %/,%,$(dir $(abspath $(lastword $(MAKEFILE_LIST)))))
PLAN   := PYTHONPATH=$(call q,$(ROOT)/src) $(PYTHON) -m ptovs.pipeline
FOLDERS := $(shell $(PLAN) scenes $(QDATA))
ifeq ($(.SHELLSTATUS),3)
$(error a scene folder under $(DATA) has a name that is not allowed: rename it (see the message above); nothing was run)
else ifneq ($(filter-out 0,$(.SHELLSTATUS)),)
$(error listing the scenes under $(DATA) failed (exit $(.SHELLSTATUS), see above; is $(PYTHON) a Python 3?))
endif
ifeq ($(origin SCENES),undefined)
SCENES := $(FOLDERS)
else
SCENES_OK := $(shell $(PLAN) check-scenes $(call q,$(SCENES)))
ifneq ($(filter-out 0,$(.SHELLSTATUS)),)
$(error SCENES has a name that is not allowed: give other names (see the message above); nothing was run)
endif
endif
STAGES := $(shell $(PLAN) stages)
# what the pipeline targets run first and with (tests point these at their own env)
SETUP     ?= setup
PTOVS_BIN ?= $(BIN)/ptovs
PTOVS  := $(PTOVS_BIN) --work-dir $(QWORK) --config $(call q,$(CONFIG))
# the demo: the `demo` synthetic scene, seed 0 (20 photos of 160-176 px; its parts are
# an Ionic column, two minarets, a stone wall, a tiled roof), its config (a Gaussian
# budget that fits it), and the text select and roam find (docs/results.md, "The demo")
DEMO_SCENE  ?= demo_s0
DEMO_CONFIG ?= configs/demo.toml
DEMO_TEXT   ?= Minaret
DEMO := $(PTOVS_BIN) --work-dir $(QWORK) --config $(call q,$(DEMO_CONFIG))

.PHONY: setup demo pictures view test system-deps test-slurm lint format bench bench-accuracy bench-speed-error bench-stability bench-encoders bench-real-chain bench-standin bench-multiapp bench-growth check-readme all cluster scenes table status clean-work $(SCENES)

# where torch and torchvision come from: PyTorch's CPU index by default (PyPI's Linux
# torch is the CUDA build, several GB); with an NVIDIA GPU give its CUDA index, e.g.
# TORCH_INDEX=https://download.pytorch.org/whl/cu130; empty, pip's own configuration decides
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu
TORCH_FROM   = $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX))
setup: $(VENV)/.installed
$(VENV)/.installed: pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q torch==2.13.0 $(TORCH_FROM)        # never an unpinned torch
	$(BIN)/pip install -q torchvision==0.28.0 $(TORCH_FROM)  # matches torch 2.13 (for the extras)
	$(BIN)/pip install -q 'setuptools>=70.1'  # builds sam2 below (no wheel package needed)
	SAM2_BUILD_CUDA=0 $(BIN)/pip install -q --no-build-isolation --no-deps sam2==1.1.0  # pyproject's [sam2]
	$(BIN)/pip install -q -e '.[dev,clip,sam,sam2,view,cluster]'  # the extras' tests run in CI
	$(BIN)/pip install -q --no-deps viser==1.0.0  # see pyproject's [view] extra
	touch $@

demo: setup
	$(BIN)/ptovs synth-scene $(QDATA) --preset demo --seed 0
	@for s in $(STAGES); do $(DEMO) $$s --data $(QDATA)/$(DEMO_SCENE) || exit 1; done
	$(DEMO) export-ply --data $(QDATA)/$(DEMO_SCENE) --out $(QWORK)/$(DEMO_SCENE)/$(DEMO_SCENE).ply
	$(DEMO) select "$(DEMO_TEXT)" --data $(QDATA)/$(DEMO_SCENE) --out $(QWORK)/$(DEMO_SCENE)/select.ply --rest $(QWORK)/$(DEMO_SCENE)/rest.ply
	$(DEMO) style --data $(QDATA)/$(DEMO_SCENE)
	$(DEMO) roam "$(DEMO_TEXT)" --data $(QDATA)/$(DEMO_SCENE) --out $(QWORK)/$(DEMO_SCENE)/tour.mp4 --frames 30 --size 256x176
	$(DEMO) status --data $(QDATA)/$(DEMO_SCENE)
	@echo "masks, heatmaps, overlays: "$(QWORK)"/$(DEMO_SCENE)/query-out/male/; metrics: "$(QWORK)"/$(DEMO_SCENE)/evaluate.md"
	@echo "selection: "$(QWORK)"/$(DEMO_SCENE)/select.ply; styles: "$(QWORK)"/$(DEMO_SCENE)/style-out/male/; video: "$(QWORK)"/$(DEMO_SCENE)/tour.mp4"

# after `make demo`: the README's pictures and the figures their captions quote
# (docs/img, docs/results/demo.json), redrawn from the demo's outputs
pictures: setup
	$(BIN)/python bench/pictures.py --data $(QDATA)/$(DEMO_SCENE) --work $(QWORK) --config $(call q,$(DEMO_CONFIG)) --text "$(DEMO_TEXT)" --figures docs/results/demo.json

# after `make demo`: the demo scene in the browser (open the URL it prints, with its token; Ctrl-C stops)
view: setup
	$(DEMO) view --data $(QDATA)/$(DEMO_SCENE)

# TEST_JOBS pytest workers (pytest-xdist): the suite waits on processes, browsers and
# a Slurm for much of its time, so two workers on two cores finish it sooner; the
# Slurm tests share one worker (tests/conftest.py). Without root and the system
# packages, the first line says which are missing and the suite runs without their
# tests (named in the summary); CI=true or PTOVS_REQUIRE_SYSTEM_DEPS=1 requires them
TEST_JOBS ?= 2
test: system-deps setup
	$(BIN)/python -m pytest -q -n $(TEST_JOBS) --dist loadgroup --durations=25

# the README's commands run as written on the synthetic scenes they name (about an
# hour; tests/test_readme.py checks every line parses, in seconds)
check-readme: setup
	$(BIN)/python tools/check_readme.py --root work/readme

# the system packages the tests need (g++, chromium, a single-node Slurm): installed
# when run as root (sudo make system-deps); else one line names the missing ones
system-deps:
	@bash tools/system-deps.sh

# the workflow on a real single-node Slurm alone (root; apt-get install slurm-wlm munge
# slurmdbd mariadb-server): `make test` runs it too
test-slurm: setup
	$(BIN)/python -m pytest -q -m slurm tests/test_workflow.py

lint: setup
	$(BIN)/ruff format --check . && $(BIN)/ruff check .

format: setup
	$(BIN)/ruff format . && $(BIN)/ruff check --fix .

# the rasterizer; reconstruct, extract, train and query on bench seeds (scenes under
# DATA, work under WORK/bench); the real photo sets (REAL) and their pictures
bench: setup
	$(BIN)/python bench/raster.py
	$(BIN)/python bench/reconstruct.py --seeds 0 1 2 --data $(QDATA) --work $(QWORK)/bench
	$(BIN)/python bench/extract.py --seeds 0 1 2 --data $(QDATA) --work $(QWORK)/bench
	$(BIN)/python bench/train.py --seeds 0 1 2 --data $(QDATA) --work $(QWORK)/bench
	$(BIN)/python bench/query.py --seeds 0 --data $(QDATA) --work $(QWORK)/bench
	$(BIN)/python bench/real.py --real $(REAL) --work $(QWORK)/real
	$(BIN)/python bench/real.py --real $(REAL) --work $(QWORK)/real --sets fountain_p11 --megapixels 12
	$(BIN)/python bench/segment_pictures.py $(REAL)/herzjesu_p8/images/0004.jpg --out docs/img/segments_herzjesu.jpg
	$(BIN)/python bench/segment_pictures.py $(REAL)/fountain_p11/images/0005.jpg --out docs/img/segments_fountain.jpg
	$(MAKE) bench-growth

# the accuracy instrument: ACC_SEEDS seeds of the `small` preset, every
# variant, ceilings, cluster-bootstrap CIs; dev = the first half of the seeds, test
# = the second. Resumes where a killed run stopped. Tables: work/accuracy/accuracy.md
ACC_SEEDS ?= 0-17
bench-accuracy: setup
	$(BIN)/python bench/accuracy.py --preset small --seeds $(ACC_SEEDS) \
	  --data $(QDATA)/accuracy --work $(QWORK)/accuracy

# speed against error, one front per question: every recipe's whole chain against
# mIoU (the accuracy instrument: dev seeds 0-8 choose, test seeds 9-17 report) and
# reconstruct against held-out PSNR (bench seed 0, herzjesu_p8, fountain_p11, 500
# steps); raw CSVs under docs/results/, the picture docs/img/speed_error.png. Resumes
# where a killed run stopped; about 3 h from scratch
bench-speed-error: setup
	$(BIN)/python bench/speed_error.py --acc-data $(QDATA)/accuracy --acc-work $(QWORK)/accuracy \
	  --real $(REAL) --data $(QDATA)/speed_error --work $(QWORK)/speed_error \
	  --recon-json $(QWORK)/speed_error/reconstruct.json

# stability: the answers a user reads when the input moves by what no user would notice
# (the photos re-saved as JPEG 95, torch's float paths moved, the chain's seeds changed),
# each run in its own work folder: the demo scene under every perturbation, the
# accuracy instrument's dev seeds (STAB_SEEDS; about 6 min a seed, not timed whole),
# then the demo's perturbations made only after a stage (where the change grows)
STAB_SEEDS ?= 0-8
bench-stability: setup
	$(BIN)/python bench/stability.py --seeds $(STAB_SEEDS) --data $(QDATA)/stability \
	  --acc-data $(QDATA)/accuracy --work $(QWORK)/stability --out $(QWORK)/stability/stability.json

# the stand-in encoder's failure profile against CLIP's: calibration seeds only,
# crops only, no method measured (STANDIN_VERSION=1 for the original stand-in)
STANDIN_VERSION ?= 5
bench-standin: setup
	$(BIN)/python bench/standin_profile.py --seeds 300-305 --jobs 2 --version $(STANDIN_VERSION) \
	  --out $(QWORK)/standin/profile_v$(STANDIN_VERSION).json

# the paper's multi-appearance claim judged in the world of stand-in 5 on truth
# segments, fresh seeds dev 220-228, test 229-246, differences paired against
# male-truth: the front end first (MULTIAPP_LABELS=2d-truth MULTIAPP_SEEDS=220-228),
# then pass 1 (the default), then Table 4
# (MULTIAPP_LABELS="same-appearance-truth select-random-truth")
MULTIAPP_LABELS ?= 2d-truth male-truth no-multi-appearance-truth langsplat-truth
MULTIAPP_SEEDS ?= 220-246
MULTIAPP_DEV ?= 220-228
bench-multiapp: setup
	$(BIN)/python bench/accuracy.py --preset small --standin 5 --seeds $(MULTIAPP_SEEDS) --dev $(MULTIAPP_DEV) \
	  --data $(QDATA)/accuracy-v5 --work $(QWORK)/accuracy-v5 \
	  --labels $(MULTIAPP_LABELS) --base male-truth

# real-class encoders on 2 cores, random weights (docs/results.md, "Real encoders on a
# CPU"): crops/s of each encoder in fp32 and bf16, and by runtime at 1 and 2 threads
bench-encoders: setup
	$(BIN)/python bench/encoders.py --out $(QWORK)/encoders.json
	$(BIN)/python bench/encoders.py --runtimes --models MobileCLIP2-S0 ViT-B-16 --crops 96 \
	  --out $(QWORK)/runtimes.json

# the real-class chain end to end (random-weight MobileCLIP2-S0, hier; full method and
# photo alone, photos to query and select, each stage in its own process) on 200
# landmark photos, SAM 2.1 tiny on 20 of them, 763-photo hours projected (~2 h)
bench-real-chain: setup
	$(BIN)/python bench/real_chain.py --photos 200 --sam2 20 --work $(QWORK)/real_chain

# how each stage's time, peak RSS and output quality grow with the collection: the
# landmark world at 100, 200, 400 and 763 photos, one size at a time, the default
# chain on 2 threads (about 3 h); scenes under $(WORK)/growth/data, results in
# $(WORK)/growth/growth.json, the plot beside it
bench-growth: setup
	$(BIN)/python bench/growth.py --preset landmark --seed 0 --photos 100 200 400 763 \
	  --threads 2 --work $(QWORK)/growth --plot

# threads per scene job: the cores shared among make's parallel jobs (-jN; a bare -j
# counts as one job per core), at least one. OpenMP teams on oversubscribed cores
# spin at every barrier: three 2-thread jobs on 2 cores ran ~3x slower in total.
NPROC   := $(shell nproc 2>/dev/null || echo 1)
JOBS     = $(if $(filter -j,$(MAKEFLAGS)),$(NPROC),$(or $(patsubst -j%,%,$(filter -j%,$(MAKEFLAGS))),1))
THREADS ?= $(shell n=$$(( $(NPROC) / $(JOBS) )); [ $$n -ge 1 ] && echo $$n || echo 1)

# every stage of every scene, then the table; -k and the leading "-": a failing
# scene writes $(WORK)/<scene>/FAILED (with its log's path) and the others go on
all: $(SETUP)
	-@$(MAKE) --no-print-directory -k scenes
	@$(PTOVS) table --data $(QDATA) --out $(QWORK)/table.md --strict

scenes: $(SCENES)
$(SCENES): $(SETUP)
	@mkdir -p $(call q,$(WORK)/$@) && rm -f $(call q,$(WORK)/$@/FAILED)
	@for s in $(STAGES); do \
	  OMP_NUM_THREADS=$(THREADS) $(PTOVS) -q $$s --scene $(call q,$@) --data $(call q,$(DATA)/$@) \
	    >> $(call q,$(WORK)/$@/run.log) 2>&1 || \
	  { echo "$$s failed; see "$(call q,$(WORK)/$@/run.log) | tee $(call q,$(WORK)/$@/FAILED); exit 1; }; \
	done
	@echo $(call q,$@: every stage done)

# the same batch through Snakemake (extra [cluster]; workflow/Snakefile): PROFILE=local
# on this machine's cores, PROFILE=slurm on a cluster (partition and account: edit
# workflow/profiles/slurm/config.yaml, or SMK_ARGS="--default-resources
# slurm_partition=P slurm_account=A"). Same per-scene table as `all`, in WORK/table.md
PROFILE  ?= local
SMK_ARGS ?=
cluster: $(SETUP)
	$(BIN)/python -m snakemake -s $(call q,$(ROOT)/workflow/Snakefile) \
	  --profile $(call q,$(ROOT)/workflow/profiles/$(PROFILE)) \
	  $(if $(filter local,$(PROFILE)),--cores $(NPROC)) $(SMK_ARGS) \
	  --config data=$(QDATA) work=$(QWORK) config=$(call q,$(CONFIG))

table: $(SETUP)
	@$(PTOVS) table --data $(QDATA) --out $(QWORK)/table.md

status: $(SETUP)
	@for sc in $(SCENES); do $(PTOVS) status --scene "$$sc" --data $(QDATA)/"$$sc"; done

clean-work:
	rm -rf $(QWORK)

# `make print-STAGES`, `make print-SCENES DATA=...`: what a variable holds
print-%:
	@echo $($*)
