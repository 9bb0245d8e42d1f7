# slamreplay: every target builds the virtualenv first when needed, so any of them
# works as the very first command on a fresh machine.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
DATA   ?= ../shared/data
ARGS   ?=

.PHONY: venv demo serve test test-ray lint bench cholmod clean

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
	$(BIN)/python -m pytest -n 2 -q -m "not ray" $(ARGS)

# The Ray executor against a local Ray instance: installs the ray extra (about 20 s, 290 MB), then about
# a minute of tests, most of it Ray's start-up; apart from `make test` so that it needs no Ray. CI runs both.
test-ray: $(STAMP)
	$(BIN)/python -m pip install --quiet -e ".[dev,ray]"
	$(BIN)/python -m pytest -q -m ray tests/api/test_ray_executor.py tests/api/test_suite_cli.py $(ARGS)

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
