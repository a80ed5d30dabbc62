# Two commands set everything up on a fresh machine (see README.md):
#   make solve   - train NFQ with the textbook defaults on CartPole-v1 until solved, evaluate, save, load
#   make test    - run the test suite (the slow learning test included)
# torch==2.13.0 (the CPU build on this machine's disk) is installed before the project: letting pip
# resolve a plain `torch` first would pull several GB of CUDA packages.

VENV ?= .venv
PYTHON := $(VENV)/bin/python
STAMP := $(VENV)/.sb3-nfq-installed

.PHONY: setup solve test lint

setup: $(STAMP)

$(STAMP): pyproject.toml
	python3 -m venv $(VENV)
	$(PYTHON) -m pip install --quiet torch==2.13.0
	$(PYTHON) -m pip install --quiet -e ".[tests]"
	touch $(STAMP)

solve: $(STAMP)
	$(PYTHON) examples/solve_cartpole.py

test: $(STAMP)
	$(PYTHON) -m pytest -p no:cacheprovider

lint: $(STAMP)
	$(PYTHON) -m ruff check .
	$(PYTHON) -m ruff format --check .
	$(PYTHON) -m mypy
