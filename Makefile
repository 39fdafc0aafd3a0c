# Two-command quick start: `make demo` and `make test`. Each creates .venv when
# missing and installs what it needs, so a fresh clone with Python >= 3.11 and
# make is enough.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DEMO_OUT ?= out/demo

.PHONY: demo test lint format figures clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e ".[test,dev,figures]"
	touch $(STAMP)

# The main job: the smoother against the paper's Kalman filter (and the raw
# measurements, IPPE) on the paper's noisy scenario, 5 seeds: table + figures.
demo: $(STAMP)
	$(BIN)/python experiments/compare.py --quick --duration 10 --out-dir $(DEMO_OUT)
	$(BIN)/python experiments/paper_figures.py --out $(DEMO_OUT)/figures
	@echo "figures and tables: $(DEMO_OUT)/"

test: $(STAMP)
	$(BIN)/python -m pytest -q

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: $(STAMP)
	$(BIN)/ruff format .
	$(BIN)/ruff check --fix .

figures: $(STAMP)
	$(BIN)/python experiments/paper_figures.py --out docs/figures
	$(BIN)/python experiments/factor_graph_figure.py --out docs/figures
	$(BIN)/python experiments/compare.py --out-dir docs
	$(BIN)/python experiments/sweep.py
	$(BIN)/python experiments/generalization.py
	$(BIN)/python experiments/images.py
	$(BIN)/python experiments/benchmark.py

clean:
	rm -rf $(VENV) out .pytest_cache .ruff_cache
