# Thin wrappers named by the README. Everything runs from a project-local virtual environment.
PY ?= python3.11
VENV ?= .venv
BIN := $(VENV)/bin
# the physics catalog's models, asked when a recipe needs them (after install made the venv)
MODELS = $(shell $(BIN)/neuro models --catalog)

.PHONY: install install-web web chromium test lint up train train-all eval bench clean

$(BIN)/neuro: pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install --quiet -e '.[dev,stack,bench]'
	touch $(BIN)/neuro

install: $(BIN)/neuro

# The dashboard (web/): Node packages exactly as package-lock.json pins them, then the Vite build.
WEB_SRC := $(shell find web/src web/index.html web/vite.config.ts web/tsconfig.json -type f 2>/dev/null)
web/node_modules/.package-lock.json: web/package.json web/package-lock.json
	cd web && npm ci --no-audit --no-fund
	touch $@
install-web: web/node_modules/.package-lock.json
web/dist/index.html: web/node_modules/.package-lock.json $(WEB_SRC)
	cd web && npm run build
web: web/dist/index.html

# Debian's Chromium for the end-to-end tests (never a browser download of a tool's own).
SUDO := $(shell [ "$$(id -u)" -ne 0 ] && command -v sudo)
chromium:
	@if [ ! -x /usr/bin/chromium ]; then $(SUDO) apt-get update && $(SUDO) apt-get install -y chromium; fi

# Lint, type and layer checks, the web checks (API types current, tsc, vitest), then pytest (e2e included).
test: install web chromium
	$(BIN)/ruff check .
	$(BIN)/mypy
	$(BIN)/lint-imports
	cd web && npm run check:api && npx tsc --noEmit && npx vitest run
	$(BIN)/pytest -q

lint: install
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy
	$(BIN)/lint-imports

# The whole stack (services/stack.py): Redis found or started, emulator :8000, controller API :8001 and a
# worker, trainer API :8002 and a training worker, dashboard :8080. Ctrl-C stops everything it started.
up: install web
	$(BIN)/python -m services.stack

# Train one model: make train MODEL=pendulum-active SUBSTEPS=50
MODEL ?= pendulum-passive
SUBSTEPS ?= 50
train: install
	$(BIN)/neuro train $(MODEL) --substeps $(SUBSTEPS)

# Rebuild every committed default artifact (n = 25, 100, then 50 so that 50 is "latest"). The longest
# super-step is the hardest map to learn, so N^100 gets a wider network and more time (see BENCHMARKS.md).
N100_OPTS ?= --hidden 128,128 --epochs 2000 --max-seconds 270
# The tumbling quadrotor's N^100 (a half turn in one super-step) needs a deeper network and more data to
# stay within 2x of its N^25 over long flights: about 40 minutes on two cores.
N100_OPTS_QUADROTOR ?= --hidden 256,256,256 --activation silu --schedule cosine --batch-size 512 \
  --examples 750000 --epochs 2000 --max-seconds 1800 --time-budget 3600
train-all: install
	@test -n "$(MODELS)" || { echo "neuro models --catalog listed no models" >&2; exit 1; }
	for m in $(MODELS); do \
	  opts="$(N100_OPTS)"; [ "$$m" = quadrotor ] && opts="$(N100_OPTS_QUADROTOR)"; \
	  $(BIN)/neuro train $$m --substeps 25 --out artifacts || exit 1; \
	  $(BIN)/neuro train $$m --substeps 100 $$opts --out artifacts || exit 1; \
	  $(BIN)/neuro train $$m --substeps 50 --out artifacts || exit 1; \
	done

eval: install
	$(BIN)/neuro eval $(MODEL)

bench: install
	$(BIN)/neuro bench $(MODEL)

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache web/node_modules web/dist

# Regenerate proto/ (JSON Schemas of the wire models, the emulator's, controller's and trainer's OpenAPI
# documents).
.PHONY: proto
proto: install
	$(BIN)/python -m services.export_proto
	@if [ -d web/node_modules ]; then cd web && npm run --silent gen:api; \
	else echo "web/node_modules missing: run make install-web, then make proto, to regenerate web/src/api"; fi
