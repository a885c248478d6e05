# twinrl: `make demo` and `make test` do the whole set-up on a fresh machine.
SHELL := /bin/bash
.DEFAULT_GOAL := help

VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
SYSTEM_PACKAGES := libusb-1.0-0 libegl1 libgl1 libosmesa6
# The web viewer's tests drive a real headless browser: installed where root can, else
# those tests skip and say why.
BROWSER_PACKAGES := chromium chromium-driver
# Python 3.12: on PATH, or through pyenv (.python-version pins it).
PYTHON ?= $(shell command -v python3.12 >/dev/null 2>&1 && python3.12 -c 'import sys' 2>/dev/null && echo python3.12 || echo "env PYENV_VERSION=3.12.1 python3.12")
export MUJOCO_GL ?= egl

.PHONY: help setup system-libs test test-slow test-long demo bench docs lint clean

help:
	@echo "make demo   set up, run every task's scripted expert in the twin and the plant, record,"
	@echo "            index, query, curate a LeRobot dataset and save a Rerun recording under out/demo;"
	@echo "            then the whole TwinRL pipeline against its baselines (twinrl demo --preset quick,"
	@echo "            about 20 min) with its report in out/twinrl_demo/report.md"
	@echo "make test   set up, then lint and run the test suite (all but the slow end-to-end runs)"
	@echo "make test-slow  set up, then run the slow end-to-end tests (CI runs both)"
	@echo "make test-long  set up, then run the runs too long for CI (gap, builds, image RL)"
	@echo "make bench  set up, then run the benchmarks"
	@echo "make docs   set up, then build the documentation site into build/site (warnings are errors)"

setup: system-libs $(STAMP)

# Installs missing system libraries when run as root; otherwise prints the command.
system-libs:
	@command -v dpkg >/dev/null 2>&1 || { echo "note: not a Debian system; make sure these are installed: $(SYSTEM_PACKAGES)"; exit 0; }; \
	missing=""; for pkg in $(SYSTEM_PACKAGES); do dpkg -s $$pkg >/dev/null 2>&1 || missing="$$missing $$pkg"; done; \
	if [ -z "$$missing" ]; then exit 0; fi; \
	if [ "$$(id -u)" = 0 ]; then \
		echo "installing system libraries:$$missing"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq$$missing >/dev/null; \
	else \
		echo "missing system libraries:$$missing"; \
		echo "install them with: sudo apt-get install -y$$missing"; exit 1; \
	fi
	@command -v dpkg >/dev/null 2>&1 || exit 0; \
	missing=""; for pkg in $(BROWSER_PACKAGES); do dpkg -s $$pkg >/dev/null 2>&1 || missing="$$missing $$pkg"; done; \
	if [ -z "$$missing" ]; then exit 0; fi; \
	if [ "$$(id -u)" = 0 ]; then \
		echo "installing the browser tests' browser:$$missing"; \
		apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq$$missing >/dev/null; \
	else \
		echo "note: the web viewer's browser tests will skip; install their browser with: sudo apt-get install -y$$missing"; \
	fi

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; assert sys.version_info[:2] >= (3, 12)' 2>/dev/null || \
		{ echo "Python 3.12 is required: install it (e.g. pyenv install 3.12) or set PYTHON=/path/to/python3.12"; exit 1; }
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	@touch $(STAMP)

# The suite runs on every core, a test file per worker, each worker on one thread (torch
# and OpenMP threads of two workers on two cores fight: 9.2 min against 6.3); the tests
# that keep real time against an emulated controller run after it, alone. Each prints its
# slowest tests, to keep the suite within CI's time. The emulator, its controller link and
# the test fill both cores of a 2-core host, where a real-time bound fails now and then
# (a different one in each of the last three runs): such a test runs up to twice more,
# and each rerun is listed in the summary (RERUN) so that a flake stays seen.
PARALLEL := OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 $(BIN)/pytest -n auto --dist loadfile
REALTIME := $(BIN)/pytest -q -rfER --reruns 2 --reruns-delay 1
test: setup
	$(BIN)/ruff check .
	$(PARALLEL) -q --durations=15 -m "not slow and not realtime and not long"
	$(REALTIME) --durations=10 -m "realtime and not slow and not long"

# The end-to-end runs marked slow (about 5 minutes more on 2 cores); CI runs them after
# `make test`: on every core, then those that keep real time (timed kills among them)
# alone. Those marked long as well run beyond CI's 30 minutes: `make test-long` runs them.
test-slow: setup
	$(PARALLEL) -q -m "slow and not realtime and not long"
	$(REALTIME) -m "slow and realtime and not long"

# The runs too long for CI (about 9 minutes on 2 cores), and the driver excitation's gap
# diagnosis, a known failure (about 1.5 minutes more): before a release, or when the gap
# workflow, the object builds or the image policy's RL change.
test-long: setup
	$(PARALLEL) -q -m "long and not realtime"
	$(REALTIME) -m "long and realtime"

DEMO := out/demo
demo: setup
	$(BIN)/twinrl sim expert all --world twin --world plant --episodes 10
	@rm -rf $(DEMO)   # the demo's own output from a previous run
	$(BIN)/twinrl sim expert all --world twin --world plant --episodes 1 --out $(DEMO)/session
	$(BIN)/twinrl data index $(DEMO)/session --catalog $(DEMO)/catalog.parquet
	$(BIN)/twinrl data query --catalog $(DEMO)/catalog.parquet --task pick_place
	$(BIN)/twinrl data curate --catalog $(DEMO)/catalog.parquet --task pick_place --to $(DEMO)/datasets/pick_place
	$(BIN)/twinrl view $(DEMO)/session#0 $(DEMO)/session#2 --save $(DEMO)/pick_place_twin_vs_plant.rrd
	@echo "open the recording with: $(BIN)/rerun $(DEMO)/pick_place_twin_vs_plant.rrd"
	@rm -rf out/twinrl_demo   # the pipeline's own output from a previous run
	$(BIN)/twinrl demo --task pick_place --preset quick --out out/twinrl_demo

bench: setup
	$(BIN)/python bench/bench_batch.py --episodes 32 --steps 60
	$(BIN)/python bench/bench_data.py --episodes 4 --steps 100
	MUJOCO_GL=egl $(BIN)/python bench/bench_recording.py --duration 60 --episode-seconds 30 --compare-seconds 20
	$(BIN)/python bench/bench_expand.py --task insert_hexagon --demos 90
	$(BIN)/python bench/bench_gap.py --episodes 20 --duration 10
	$(BIN)/python bench/bench_reconstruct.py --seconds 60
	$(BIN)/python bench/bench_reconstruct.py --seconds 60 --tag-points
	$(BIN)/python bench/bench_pipeline.py --preset smoke --workers 2
	MUJOCO_GL=egl $(BIN)/python bench/bench_robot.py --seconds 5 --trials 20
	$(BIN)/python bench/bench_cli_startup.py --runs 5
	$(BIN)/python bench/bench_rl_update.py --updates 20
	$(BIN)/python bench/bench_control_loop.py --steps 300
	@rm -rf out/bench_stage1   # the benchmark's own output from a previous run
	$(BIN)/twinrl bench stage1 --out out/bench_stage1 --policies state

# The site: guides, results, benchmarks, and the CLI and API references generated from the code.
docs: setup
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict --site-dir build/site

lint: setup
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache *.egg-info
