# passive-locator: `make serve` and `make test` work on a fresh machine.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
HOST ?= 127.0.0.1
PORT ?= 8080
STAMP := $(VENV)/.installed
VERSION := $(shell sed -n 's/^version = "\(.*\)"/\1/p' pyproject.toml)
IMAGE ?= passive-locator:$(VERSION)

.PHONY: serve test test-fast bench openapi constraints image-test install clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

# The filter hides only setuptools' notice that an editable install is one (printed on every `pip install -e`).
$(STAMP): $(BIN)/python pyproject.toml
	PYTHONWARNINGS="ignore:Editable installation" $(BIN)/python -m pip install --quiet -e '.[dev]'
	$(BIN)/python -c "from service.fixes.pipeline import compile_kernels; compile_kernels()"
	touch $(STAMP)

install: $(STAMP)

serve: $(STAMP)
	mkdir -p var
	$(BIN)/passive-locator serve --host $(HOST) --port $(PORT)

test: $(STAMP)
	$(BIN)/python -m pytest -n 2 -q

test-fast: $(STAMP)
	$(BIN)/python -m pytest -n 2 -q -m "not slow"

bench: $(STAMP)
	$(BIN)/python -m bench

openapi: $(STAMP)
	$(BIN)/python scripts/write_openapi.py

# Pins the image's runtime dependencies to what this venv has (after a dependency change in pyproject.toml).
constraints: $(STAMP)
	$(BIN)/python scripts/write_constraints.py

# Build the image with podman (a stand-in base from Debian's packages when no registry answers), then run
# scripts/container_smoke.sh on it; prints the image's size. Needs root and podman.
image-test:
	scripts/standin_base.sh
	IMAGE=$(IMAGE) scripts/container_smoke.sh

clean:
	rm -rf $(VENV) var .pytest_cache
