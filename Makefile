# Thin wrappers named by the README. Everything runs from a project-local virtual environment.
PY ?= python3.11
VENV ?= .venv
BIN := $(VENV)/bin
MODELS := pendulum-passive pendulum-active pendulum-force lander truck

.PHONY: install test lint up train train-all eval bench clean

$(BIN)/neuro: pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet -e '.[dev]'
	touch $(BIN)/neuro

install: $(BIN)/neuro

test: install
	$(BIN)/ruff check .
	$(BIN)/mypy
	$(BIN)/pytest -q

lint: install
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy

# The emulator service on 127.0.0.1:8000 over artifacts/, with Redis found or started by scripts/redis.sh.
up: install
	PYTHON=$(BIN)/python scripts/up.sh

# Train one model: make train MODEL=pendulum-active SUBSTEPS=50
MODEL ?= pendulum-passive
SUBSTEPS ?= 50
train: install
	$(BIN)/neuro train $(MODEL) --substeps $(SUBSTEPS)

# Rebuild every committed default artifact (n = 25, 100, then 50 so that 50 is "latest").
train-all: install
	for m in $(MODELS); do for n in 25 100 50; do $(BIN)/neuro train $$m --substeps $$n || exit 1; done; done

eval: install
	$(BIN)/neuro eval $(MODEL)

bench: install
	$(BIN)/neuro bench $(MODEL)

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache

# Regenerate proto/ (JSON Schemas of the wire models, the emulator's OpenAPI document) from the code.
.PHONY: proto
proto: install
	$(BIN)/python -m services.emulator.export_proto
