# ermrl: the two commands of the README quick start, and their helpers.
#
#   make demo   set up .venv, evolve reservoirs on Pendulum with velocities hidden, test the best one
#   make test   set up .venv and run the test suite (what CI runs, with `make test-slow` after it)

PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.ermrl-installed
# A CPU build of torch, installed before stable-baselines3 so that pip does not pull a CUDA build.
TORCH_SPEC ?= torch==2.13.0
PYTEST_ARGS ?=
# Processes of the default suite (pytest-xdist; a test file stays in one process). 0: one process.
TEST_WORKERS ?= 2

.PHONY: install system-deps demo test test-slow lint typecheck docs docs-serve cli-docs clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check "$(TORCH_SPEC)"
	$(PY) -m pip install --quiet --disable-pip-version-check -e ".[dev]"
	touch $(STAMP)

install: $(STAMP)

# Debian packages for headless MuJoCo rendering (ermrl video) and the headless Chromium that
# tests/test_report_browser.py opens report.html in; needs root, skipped when present.
system-deps:
	bash scripts/install_system_deps.sh

# The demo is an experiment file (experiments/demo.yaml): a small evolution on a partially
# observable task (Pendulum, velocity hidden) on the population backend, the re-evaluation of its
# best candidates, the test phase against PPO, PPO on the full observation and the unevolved
# reservoir on 5 new seeds, and the report. 2 to 4 minutes on 2 cores, depending on
# the CPU; rerunning resumes.
demo: install
	$(PY) -m ermrl run experiments/demo.yaml
	@echo "results: runs/demo/Pendulum-v1/test/summary.csv, runs/demo/Pendulum-v1/report/report.html"

test: install
	$(PY) -m pytest -m "not slow" -n $(TEST_WORKERS) --dist loadfile $(PYTEST_ARGS)

# The slow tests (end-to-end runs, SLURM, notebooks, benchmarks' quick modes) in the same
# processes as the default suite: a file stays in one process, files run side by side.
test-slow: install
	$(PY) -m pytest -m slow -n $(TEST_WORKERS) --dist loadfile $(PYTEST_ARGS)

lint: install
	$(PY) -m ruff check ermrl tests benchmarks *.py

# mypy over the package, configured in pyproject.toml ([tool.mypy]).
typecheck: install
	$(PY) -m mypy

# The documentation site (mkdocs.yml, pages in docs/), built strictly: a broken link, a missing
# page or a docstring mkdocstrings cannot read fails the build. Written to site/.
docs: install
	$(VENV)/bin/mkdocs build --strict --site-dir site

docs-serve: install
	$(VENV)/bin/mkdocs serve

# docs/cli.md is generated from the argparse parsers (tests/test_docs.py fails when it is stale).
cli-docs: install
	$(PY) -m ermrl.cli._docs docs/cli.md

clean:
	rm -rf $(VENV) runs reports site ermrl.db .pytest_cache
