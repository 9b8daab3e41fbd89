# Two commands on a fresh machine: `make demo` and `make test`.
# PYTHON: any Python that pyproject.toml's requires-python accepts, e.g. `make demo PYTHON=python3.13`.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
# torch is pinned here only to pick the build that lies on the local disk; pyproject keeps a range.
TORCH  ?= torch==2.13.0
# The Khronos glTF Validator (npm) for tests/test_gltf_validator.py, which skips without it (`make gltf-validator`).
GLTF_VALIDATOR ?= 2.0.0-dev.3.10
NODE_DIR       := .ci/node

.PHONY: demo test lint bench clean gltf-validator

# Before the venv exists (and unless this is a dry run or only `clean` or `gltf-validator`): stop with one line when
# $(PYTHON) is too old or lacks venv, warn when the fast CPU kernel cannot be built (scripts/check_python.sh).
ifeq ($(wildcard $(BIN)/python),)
ifeq ($(findstring n,$(firstword -$(MAKEFLAGS))),)
ifneq ($(filter-out clean gltf-validator,$(or $(MAKECMDGOALS),$(BIN)/python)),)
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

# One worker a core (pytest-xdist), each on one thread (tests/conftest.py); a file's tests stay on one worker, so its
# module fixtures are built once. `pytest tests` alone runs them in one process, as before.
test: lint $(VENV)/.cluster
	$(BIN)/python -m pytest -rs -n auto --dist loadfile tests

# Into $(NODE_DIR)/node_modules (gitignored), where scripts/gltf_validate.mjs looks for it; once for each version.
gltf-validator: $(NODE_DIR)/.gltf-validator-$(GLTF_VALIDATOR)

$(NODE_DIR)/.gltf-validator-$(GLTF_VALIDATOR):
	npm install --prefix $(NODE_DIR) --no-audit --no-fund --loglevel=error --save-exact gltf-validator@$(GLTF_VALIDATOR)
	touch $@

bench: $(VENV)/.installed
	$(BIN)/anisdf bench

clean:
	rm -rf $(VENV) build src/*.egg-info $(NODE_DIR)
