# The README's two commands: `make demo` and `make test`. Both set up .venv first.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
# The CPU build of torch; override elsewhere, e.g. `make test TORCH=torch` on a GPU machine.
TORCH  ?= torch==2.13.0
PYTEST_ARGS ?=
# `make test` runs the suite on this many pytest-xdist workers (2: the development and CI machines
# have 2 cores; more workers than cores slow the real-time flight tests). TEST_WORKERS=0: serial.
TEST_WORKERS ?= 2

.PHONY: setup demo test test-slow test-floors lint bench clean

setup: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q "$(TORCH)"
	$(BIN)/pip install -q -e ".[all]"
	touch $@

demo: setup
	$(BIN)/python -m safenav.demo

test: setup
	$(BIN)/python -m pytest -m "not slow" -q -n $(TEST_WORKERS) $(PYTEST_ARGS)

test-slow: setup
	$(BIN)/python -m pytest -m slow -q $(PYTEST_ARGS)

# The fast tests against the lowest versions pyproject.toml allows (constraints/floors.txt), in a
# fresh .venv-floors. Not part of `make test` or CI: a second environment to download and install
# (about 1 min of installs and 3 of tests on the 2-core machine, 2026-11-24).
FLOORS_VENV ?= .venv-floors
test-floors:
	rm -rf $(FLOORS_VENV)
	$(PYTHON) -m venv $(FLOORS_VENV)
	$(FLOORS_VENV)/bin/pip install -q --upgrade pip
	$(FLOORS_VENV)/bin/pip install -q -c constraints/floors.txt torch -e ".[all]"
	$(FLOORS_VENV)/bin/pip freeze --exclude-editable > $(FLOORS_VENV)/installed.txt
	$(FLOORS_VENV)/bin/python -m pytest -m "not slow" -q -p no:cacheprovider $(PYTEST_ARGS)

lint: setup
	$(BIN)/ruff check src tests experiments
	$(BIN)/ruff format --check src tests experiments

bench: setup
	mkdir -p benchmarks/results
	$(BIN)/safenav bench env --json benchmarks/results/env.json
	$(BIN)/safenav bench update --json benchmarks/results/update.json
	$(BIN)/safenav bench latency --json benchmarks/results/latency.json
	$(BIN)/safenav bench soak --json benchmarks/results/soak.json

clean:
	rm -rf $(VENV) $(FLOORS_VENV) .pytest_cache runs
