# Every target creates .venv if missing and installs torch (CPU build) before anything that
# depends on it, so pip never pulls the multi-GB CUDA build.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed-stamp
export OMP_NUM_THREADS ?= 1

.PHONY: install demo test test-all bench gpu-check lint notebooks docs clean

$(STAMP): setup.cfg pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --upgrade pip
	$(PY) -m pip install torch==2.13.0
	$(PY) -m pip install -e ".[sim,test,data,docs]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/hgpdm demo

# The numerical modules again on two other code paths, so that a test that holds only with this
# CPU's BLAS kernels fails here too, not on a user's machine: MKL's portable kernels
# (MKL_CBWR=COMPATIBLE) and 2 intra-op threads (other reduction splits).
NUMERIC_TESTS ?= tests/test_linalg.py tests/test_gaussian.py tests/test_expectations.py \
	tests/test_gp.py tests/test_properties.py tests/test_model_selection.py tests/inference \
	tests/decision/test_mcp.py tests/decision/test_opponent.py tests/robots/test_wam.py

test: $(STAMP)
	$(VENV)/bin/ruff check .
	HGPDM_SMOKE=1 $(PY) -m pytest -n 2 -q tests
	MKL_CBWR=COMPATIBLE HGPDM_SMOKE=1 $(PY) -m pytest -n 2 -q $(NUMERIC_TESTS)
	OMP_NUM_THREADS=2 HGPDM_SMOKE=1 $(PY) -m pytest -q -p no:xdist $(NUMERIC_TESTS)
	HGPDM_SMOKE=1 $(PY) -m pytest -n 2 -q --nbmake notebooks
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict

test-all: $(STAMP)
	$(PY) -m pytest -n 2 -q -m "" tests

bench: $(STAMP)
	$(PY) -m benchmarks

# The accelerator check (benchmarks/gpu_check.py): the GPU tests and the device benchmarks where
# CUDA is present, else the same code paths on the CPU at tiny sizes. On a GPU machine whose own
# Python holds a CUDA build of torch, name it, e.g. `make gpu-check GPU_PY=python3` (no venv is
# made then, so nothing is downloaded).
GPU_PY ?=
gpu-check: $(if $(GPU_PY),,$(STAMP))
	$(or $(GPU_PY),$(PY)) -m benchmarks.gpu_check $(GPU_CHECK_ARGS)

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check hgpdm_torch tests benchmarks

# The documentation site (mkdocs.yml, docs/): docstrings and the committed notebook outputs,
# built into site/; strict, so a docstring griffe cannot parse fails the build.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict

# Re-pair every notebook with its percent-format source (the newer of the two wins), then
# execute it in notebooks/ and save it with its outputs, at the sizes the text describes (about
# 40 minutes on 2 cores, 04 the longest at about 20). A notebook named in NB_SMOKE runs with
# HGPDM_SMOKE=1 instead (it must then say so at its top).
NB_SMOKE ?=
define NB_EXECUTE
import sys
from pathlib import Path

import nbformat
from nbclient import NotebookClient

path = Path(sys.argv[1])
nb = nbformat.read(path, as_version=4)
NotebookClient(nb, record_timing=False, resources={"metadata": {"path": str(path.parent)}}).execute()
nbformat.write(nb, path)
endef
export NB_EXECUTE

notebooks: $(STAMP)
	$(VENV)/bin/jupytext --sync notebooks/*.ipynb
	for nb in notebooks/*.ipynb; do \
	  case " $(NB_SMOKE) " in *" $$(basename $$nb .ipynb) "*) smoke=1;; *) smoke=0;; esac; \
	  echo "executing $$nb (HGPDM_SMOKE=$$smoke)"; \
	  HGPDM_SMOKE=$$smoke $(PY) -c "$$NB_EXECUTE" $$nb || exit 1; \
	done

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
