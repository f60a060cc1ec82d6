# Every target creates .venv if missing and installs torch (CPU build) before anything that
# depends on it, so pip never pulls the multi-GB CUDA build.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
export OMP_NUM_THREADS ?= 1

.PHONY: install demo test test-all bench lint notebooks clean

$(STAMP): setup.cfg pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --upgrade pip
	$(PY) -m pip install torch==2.13.0
	$(PY) -m pip install -e ".[sim,test,data]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/hgpdm demo

test: $(STAMP)
	$(VENV)/bin/ruff check .
	HGPDM_SMOKE=1 $(PY) -m pytest -n 2 -q tests
	HGPDM_SMOKE=1 $(PY) -m pytest -n 2 -q --nbmake notebooks

test-all: $(STAMP)
	$(PY) -m pytest -n 2 -q -m "" tests

bench: $(STAMP)
	$(PY) -m benchmarks

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check hgpdm_torch tests benchmarks

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
