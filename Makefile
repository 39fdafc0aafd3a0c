# Two-command quick start: `make demo` and `make test`. Each creates .venv when
# missing and installs what it needs, so a fresh clone with Python >= 3.11 and
# make is enough.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DEMO_OUT ?= out/demo

.PHONY: help demo test lint format figures clean realdata
.DEFAULT_GOAL := help

# Each target's line carries its "## description"; help lists them.
help: ## list the targets with what each does
	@awk 'BEGIN {FS = ":.*## "} /^[a-z][a-z-]*:.*## / {printf "  make %-8s %s\n", $$1, $$2}' $(MAKEFILE_LIST)

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# Byte-compiled once: where PYTHONDONTWRITEBYTECODE is set (containers, CI) every
# command would otherwise compile the package again (~0.1 s per command).
$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install --quiet -e ".[test,dev,figures]"
	$(BIN)/python -m compileall -q hvo_graph
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

# The figure scripts are independent: `make figures` runs them FIGURES_JOBS at a time,
# the longest (the serial benchmark) first, so the cores stay busy: the Monte Carlo
# scripts spread their seeds over every core (or FIGURES_WORKERS processes) and take
# the core the benchmark leaves. The benchmark's cost curve is in CPU time per call,
# which the shared cores barely bend. Output lines are kept whole; no progress bars.
FIGURES_JOBS ?= 2
FIGURES_WORKERS ?=
WORKERS = $(if $(FIGURES_WORKERS),--workers $(FIGURES_WORKERS))
FIGURE_JOBS := figure-benchmark figure-compare figure-sweep figure-generalization \
	figure-images figure-paper figure-graph
.PHONY: $(FIGURE_JOBS)

figures: $(STAMP) ## regenerate docs/figures and the experiment tables (long; jobs in parallel)
	$(MAKE) --no-print-directory -j$(FIGURES_JOBS) --output-sync=line $(FIGURE_JOBS)

figure-benchmark: $(STAMP)
	$(BIN)/python experiments/benchmark.py
figure-compare: $(STAMP)
	$(BIN)/python experiments/compare.py --out-dir docs $(WORKERS) --no-progress
figure-sweep: $(STAMP)
	$(BIN)/python experiments/sweep.py --out-dir docs $(WORKERS) --no-progress
figure-generalization: $(STAMP)
	$(BIN)/python experiments/generalization.py --out-dir docs $(WORKERS) --no-progress
figure-images: $(STAMP)
	$(BIN)/python experiments/images.py --out-dir docs --no-progress
figure-paper: $(STAMP)
	$(BIN)/python experiments/paper_figures.py --out docs/figures
figure-graph: $(STAMP)
	$(BIN)/python experiments/factor_graph_figure.py --out docs/figures

# Real images for the tests (not in the repository): OpenCV's sample data from Debian's
# opencv-doc package (Apache-2.0 / BSD-3-Clause; its copyright file is copied along):
# 13 views of a 9x6 chessboard with left_intrinsics.yml, and graf1/graf3 with H1to3p.xml.
REALDATA := data/real/opencv
REALDATA_FILES := left01.jpg left02.jpg left03.jpg left04.jpg left05.jpg left06.jpg \
	left07.jpg left08.jpg left09.jpg left11.jpg left12.jpg left13.jpg left14.jpg \
	left_intrinsics.yml graf1.png graf3.png H1to3p.xml

realdata: $(REALDATA)/H1to3p.xml ## fetch OpenCV's real sample images for the tests (apt-get download)

$(REALDATA)/H1to3p.xml:
	@command -v apt-get >/dev/null && command -v dpkg >/dev/null || \
		{ echo "realdata: needs apt-get and dpkg (Debian or Ubuntu) to fetch opencv-doc"; exit 1; }
	rm -rf data/real/.fetch && mkdir -p data/real/.fetch $(REALDATA)
	cd data/real/.fetch && apt-get download opencv-doc
	dpkg -x data/real/.fetch/opencv-doc_*.deb data/real/.fetch/x
	for f in $(REALDATA_FILES); do \
		cp data/real/.fetch/x/usr/share/doc/opencv-doc/examples/data/$$f $(REALDATA)/ || exit 1; \
	done
	cp data/real/.fetch/x/usr/share/doc/opencv-doc/copyright $(REALDATA)/COPYRIGHT
	rm -rf data/real/.fetch

clean: ## remove .venv, out/ and caches
	rm -rf $(VENV) out .pytest_cache .ruff_cache
