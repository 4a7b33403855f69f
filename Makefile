# tofdenoise — set-up, training, tests and benchmarks.
# `make train` and `make test` bootstrap .venv themselves (re-built when pyproject.toml is newer).
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
# Reproducible installs: LOCK holds the exact version of every package of the venv (torch and its neighbours: the
# numbers of `make reproduce` depend on them), made by `make lock`; `make venv` installs through it (pip's constraints,
# PIP_CONSTRAINT). torch and triton are pinned there too but installed as TORCH / TRITON (default: the lock's), so a
# GPU user chooses another build; CONSTRAINTS= (empty) installs without pins, e.g. next to a CUDA torch whose own
# dependency pins differ from the lock's.
LOCK := requirements/constraints-cpu.txt
CONSTRAINTS ?= $(LOCK)
locked = $(shell sed -n 's/^$(1)==//p' $(LOCK))
# CPU build by default (no multi-GB CUDA download). GPU users: make TORCH="torch==2.11.0" ... or
# TORCH="torch --index-url <your CUDA wheel index>".
TORCH ?= torch==$(call locked,torch)
# Triton for the selective-scan kernels' tests in Triton's interpreter (TRITON_INTERPRET=1, CPU tensors); installed
# only next to a CPU torch on Linux x86-64 (a CUDA torch brings its own Triton).
TRITON ?= triton==$(call locked,triton)
PY := $(VENV)/bin/python
STAMP := $(VENV)/.tofdenoise-installed

# Training selections (Hydra config groups); ARGS takes any extra Hydra overrides.
BACKBONE ?=
NOISE ?=
LOSS ?=
DATA ?=
RUN_DIR ?=
ARGS ?=
PYTEST_ARGS ?=
# pytest-xdist workers of make test and make test-slow (2: the CI machine's cores; 0: one process)
PYTEST_WORKERS ?= 2
PYTEST_XDIST = -n $(PYTEST_WORKERS) --dist worksteal
BENCH_ARGS ?=

export PYTHONUNBUFFERED := 1

.PHONY: help venv lock train test test-slow probe lint format docs bench robustness realset reproduce reproduce-check cli-configs clean

help:
	@echo "make train   - small default training on built-in procedural scenes (CPU)"
	@echo "               BACKBONE=dvss NOISE=hetero LOSS=full DATA=procedural RUN_DIR=path ARGS='hydra overrides'"
	@echo "make test    - run the test suite (slow experiments excluded)"
	@echo "make test-slow - run the slow experiments too"
	@echo "make probe   - the reliability probes: every family of fault against every command, slow cases included"
	@echo "               (signals, a real full tmpfs where root allows it; docs/reliability.md)"
	@echo "make lint    - ruff lint + format check (CI runs it before the tests); make format applies both"
	@echo "make docs    - the documentation site with the API reference, built strict into site/ (open site/index.html)"
	@echo "make bench   - side-by-side performance measurements (see docs/benchmarks.md); BENCH_ARGS=--quick"
	@echo "make robustness - the robustness grid (108 small runs, resumable; GRID_DIR=runs/robustness GRID_ARGS=...)"
	@echo "make realset - the stand-in real set: a second simulated camera, calibrated from its own captures"
	@echo "               (200 scenes, one per CPU core at a time; REALSET_DIR=runs/realset REALSET_ARGS='--workers 4 ...')"
	@echo "make reproduce TABLE=1|2|3 | FIGURE=6|7|8 | STUDY=dynrange|schedule|dataseed [PROFILE=cpu|gpu|gpu-short] [SEEDS=0,1,2] - a paper table,"
	@echo "               figure or study (resumable; records in docs/results/, page docs/results.md;"
	@echo "               REPRO_ARGS='--extra data.source_kwargs.root=...')"
	@echo "make reproduce-check [PROFILE=cpu] [CHECK='3 dynrange'] - rerun one small recorded run per table at this"
	@echo "               commit and compare it with its record within a stated tolerance (docs/results.md)"
	@echo "make cli-configs - regenerate the LightningCLI YAMLs (configs/cli/) after editing configs/"
	@echo "make venv    - only create/refresh .venv (TORCH='torch==X' to choose the torch build)"
	@echo "make lock    - refresh $(LOCK) (exact versions make venv installs) from a fresh venv"

venv: $(STAMP)

# every pip install of the venv goes through the lock (less the torch and triton lines: TORCH / TRITON choose those)
$(STAMP): export PIP_CONSTRAINT = $(abspath $(VENV))/constraints.txt
$(STAMP): pyproject.toml $(CONSTRAINTS)
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@if [ -n "$(CONSTRAINTS)" ]; then grep -v -E '^(torch|triton)==' "$(CONSTRAINTS)"; fi > $(VENV)/constraints.txt
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet "$(TORCH)"
	$(PY) -m pip install --quiet -e ".[dev,onnx,recordings,cluster,docs,launchers]"
	$(PY) -m pip install --quiet -e ".[sweep]"
	@if $(PY) -c "import platform, sys, torch; sys.exit(not (torch.version.cuda is None and sys.platform == 'linux' and platform.machine() == 'x86_64'))"; then \
		$(PY) -m pip install --quiet "$(TRITON)"; fi
	@touch $(STAMP)

# The lock, refreshed: a throw-away venv built by `make venv` without pins (the newest versions pyproject.toml allows;
# torch and triton: TORCH / TRITON, default the lock's own, e.g. make lock TORCH=torch==2.14.0), frozen into $(LOCK).
# Python 3.11 on Linux x86-64, as the CI; review the diff, run make test, commit the file.
LOCK_VENV ?= .venv-lock
lock:
	rm -rf $(LOCK_VENV)
	$(MAKE) --no-print-directory venv VENV=$(LOCK_VENV) CONSTRAINTS= TORCH="$(TORCH)" TRITON="$(TRITON)"
	@mkdir -p $(dir $(LOCK))
	{ echo "# Exact versions of the venv \`make venv\` builds (it installs through this file); refresh: make lock."; \
	  echo "# Made $$(date -u +%Y-%m-%d) by make lock: $$($(LOCK_VENV)/bin/python -V), $$(uname -sm), $(TORCH)."; \
	  $(LOCK_VENV)/bin/python -m pip freeze --exclude-editable | sed -E 's/^(torch==[^+]*)\+.*/\1/'; } > $(LOCK).tmp
	mv $(LOCK).tmp $(LOCK)
	rm -rf $(LOCK_VENV)

train: $(STAMP)
	$(VENV)/bin/tofdenoise train \
		$(if $(BACKBONE),backbone=$(BACKBONE)) \
		$(if $(NOISE),noise=$(NOISE)) \
		$(if $(LOSS),loss=$(LOSS)) \
		$(if $(DATA),data=$(DATA)) \
		$(if $(RUN_DIR),paths.run_dir=$(RUN_DIR)) \
		$(ARGS)

test: $(STAMP)
	$(PY) -m pytest $(PYTEST_XDIST) $(PYTEST_ARGS)

test-slow: $(STAMP)
	$(PY) -m pytest -m "slow" $(PYTEST_XDIST) $(PYTEST_ARGS)

# The reliability probes (tests/reliability, docs/reliability.md) with their slow cases, and the mid-epoch resume pin;
# `make test` runs the fast ones
probe: $(STAMP)
	$(PY) -m pytest tests/reliability tests/training/test_mid_epoch_resume.py -m "not gpu" $(PYTEST_ARGS)

lint: $(STAMP)
	$(VENV)/bin/ruff check src tests benchmarks docs/_ext
	$(VENV)/bin/ruff format --check src tests benchmarks docs/_ext

format: $(STAMP)
	$(VENV)/bin/ruff check --fix src tests benchmarks docs/_ext
	$(VENV)/bin/ruff format src tests benchmarks docs/_ext

# The documentation site (mkdocs.yml): docs/*.md and the API reference generated from the docstrings, into site/.
# Strict: a broken link or a docstring that drifts from its signature fails (tests/test_docs.py runs the same build)
docs: $(STAMP)
	$(VENV)/bin/mkdocs build --strict --site-dir site

bench: $(STAMP)
	$(PY) benchmarks/run_all.py $(BENCH_ARGS)

# Does the default recipe learn for every backbone x noise x loss x seed x camera? Finished runs are skipped,
# interrupted ones resume; the table goes to the terminal and to $(GRID_DIR)/robustness.md.
GRID_DIR ?= runs/robustness
GRID_ARGS ?=
robustness: $(STAMP)
	$(VENV)/bin/tofdenoise grid robustness --out $(GRID_DIR) --markdown $(GRID_DIR)/robustness.md $(GRID_ARGS)

# The stand-in real set (docs/camera-tutorial.md): camera cam75's calibration captures -> calibrate ->
# $(REALSET_DIR)/calibration.yaml, and its capture set with mixed pixels -> $(REALSET_DIR)/captures. Then:
#   tofdenoise train ++data.sensor=$(REALSET_DIR)/calibration.yaml ++data.real_dir=$(REALSET_DIR)/captures
REALSET_DIR ?= runs/realset
REALSET_ARGS ?=
realset: $(STAMP)
	$(VENV)/bin/tofdenoise sensor realset --out $(REALSET_DIR) $(REALSET_ARGS)

# The paper's tables and figures and the studies beyond it (docs/results.md): one of TABLE=1|2|3, FIGURE=6|7|8 or
# STUDY=dynrange|schedule|dataseed. Finished runs are skipped, interrupted ones resume, failures are listed.
TABLE ?=
FIGURE ?=
STUDY ?=
PROFILE ?= cpu
SEEDS ?= 0,1,2
REPRO_ARGS ?=
comma := ,
repro_target = $(if $(TABLE),--table $(TABLE)) $(if $(FIGURE),--figure $(FIGURE)) $(if $(STUDY),--study $(STUDY))
reproduce: $(STAMP)
	@test $(words $(repro_target)) -eq 2 || { echo "make reproduce: set one of TABLE=1|2|3, FIGURE=6|7|8 or STUDY=dynrange|schedule|dataseed (e.g. make reproduce TABLE=3)"; exit 2; }
	$(VENV)/bin/tofdenoise reproduce $(repro_target) --profile $(PROFILE) --seeds $(subst $(comma), ,$(SEEDS)) $(REPRO_ARGS)

# Do the committed records reproduce at this commit? One small recorded run per table (CHECK= a subset: 1 2 3
# dynrange), rerun under runs/reproduce-check/<profile> and compared with its record; exit 1 when one does not
CHECK ?=
reproduce-check: $(STAMP)
	$(VENV)/bin/tofdenoise reproduce --check $(CHECK) --profile $(PROFILE) $(REPRO_ARGS)

# configs/cli/*.yaml are generated from the Hydra configs (one source of truth); a test fails when they are stale
cli-configs: $(STAMP)
	$(PY) -m tofdenoise.cli.export_cli_config

clean:
	rm -rf $(VENV) $(LOCK_VENV) .pytest_cache build site *.egg-info src/*.egg-info
