# Two commands on a fresh machine: `make demo` and `make test`.
# PYTHON: any Python that pyproject.toml's requires-python accepts, e.g. `make demo PYTHON=python3.13`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
# torch is pinned here only to pick the build that lies on the local disk; pyproject keeps a range.
TORCH  ?= torch==2.13.0

.PHONY: demo test lint bench clean

# Before the venv exists (and unless this is a dry run or only `clean`): stop with one line when $(PYTHON) is too
# old or lacks venv, warn when the fast CPU kernel cannot be built (scripts/check_python.sh).
ifeq ($(wildcard $(BIN)/python),)
ifeq ($(findstring n,$(firstword -$(MAKEFLAGS))),)
ifneq ($(filter-out clean,$(or $(MAKECMDGOALS),$(BIN)/python)),)
PYTHON_PROBLEM := $(shell sh scripts/check_python.sh "$(PYTHON)")
$(if $(PYTHON_PROBLEM),$(error $(PYTHON_PROBLEM)))
endif
endif
endif

$(BIN)/python:
	$(PYTHON) -m venv $(VENV) || { rm -rf $(VENV); exit 1; }

$(VENV)/.installed: $(BIN)/python pyproject.toml
	$(BIN)/pip install -q "$(TORCH)"
	$(BIN)/pip install -q -e ".[dev,video,colmap,viewer,export,materials,masks]"
	touch $@

# Ray (anisdf batch / reproduce --ray) only for the tests, which run a local Ray; users add it with anisdf[cluster]
$(VENV)/.cluster: $(VENV)/.installed
	$(BIN)/pip install -q -e ".[cluster]"
	touch $@

demo: $(VENV)/.installed
	$(BIN)/anisdf demo

lint: $(VENV)/.installed
	$(BIN)/ruff check src tests benchmarks

test: lint $(VENV)/.cluster
	$(BIN)/python -m pytest -rs tests

bench: $(VENV)/.installed
	$(BIN)/anisdf bench

clean:
	rm -rf $(VENV) build src/*.egg-info
