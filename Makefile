# ctgs Makefile. `make demo` runs the whole pipeline on the built-in demo scene; `make test` runs the tests.
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
CTGS := $(VENV)/bin/ctgs
# torch is pinned here, not in pyproject: 2.13.0 resolves to a local CPU wheel on the dev/CI machines.
TORCH_SPEC ?= torch==2.13.0
STAMP := $(VENV)/.installed

.PHONY: setup test test-fast demo cuda-check bench clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q "$(TORCH_SPEC)"
	$(PY) -m pip install -q -e ".[test]"
	touch $@

setup: $(STAMP)

# pytest exit code 5 (no tests collected) must fail, not pass silently.
test: $(STAMP)
	$(MAKE) --no-print-directory cuda-check
	$(PY) -m pytest -q -ra tests; rc=$$?; if [ $$rc -eq 5 ]; then echo "no tests collected"; exit 1; fi; exit $$rc

test-fast: $(STAMP)
	$(PY) -m pytest -q -ra -m "not slow" tests

# Compile (not run) the CUDA sources when nvcc is present, so CUDA code that does not build fails CI.
cuda-check: $(STAMP)
	@if command -v nvcc >/dev/null 2>&1; then \
		$(PY) kernels/check_cuda_build.py; \
	else echo "cuda-check: nvcc not found, skipping CUDA compile check"; fi

bench: $(STAMP)
	$(PY) benchmarks/bench_render.py

clean:
	rm -rf build out runs .pytest_cache
