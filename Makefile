# Two commands set everything up on a fresh machine (see README.md):
#   make solve   - train NFQ with the textbook defaults on CartPole-v1 until solved, evaluate, save, load
#   make test    - run the test suite (the slow learning test included)
# `make solve` installs the package alone; `make test` adds the tests extra (zoo, offline, benchmarks, lint).
# torch is installed first, from its CPU build: left to resolve stable-baselines3's plain `torch` requirement, pip
# would pull the CUDA build and its libraries (several GB) on Linux.

VENV ?= .venv
PYTHON := $(VENV)/bin/python
TORCH ?= torch==2.13.0
CORE := $(VENV)/.sb3-nfq-core
DEV := $(VENV)/.sb3-nfq-dev

.PHONY: setup solve test lint

setup: $(DEV)

$(CORE): pyproject.toml
	python3 -m venv $(VENV)
	$(PYTHON) -m pip install --quiet "$(TORCH)"
	$(PYTHON) -m pip install --quiet -e .
	touch $(CORE)

$(DEV): $(CORE)
	$(PYTHON) -m pip install --quiet -e ".[tests]"
	touch $(DEV)

solve: $(CORE)
	$(PYTHON) examples/solve_cartpole.py

test: $(DEV)
	$(PYTHON) -m pytest -p no:cacheprovider

lint: $(DEV)
	$(PYTHON) -m ruff check .
	$(PYTHON) -m ruff format --check .
	$(PYTHON) -m mypy
