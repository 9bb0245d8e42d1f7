# slamreplay: every target builds the virtualenv first when needed, so any of them
# works as the very first command on a fresh machine. Python 3.10 to 3.13 (PYTHON=... picks one).
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
# The interpreter's version is part of the stamp: a .venv made by another interpreter (a failed
# attempt with an old Python, or PYTHON=... changed) is rebuilt, never silently reused.
PY_VERSION := $(shell $(PYTHON) -c 'import sys; print("%d.%d.%d" % sys.version_info[:3])' 2>/dev/null)
STAMP  := $(VENV)/.installed-py$(PY_VERSION)
DATA   ?= ../shared/data
ARGS   ?=

.PHONY: venv demo serve test test-ray test-docs test-pythons test-viewer test-browser snapshots readme-figures fuzz viewer-deps lint bench cholmod clean
.PHONY: examples test-examples

venv: $(STAMP)

$(STAMP): pyproject.toml
	@test -n "$(PY_VERSION)" || { echo "make: '$(PYTHON)' does not run: install Python 3.10-3.13 or pass PYTHON=/path/to/python3"; exit 2; }
	@$(PYTHON) -c 'import sys; sys.exit(sys.version_info[:2] < (3, 10))' || { echo "make: $(PYTHON) is Python $(PY_VERSION); slamreplay needs 3.10 to 3.13: pass PYTHON=/path/to/python3.X"; exit 2; }
	@if test -x $(BIN)/python && test "$$($(BIN)/python -c 'import sys; print("%d.%d.%d" % sys.version_info[:3])' 2>/dev/null)" != "$(PY_VERSION)"; then \
		echo "$(VENV) was made by another Python; rebuilding it with $(PYTHON) ($(PY_VERSION))"; rm -rf $(VENV); fi
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e ".[dev]"
	@rm -f $(VENV)/.installed*
	@touch $(STAMP)
	@echo "$(VENV) is ready (Python $(PY_VERSION)). To type slamreplay and rerun without the $(BIN)/ prefix: source $(BIN)/activate"

demo: $(STAMP)
	@echo "Tip: source $(BIN)/activate puts slamreplay and rerun on your PATH; without it, type $(BIN)/slamreplay and $(BIN)/rerun"
	$(BIN)/slamreplay demo --data $(DATA) $(ARGS)

# The HTTP service on the built-in defaults: SQLite job store and local worker processes,
# uploads in recordings/, runs in runs/ (SLAMREPLAY_TOKEN, SLAMREPLAY_WORKERS... apply).
serve: $(STAMP)
	$(BIN)/slamreplay serve --data-dir . $(ARGS)

test: $(STAMP)
	$(BIN)/python -m pytest -n 2 -q -m "not ray and not docs and not viewer and not browser" $(ARGS)

# The compiled external-pipeline example (docs/external.md), built with Debian's C compiler: installed with
# apt-get when there is none, as test-browser installs chromium. test-examples runs its tests with it.
EXAMPLE_C := examples/external_c/build/deadreckon
examples: $(EXAMPLE_C)

$(EXAMPLE_C): examples/external_c/deadreckon.c
	@command -v cc >/dev/null || { apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q gcc libc6-dev; }
	mkdir -p $(dir $@)
	cc -O2 -std=c99 -Wall -Wextra -o $@ $< -lm

test-examples: $(STAMP) examples
	$(BIN)/python -m pytest -q tests/replay/test_external_examples.py $(ARGS)

# The headless Rerun viewer draws with Vulkan; without a GPU, Mesa's software rasterizer (lavapipe).
VIEWER_DEBS := mesa-vulkan-drivers libvulkan1 libegl1
viewer-deps:
	@dpkg -s $(VIEWER_DEBS) >/dev/null 2>&1 || { apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q $(VIEWER_DEBS); }

# Runs drawn by the real Rerun viewer: orientation from pixels, no blank view in any pipeline (about 2 min).
test-viewer: $(STAMP) viewer-deps
	$(BIN)/python -m pytest -q -m viewer tests/viewer $(ARGS)

# The web page in a real browser: Debian's headless chromium driven by Playwright for Python (the
# browser extra; PLAYWRIGHT_SKIP_BROWSER_DOWNLOAD: Playwright's own browser download is never used).
# Upload, a job, a regression in red, the Rerun web viewer loading a job's .rrd; every page at laptop and
# phone size (axe-core scan, console errors, sideways scroll); the API docs offline (about 2 min on 2 cores).
# Screenshots of every page at both sizes go to WEB_SHOTS (CI keeps them); README_IMAGES=docs/images also
# rewrites the README's screenshots of the web page.
WEB_SHOTS ?= results/web-shots
test-browser: $(STAMP)
	@test -x /usr/bin/chromium || { apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium; }
	PLAYWRIGHT_SKIP_BROWSER_DOWNLOAD=1 $(BIN)/python -m pip install --quiet -e ".[dev,browser]"
	rm -rf $(WEB_SHOTS)
	SLAMREPLAY_BROWSER_SHOTS=$(abspath $(WEB_SHOTS)) SLAMREPLAY_README_IMAGES=$(if $(README_IMAGES),$(abspath $(README_IMAGES))) \
		$(BIN)/python -m pytest -q -m browser tests/web $(ARGS); status=$$?; \
		echo "screenshots of every page at 1366x768 and 390x844 (page-*.png): $(WEB_SHOTS)/"; exit $$status

# The figures README.md and docs/ quote from the demo (<!-- demo: ... --> spans), rewritten from a fresh demo's
# runs in runs/demo (docs/demo_figures.py); `make test-docs` fails when one differs from a fresh demo.
readme-figures: $(STAMP)
	$(BIN)/slamreplay demo --out runs/demo --data $(DATA)
	$(BIN)/python docs/demo_figures.py --demo runs/demo --write

# The README's viewer pictures: every demo pipeline and a diff, rendered by `slamreplay snapshot` into docs/images/
# from a fresh demo of a commit (HEAD, or REV=...; exported, so the work tree never reaches a picture), each with
# its record in docs/images/pictures.json (commit, sha256, the metrics it shows), which `make test-docs` checks.
# With the public datasets in DATA, also the pictures of docs/real-data.md (MRCLAM's five robots, Victoria Park).
# About 4 minutes on 2 cores, 11 with the datasets. WHAT=all (or web) also takes the web page's pictures with the
# browser tests (chromium and Playwright, as make test-browser installs them; 2 more minutes). The compare and
# history reports' pictures: bash docs/make_compare_report.sh, bash docs/make_history_report.sh.
REV ?= HEAD
WHAT ?= viewer
snapshots: $(STAMP) viewer-deps
	$(BIN)/python docs/make_snapshots.py --out docs/images --rev $(REV) --what $(WHAT) $(if $(wildcard $(DATA)),--data $(DATA)) $(ARGS)

# The Ray executor against a local Ray instance: installs the ray extra (about 20 s, 290 MB), then about
# a minute of tests, most of it Ray's start-up; apart from `make test` so that it needs no Ray. CI runs both.
test-ray: $(STAMP)
	$(BIN)/python -m pip install --quiet -e ".[dev,ray]"
	$(BIN)/python -m pytest -q -m ray tests/api/test_ray_executor.py tests/api/test_suite_cli.py $(ARGS)

# Every ```sh/```bash/```console/```python block of README.md and docs/*.md, run in a fresh copy of the repository
# with $(BIN) on PATH (tests/test_readme.py); blocks marked <!-- docs-test: skip (why) --> are reported. Then the
# figures and pictures against one fresh demo, and every linked picture against its record (tests/test_docs_pictures.py).
test-docs: $(STAMP)
	$(BIN)/python -m pytest -q -m docs tests/test_readme.py tests/test_docs_pictures.py $(ARGS)

# The oldest and newest supported Pythons (3.10, 3.13), each in its own .venv-3.X: found as
# python3.X on PATH or a pyenv install (or PYTHON_3_10=/path...); one that is missing is skipped
# with a message. In each: the suite but its slow tests (PYTHONS_TESTS, about 4 min); on 3.10 also the
# README's blocks (about 3 min: 3.10 has rerun-sdk 0.39, the others 0.41 as make test-docs runs them); then the
# same cells run under both must pass `slamreplay diff` (.ci/cross-python-diff.sh, about 2 min). About 17 minutes
# in all on 2 cores.
PYTHONS_TESTS ?= -m "not ray and not docs and not slow and not viewer and not browser"
test-pythons:
	@found=""; for v in 3.10 3.13; do \
		py=""; for c in "$$(eval echo \$${PYTHON_$$(echo $$v | tr . _)})" python$$v \
			$$(ls -d $${PYENV_ROOT:-$$HOME/.pyenv}/versions/$$v.*/bin/python$$v 2>/dev/null | sort -rV); do \
			if [ -n "$$c" ] && "$$c" -c 'import sys; sys.exit(sys.version_info[:2] != tuple(map(int, "'$$v'".split("."))))' 2>/dev/null; \
			then py=$$(command -v "$$c"); break; fi; done; \
		if [ -z "$$py" ]; then echo "test-pythons: Python $$v not found (python$$v on PATH, a pyenv install, or PYTHON_$$(echo $$v | tr . _)=...): skipped"; continue; fi; \
		echo "test-pythons: Python $$v at $$py"; \
		$(MAKE) --no-print-directory venv VENV=.venv-$$v PYTHON=$$py || exit 1; \
		.venv-$$v/bin/python -m pytest -n 2 -q $(PYTHONS_TESTS) $(ARGS) || exit 1; \
		if [ "$$v" = 3.10 ]; then .venv-$$v/bin/python -m pytest -q -m docs tests/test_readme.py || exit 1; fi; \
		found="$$found .venv-$$v"; \
	done; \
	set -- $$found; if [ $$# -eq 2 ]; then .ci/cross-python-diff.sh $$1 $$2 || exit 1; \
	else echo "test-pythons: the cross-interpreter diff needs both 3.10 and 3.13: skipped"; fi

# Coverage-guided fuzzing (atheris, the fuzz extra) of every byte parser, one harness after the other, each
# for a fifth of FUZZ_SECONDS from its stored seed corpus: the MCAP reader, inspect and recover
# (tests/fuzz/harness_mcap.py), suite files (harness_suite.py), form uploads (harness_upload.py), ROS 2 bags
# (harness_ros2bag.py) and the dataset importers: MRCLAM, Victoria Park, image folders (harness_datasets.py).
# New inputs go to FUZZ_DIR/<harness> (the committed corpus is read only, never written), findings to
# FUZZ_DIR/<harness>-crash-* (then store them as cases); the first finding fails the run.
# FUZZ_RUNS=N instead runs N inputs per harness from seed FUZZ_SEED: the same inputs on every machine, which is
# what CI runs (a time budget explores a different path on a faster machine, and a CI run must be repeatable).
FUZZ_SECONDS ?= 1800
FUZZ_DIR ?= /tmp/slamreplay-fuzz
FUZZ_SEED ?= 0
FUZZ_HARNESSES := mcap suite upload ros2bag datasets
FUZZ_EACH = $(shell expr $(FUZZ_SECONDS) / 5)
# With FUZZ_RUNS, harness h runs FUZZ_RUNS x its weight inputs (the weights even out their speeds: the ROS 2 bag
# harness opens two bags per input, 15/s; the dataset importers write a folder and a recording, about 1,000/s; the
# suite parser runs 13,000/s).
FUZZ_LIMIT = $(if $(FUZZ_RUNS),-runs=$(shell expr $(FUZZ_RUNS) \* $(2)) -seed=$(or $(filter-out 0,$(FUZZ_SEED)),1),\
	-max_total_time=$(FUZZ_EACH) $(if $(filter-out 0,$(FUZZ_SEED)),-seed=$(FUZZ_SEED)))
FUZZ_RUN = nice -n 10 $(BIN)/python tests/fuzz/harness_$(1).py $(call FUZZ_LIMIT,$(1),$(2)) \
	-artifact_prefix=$(FUZZ_DIR)/$(1)- $(3) $(FUZZ_DIR)/$(1) tests/fuzz/corpus/$(1)
fuzz: $(STAMP)
	$(BIN)/python -m pip install --quiet -e ".[dev,fuzz]"
	$(if $(FUZZ_RUNS),rm -rf $(addprefix $(FUZZ_DIR)/,$(FUZZ_HARNESSES)))
	@mkdir -p $(addprefix $(FUZZ_DIR)/,$(FUZZ_HARNESSES))
	$(call FUZZ_RUN,mcap,40,-timeout=20 -rss_limit_mb=4096 -max_len=65536)
	$(call FUZZ_RUN,suite,100,-timeout=10 -rss_limit_mb=2048 -max_len=4096 -dict=tests/fuzz/suite.dict)
	$(call FUZZ_RUN,upload,40,-timeout=10 -rss_limit_mb=2048 -max_len=8192)
	$(call FUZZ_RUN,ros2bag,1,-timeout=20 -rss_limit_mb=3072 -max_len=65536)
	$(call FUZZ_RUN,datasets,40,-timeout=20 -rss_limit_mb=3072 -max_len=16384 -dict=tests/fuzz/datasets.dict)

lint: $(STAMP)
	$(BIN)/ruff check recorder replay algorithms api tests benchmarks examples

# Benchmarks against the peers (bench extra), each writing --json into BENCH_DIR, then one table of
# ratios against issue 17's targets (benchmarks/summary.py; the README's performance table).
# About 10 minutes on 2 cores; `make bench QUICK=1` takes the short path of replay and pose graph (about 5).
BENCH_DIR ?= results/bench
bench: $(STAMP)
	$(BIN)/python -m pip install --quiet -e ".[dev,bench]"
	@mkdir -p $(BENCH_DIR)
	nice $(BIN)/python benchmarks/replay_throughput.py $(if $(QUICK),--quick) --json $(BENCH_DIR)/replay_throughput.json
	nice $(BIN)/python benchmarks/posegraph.py --data $(DATA) $(if $(QUICK),--quick) --json $(BENCH_DIR)/posegraph.json
	nice $(BIN)/python benchmarks/loop_closure.py --json $(BENCH_DIR)/loop_closure_sim.json
	nice $(BIN)/python benchmarks/loop_closure.py --rtabmap $(DATA)/rtabmap-loop-samples --json $(BENCH_DIR)/loop_closure_rtabmap.json
	$(if $(QUICK),,nice $(BIN)/python benchmarks/registration.py)
	@echo; $(BIN)/python benchmarks/summary.py $(BENCH_DIR)

# Optional: CHOLMOD (SuiteSparse) through scikit-sparse for the pose-graph solver; without it CVXOPT's CHOLMOD
# (the solver extra) or QDLDL (a core dependency) is used.
cholmod: $(STAMP)
	@dpkg -s libsuitesparse-dev >/dev/null 2>&1 || apt-get install -y -q libsuitesparse-dev
	$(BIN)/python -m pip install --quiet -e ".[dev,cholmod]"

clean:
	rm -rf $(VENV) .venv-3.* runs .pytest_cache .ruff_cache .hypothesis
