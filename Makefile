# slamreplay: every target builds the virtualenv first when needed, so any of them
# works as the very first command on a fresh machine.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DATA   ?= ../shared/data
ARGS   ?=

.PHONY: venv demo serve test lint bench cholmod clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[dev]"
	@touch $(STAMP)

demo: $(STAMP)
	$(BIN)/slamreplay demo --data $(DATA) $(ARGS)

# The HTTP service on the built-in defaults: SQLite job store and local worker processes,
# uploads in recordings/, runs in runs/ (SLAMREPLAY_TOKEN, SLAMREPLAY_WORKERS... apply).
serve: $(STAMP)
	$(BIN)/slamreplay serve --data-dir . $(ARGS)

test: $(STAMP)
	$(BIN)/python -m pytest -n 2 -q $(ARGS)

lint: $(STAMP)
	$(BIN)/ruff check recorder replay algorithms api tests benchmarks

bench: $(STAMP)
	$(BIN)/python -m pip install --quiet -e ".[dev,bench]"
	$(BIN)/python benchmarks/replay_throughput.py
	$(BIN)/python benchmarks/posegraph.py --data $(DATA)
	$(BIN)/python benchmarks/registration.py

# Optional: CHOLMOD (SuiteSparse) for the pose-graph solver; without it SciPy's SuperLU is used.
cholmod: $(STAMP)
	@dpkg -s libsuitesparse-dev >/dev/null 2>&1 || apt-get install -y -q libsuitesparse-dev
	$(BIN)/python -m pip install --quiet -e ".[dev,cholmod]"

clean:
	rm -rf $(VENV) runs .pytest_cache .ruff_cache .hypothesis
