# Two entry points for a fresh machine (see README):
#   make repro   install into .venv, plan dvc.yaml from params.yaml (mapex plan), then run the whole pipeline
#                (mapex repro: dvc repro with independent stage items side by side, one per core)
#   make test    install into .venv, then run the test suite
# and `make lint` (ruff: lint and format check, configured in pyproject.toml), which CI runs first.
#
# The tests come in three tiers, chosen by pytest markers (registered in pyproject.toml):
#   make test-fast  the library-level tests, 1 to 2 min: everything but the files marked
#                   `integration` (a module-level pytestmark: DVC chains, stage commands in
#                   subprocesses one after another, long training) and the tests marked `slow`
#   make test       everything not marked slow (the integration files too), about 6.5 min
#   make test-slow  the tests marked slow (sweeps on a Ray cluster, the every-method DVC chain)
#   make test-kernels  the fast tier again under other CPU kernels than this machine's own
# CI (.ci/run) runs lint, test, test-kernels and test-slow. An unmarked new test file lands in the fast tier.
#
# torch: the CPU build is installed first, so nothing later pulls the multi-GB CUDA build.
# TORCH_SPEC and TORCH_INDEX choose another build, e.g. for a CUDA 12.8 machine:
#   make install TORCH_SPEC=torch==2.13.0 TORCH_INDEX=https://download.pytorch.org/whl/cu128
PYTHON ?= python3.11
VENV ?= .venv
TORCH_SPEC ?= torch==2.13.0
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu
BIN := $(VENV)/bin
# pytest-xdist workers for `make test`, one per core of the 2-core machines this project targets;
# each test file runs whole in one worker (--dist loadfile), so module fixtures are built once.
TEST_WORKERS ?= 2
# stage items side by side in `make repro` (0: one per core)
JOBS ?= 0

.PHONY: install repro test test-fast test-kernels test-slow lint format bench bench-speed clean-venv

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

install: $(BIN)/python
	@# torch alone first: a local wheel (pip's find-links) if there is one, else the PyTorch
	@# index named by TORCH_INDEX (CPU by default), never PyPI's CUDA default. Its own
	@# dependencies then come from the usual index together with the project's.
	$(BIN)/pip install -q --no-index --no-deps "$(TORCH_SPEC)" 2>/dev/null \
	  || $(BIN)/pip install -q --no-deps "$(TORCH_SPEC)" --index-url $(TORCH_INDEX)
	@# the core package only: `make repro` needs nothing more (test and bench add their extras)
	$(BIN)/pip install -q "$(TORCH_SPEC)" -e . > $(VENV)/install.log 2>&1 \
	  || { cat $(VENV)/install.log; echo "install failed (log: $(VENV)/install.log)"; exit 1; }

# dvc.yaml is planned from params.yaml's methods, variants, seeds and objectives: planned first,
# so editing params.yaml is all a user does before `make repro` (plain `dvc repro` needs
# `mapex plan` after such an edit; every stage names it when the plan is stale).
repro: install
	PATH="$(CURDIR)/$(BIN):$$PATH" mapex plan
	@# `dvc repro` runs one stage item at a time; `mapex repro` runs each item's `dvc repro
	@# --single-item` once its upstream is done, one per core (JOBS=1: plain dvc repro), so the
	@# two seeds' extractions, evaluations and scores share the cores (docs/manual.md, "Running")
	PATH="$(CURDIR)/$(BIN):$$PATH" mapex repro --jobs $(JOBS)

test: install
	@# the test tools (dev, with stable-baselines3) and the optional extras (Ray, morl-baselines,
	@# onnx), so tests/test_sweep.py, tests/test_morld.py and the ONNX export test run instead of skipping
	$(BIN)/pip install -q -e ".[dev,sweep,baselines,onnx]" >> $(VENV)/install.log 2>&1 \
	  || { cat $(VENV)/install.log; echo "install of .[dev,sweep,baselines,onnx] failed (log: $(VENV)/install.log)"; exit 1; }
	@# a headless browser for the explorer's tests (tests/test_explorer.py, tests/test_render.py:
	@# Playwright, from the dev extra, drives Debian's chromium, so it downloads no browser): installed
	@# with apt when missing and root, else those tests skip saying why
	@command -v chromium >/dev/null || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null \
	  && { apt-get install -y -q chromium || { apt-get update -q && apt-get install -y -q chromium; }; } \
	  >> $(VENV)/install.log 2>&1; } || echo "no chromium: the explorer's browser tests will skip"
	PATH="$(CURDIR)/$(BIN):$$PATH" python -m pytest -q -n $(TEST_WORKERS) --dist loadfile

# The fast tier: the same suite less the files marked integration (pyproject.toml's markers).
test-fast: install
	$(BIN)/pip install -q -e ".[dev,sweep,baselines,onnx]" >> $(VENV)/install.log 2>&1 \
	  || { cat $(VENV)/install.log; echo "install of .[dev,sweep,baselines,onnx] failed (log: $(VENV)/install.log)"; exit 1; }
	PATH="$(CURDIR)/$(BIN):$$PATH" python -m pytest -q -n $(TEST_WORKERS) --dist loadfile -m "not slow and not integration"

# The fast tier again, computed with other kernels than this CPU picks (.ci/other_kernels.py: an
# OpenBLAS core type it does not pick; torch's AVX2 paths where it has AVX-512): a test that pins
# one CPU's last bits fails here, on the developer's machine, before it fails on another. CI runs it.
test-kernels: install
	$(BIN)/pip install -q -e ".[dev,sweep,baselines,onnx]" >> $(VENV)/install.log 2>&1 \
	  || { cat $(VENV)/install.log; echo "install of .[dev,sweep,baselines,onnx] failed (log: $(VENV)/install.log)"; exit 1; }
	@echo "kernels: $$($(BIN)/python .ci/other_kernels.py)"
	env $$($(BIN)/python .ci/other_kernels.py) PATH="$(CURDIR)/$(BIN):$$PATH" \
	  python -m pytest -q -n $(TEST_WORKERS) --dist loadfile -m "not slow and not integration"

# The tests marked slow (sweeps on a Ray cluster, every method's stages through one DVC chain:
# about 4 minutes more), which `make test` leaves out to stay within 8 minutes; CI runs both.
test-slow: install
	$(BIN)/pip install -q -e ".[dev,sweep,baselines,onnx]" >> $(VENV)/install.log 2>&1 \
	  || { cat $(VENV)/install.log; echo "install of .[dev,sweep,baselines,onnx] failed (log: $(VENV)/install.log)"; exit 1; }
	PATH="$(CURDIR)/$(BIN):$$PATH" python -m pytest -q -n $(TEST_WORKERS) --dist loadfile -m slow

lint: install
	$(BIN)/pip install -q -e ".[dev]" >> $(VENV)/install.log 2>&1 \
	  || { cat $(VENV)/install.log; echo "install of .[dev] failed (log: $(VENV)/install.log)"; exit 1; }
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: install
	$(BIN)/pip install -q -e ".[dev]" >> $(VENV)/install.log 2>&1
	$(BIN)/ruff check --fix .
	$(BIN)/ruff format .

bench: install
	$(BIN)/pip install -q -e ".[bench]"
	$(BIN)/python benchmarks/bench_specialist.py
	$(BIN)/python benchmarks/bench_fit_critics.py
	$(BIN)/python benchmarks/bench_extract.py

# Issue 46's figures (children per iteration, evaluate in two processes): 3-5 min on an idle machine
bench-speed: install
	PYTHON=$(BIN)/python bash benchmarks/speed.sh

clean-venv:
	rm -rf $(VENV)
