# Two commands set everything up on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
# torch is installed before the package, from TORCH_SPEC (a pip requirement) and TORCH_INDEX (an
# index URL, optional). pip takes the newest wheel that matches from every place it is configured
# to look: on a standard Linux x86_64 install that is PyPI's torch==2.13.0, a CUDA build (with
# NVIDIA's CUDA libraries, several GB); where pip is configured with a local wheel folder
# (find-links) holding torch-2.13.0+cpu, as on this project's CI machines, it is that CPU build.
# CPU-only anywhere: make cpu (= make setup TORCH_INDEX=$(CPU_INDEX)).
# A CUDA build for your driver: make setup TORCH_INDEX=https://download.pytorch.org/whl/cu126
# The index a venv was set up with is remembered ($(VENV)/.torch-index): a later make demo or
# make test without TORCH_INDEX keeps that build; make setup TORCH_INDEX= goes back to pip's.
CPU_INDEX   := https://download.pytorch.org/whl/cpu
TORCH_SPEC  ?= torch==2.13.0
TORCH_INDEX ?= $(shell cat $(VENV)/.torch-index 2>/dev/null)
TORCH       := $(TORCH_SPEC)$(if $(TORCH_INDEX), --index-url $(TORCH_INDEX))
# The torch request the venv was set up with; a different one reinstalls torch (and the package).
TORCH_STAMP := $(VENV)/.torch-spec
STAMP       := $(VENV)/.installed

.PHONY: setup cpu lint test test-burn test-all test-gpu demo bench clean FORCE
# `make` alone (e.g. `make TORCH_INDEX=...`) sets up .venv, not only its torch.
.DEFAULT_GOAL := setup

$(TORCH_STAMP): FORCE
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@if [ "$$(cat $@ 2>/dev/null)" != "$(TORCH)" ]; then \
	  if [ -f $@ ]; then $(PY) -m pip uninstall -q -y torch; fi; \
	  $(PY) -m pip install -q --upgrade pip && \
	  $(PY) -m pip install -q "$(TORCH_SPEC)" $(if $(TORCH_INDEX),--index-url $(TORCH_INDEX)) && \
	  echo "$(TORCH)" > $@ && echo "$(TORCH_INDEX)" > $(VENV)/.torch-index; \
	fi

$(STAMP): $(TORCH_STAMP) pyproject.toml Makefile tools/ensure_llvm.sh
	@tools/ensure_llvm.sh >/dev/null
	$(PY) -m pip install -q -e ".[test,bench]"
	@touch $(STAMP)

setup: $(STAMP)

# The CPU build of torch (no CUDA libraries), kept by every later make command.
cpu:
	$(MAKE) setup TORCH_INDEX=$(CPU_INDEX)

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

# --durations=15: the slowest 15 tests and their seconds, printed after the run (CI too).
test: $(STAMP) lint
	$(PY) -m pytest -m "not slow" -q --durations=15

# The same tests with BURN busy-loop processes beside them (pytest --burn): a loaded machine.
BURN ?= 1
test-burn: $(STAMP)
	$(PY) -m pytest -m "not slow" -q --durations=15 --burn $(BURN)

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
