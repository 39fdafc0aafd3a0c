# Two-command quick start: `make demo` and `make test`. Each creates .venv when
# missing and installs what it needs, so a fresh clone with Python >= 3.11 and
# make is enough.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DEMO_OUT ?= out/demo

.PHONY: help demo test lint format figures clean
.DEFAULT_GOAL := help

# Each target's line carries its "## description"; help lists them.
help: ## list the targets with what each does
	@awk 'BEGIN {FS = ":.*## "} /^[a-z][a-z-]*:.*## / {printf "  make %-8s %s\n", $$1, $$2}' $(MAKEFILE_LIST)

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e ".[test,dev,figures]"
	touch $(STAMP)

# The main job: the smoother against the paper's Kalman filter (and the raw
# measurements, IPPE) on the paper's noisy scenario, 5 seeds: table + figures.
demo: $(STAMP) ## the smoother against the paper's Kalman filter: table and figures in out/demo/
	$(BIN)/python experiments/compare.py --quick --duration 10 --out-dir $(DEMO_OUT)
	$(BIN)/python experiments/paper_figures.py --out $(DEMO_OUT)/figures
	@echo "figures and tables: $(DEMO_OUT)/"

test: $(STAMP) ## run the test suite (creates .venv and installs on first use)
	$(BIN)/python -m pytest -q

lint: $(STAMP) ## ruff check and format check
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: $(STAMP) ## ruff format and fix
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

figures: $(STAMP) ## regenerate docs/figures and the experiment tables (long)
	$(BIN)/python experiments/paper_figures.py --out docs/figures
	$(BIN)/python experiments/factor_graph_figure.py --out docs/figures
	$(BIN)/python experiments/compare.py --out-dir docs
	$(BIN)/python experiments/sweep.py
	$(BIN)/python experiments/generalization.py
	$(BIN)/python experiments/images.py
	$(BIN)/python experiments/benchmark.py

clean: ## remove .venv, out/ and caches
	rm -rf $(VENV) out .pytest_cache .ruff_cache
