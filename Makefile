# tetdose — two commands for a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
# Numba caches compiled kernels per source hash: a kernel edit never reuses a stale cache (numba #1833).
NUMBA_CACHE_DIR := $(CURDIR)/.numba-cache/$(shell find src/tetdose -name '*.py' | sort | xargs cat | sha1sum | cut -c1-12)
export NUMBA_CACHE_DIR
export MPLBACKEND := Agg

.PHONY: venv demo test validate bench lint tools docs clean

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[dev,fem,dask,meshing]'
	touch $@

venv: $(VENV)/.installed

# Optional system tools used by the DICOM validation tests (skipped when absent).
tools:
	@if command -v dciodvfy >/dev/null 2>&1; then :; \
	elif command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then \
	  (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq dicom3tools) >/dev/null 2>&1 \
	  || echo "dicom3tools not installed: DICOM validator tests will skip"; \
	else echo "apt-get not available: DICOM validator tests will skip"; fi

demo: venv
	$(VENV)/bin/tetdose demo -o demo-out

lint: venv
	$(PY) -m ruff check src tests bench

# Two pytest-xdist workers, one test file each at a time (module fixtures built once), the longest
# files first (tests/conftest.py). Cold numba cache, 2 idle cores: ~9.5 min (serial: ~16.5 min).
# TEST_WORKERS=0 runs the tests in this process, one after the other.
TEST_WORKERS ?= 2
XDIST := -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder

test: venv tools lint
	$(PY) -m pytest -m "not slow" -q $(XDIST)

validate: venv tools
	$(PY) -m pytest -m slow -q

bench: venv
	for b in bench/bench_*.py; do $(PY) $$b || exit 1; done

# The documentation site (docs/_build/html/index.html, readable offline): the examples run during
# the build and a warning fails it. Not part of `make test` (the examples take minutes).
$(VENV)/.docs-installed: $(VENV)/.installed
	$(PY) -m pip install --quiet -e '.[docs]'
	touch $@

docs: $(VENV)/.docs-installed tools
	$(PY) -m sphinx -W --keep-going -b html docs docs/_build/html

clean:
	rm -rf $(VENV) .numba-cache .pytest_cache docs/_build docs/generated docs/auto_examples
