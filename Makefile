# Two entry points: `make demo` and `make test`. Each installs what is missing into .venv first.
# Heavy pieces have pinned install steps (see README.md, section Install): torch 2.13.0 is the CPU wheel on disk,
# theseus-ai is an sdist that needs SuiteSparse headers and scikit-sparse 0.4.16.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
PIP := $(PY) -m pip
STAMP := $(VENV)/.installed
# g++: scikit-sparse is built from source, and torch.compile (deform/compiled.py) compiles C++
APT_PKGS := libsuitesparse-dev libusb-1.0-0 libgomp1 g++

.PHONY: install demo test test-fast lint format bench results clean sysdeps

sysdeps:
	@missing=""; for p in $(APT_PKGS); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing system packages:$$missing"; \
	  SUDO=$$( [ "$$(id -u)" = 0 ] || echo sudo ); \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$missing >/dev/null; \
	fi

$(STAMP): pyproject.toml Makefile
	$(MAKE) sysdeps
	[ -x $(PY) ] || $(PYTHON) -m venv $(VENV)
	$(PIP) install -q --upgrade pip wheel setuptools
	$(PIP) install -q torch==2.13.0
	$(PIP) install -q "numpy<2.3" scipy cython "scikit-sparse==0.4.16"
	$(PIP) install -q --no-build-isolation theseus-ai==0.2.3
	$(PIP) install -q -e ".[dev,bench]"
	# the compiled steps a service start loads, for every shipped rod (deform/models/*.pt; a package per
	# core at once, once): each rod's first start is a warm one
	$(PY) -m service prebuild --all-rods || echo "prebuild skipped: the service compiles at start-up instead"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(PY) -m service.demo

# one worker per core, each test file on one worker (its module fixtures built once); the 15
# slowest tests listed at the end, to keep the suite well under 15 minutes
test: $(STAMP)
	$(PY) -m pytest -q -x -n auto --dist loadfile --durations=15 tests

# the quick loop (a worker per core; 83 s of tests on two cores): no dataset, no compiling (tests
# not marked compile run the discrepancy tool's fused pieces eagerly, tests/conftest.py), nothing
# marked slow (markers: pyproject.toml [tool.pytest.ini_options]); `make test` runs everything
test-fast: $(STAMP)
	$(PY) -m pytest -q -x -n auto --dist loadfile -m "not slow and not compile and not needs_data" tests

# the layer contracts (import-linter, pyproject.toml [tool.importlinter]) and ruff ([tool.ruff]);
# CI runs `make lint` before the tests
lint: $(STAMP)
	$(VENV)/bin/lint-imports
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

format: $(STAMP)
	$(VENV)/bin/ruff check --fix .
	$(VENV)/bin/ruff format .

bench: $(STAMP)
	$(PY) benchmarks/speed.py

# docs/results.md from the stored results in benchmarks/results/*.json (runs no benchmark)
results: $(STAMP)
	$(PY) scripts/make_results.py

clean:
	rm -rf $(VENV) build *.egg-info
