# Two commands set everything up on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
# The CPU build of torch; override (e.g. TORCH_SPEC=torch) on a CUDA machine.
TORCH_SPEC ?= torch==2.13.0
STAMP  := $(VENV)/.installed

.PHONY: setup lint test test-all test-gpu demo bench clean

$(STAMP): pyproject.toml Makefile tools/ensure_llvm.sh
	@tools/ensure_llvm.sh >/dev/null
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -c "import torch" 2>/dev/null || $(PY) -m pip install -q "$(TORCH_SPEC)"
	$(PY) -m pip install -q -e ".[test,bench]"
	@touch $(STAMP)

setup: $(STAMP)

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

test: $(STAMP) lint
	$(PY) -m pytest -m "not slow" -q

test-all: $(STAMP)
	$(PY) -m pytest -q

# GPU readiness (tests marked gpu, on cuda_ad_rgb); each is skipped, with the reason, without CUDA.
test-gpu: $(STAMP)
	$(PY) -m pytest -m gpu -q

demo: $(STAMP)
	$(PY) -m gdpt demo --out out/demo --force

bench: $(STAMP)
	$(PY) benchmarks/poisson.py

clean:
	rm -rf $(VENV) out .pytest_cache
