# The README's two commands: `make demo` and `make test`. Both set up .venv first.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
# The CPU build of torch; override elsewhere, e.g. `make test TORCH=torch` on a GPU machine.
TORCH  ?= torch==2.13.0
PYTEST_ARGS ?=

.PHONY: setup demo test test-slow lint bench clean

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
	$(BIN)/python -m pytest -m "not slow" -q $(PYTEST_ARGS)

test-slow: setup
	$(BIN)/python -m pytest -m slow -q $(PYTEST_ARGS)

lint: setup
	$(BIN)/ruff check src tests benchmarks
	$(BIN)/ruff format --check src tests benchmarks

bench: setup
	mkdir -p benchmarks/results
	$(BIN)/safenav bench env --json benchmarks/results/env.json
	$(BIN)/safenav bench update --json benchmarks/results/update.json
	$(BIN)/safenav bench latency --json benchmarks/results/latency.json
	$(BIN)/safenav bench soak --json benchmarks/results/soak.json

clean:
	rm -rf $(VENV) .pytest_cache runs
