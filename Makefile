# Every target does its own set-up on a fresh clone: `make train` and `make test` are all you need.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
PIP    := $(PY) -m pip
STAMP  := $(VENV)/.installed

.PHONY: install train test test-slow lint bench clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PIP) install --upgrade pip
	# torch first, pinned: the CPU wheel. An unpinned torch pulls the CUDA build (several GB).
	$(PIP) install torch==2.13.0
	$(PIP) install -e ".[dev,robot,distributed]"
	touch $(STAMP)

install: $(STAMP)

train: $(STAMP)
	$(PY) train.py bimodal

test: $(STAMP)
	OMP_NUM_THREADS=1 $(PY) -m pytest -q -n 2 -m "not slow"

# the end-to-end runs of Ray, worker processes, pybullet, the sweep and the wheel (~10-18 min more)
test-slow: $(STAMP)
	OMP_NUM_THREADS=1 $(PY) -m pytest -q -m slow

lint: $(STAMP)
	$(PY) -m ruff check .
	$(PY) -m mypy
	$(PY) -m mypy --strict hireps_torch

bench: $(STAMP)
	OMP_NUM_THREADS=1 $(PY) benchmarks/dual_speed.py
	OMP_NUM_THREADS=1 $(PY) benchmarks/bimodal_modes.py

clean:
	rm -rf $(VENV) build *.egg-info
