# Two commands on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3.11
VENV   := .venv
BIN    := $(VENV)/bin
# torch is pinned here only to pick the build that lies on the local disk; pyproject keeps a range.
TORCH  ?= torch==2.13.0

.PHONY: demo test lint bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(VENV)/.installed: $(BIN)/python pyproject.toml
	$(BIN)/pip install -q "$(TORCH)"
	$(BIN)/pip install -q -e ".[dev,video,colmap,viewer,export]"
	touch $@

# Ray (anisdf batch / reproduce --ray) only for the tests, which run a local Ray; users add it with anisdf[cluster]
$(VENV)/.cluster: $(VENV)/.installed
	$(BIN)/pip install -q -e ".[cluster]"
	touch $@

demo: $(VENV)/.installed
	$(BIN)/anisdf demo

test: $(VENV)/.installed $(VENV)/.cluster
	$(BIN)/ruff check src tests benchmarks
	$(BIN)/python -m pytest -rs tests

bench: $(VENV)/.installed
	$(BIN)/anisdf bench

clean:
	rm -rf $(VENV) build src/*.egg-info
