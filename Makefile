# Two commands: `make run` (the main job) and `make test` (the test suite and the docstring examples). Each sets
# itself up.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup run test lint bench clean

$(STAMP): pyproject.toml requirements.lock
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -c requirements.lock -e ".[dev,distributed]"
	touch $(STAMP)

setup: $(STAMP)

run: $(STAMP)
	WANDB_MODE=$${WANDB_MODE:-offline} $(BIN)/python benchmarks/suite.py profile=quick

test: $(STAMP)
	WANDB_MODE=disabled $(BIN)/python -m pytest -q tests
	WANDB_MODE=disabled $(BIN)/python -m pytest -q --doctest-modules umrl

lint: $(STAMP)
	$(BIN)/ruff check umrl recipes benchmarks tests examples

bench: $(STAMP)
	$(BIN)/python benchmarks/throughput.py

clean:
	rm -rf $(VENV)
