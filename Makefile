# Two commands set everything up on a fresh machine (see README.md):
#   make solve   - train NFQ with the textbook defaults on CartPole-v1 until solved, evaluate, save, load
#   make test    - run the test suite's fast tier (what developers run often; `make test-slow` runs the rest)
# `make solve` installs the package alone; `make test` adds its zoo and offline extras and the dev group of
# pyproject.toml (tests, lint, the benchmark suite), which needs pip >= 25.1.
# torch is installed first, from its CPU build: left to resolve stable-baselines3's plain `torch` requirement, pip
# would pull the CUDA build and its libraries (several GB) on Linux.

VENV ?= .venv
PYTHON := $(VENV)/bin/python
# The one pin: the torch release the project is tested with, whose CPU build the CI machines hold; `make TORCH=...`
# picks another (README.md, Install, says how to get a CPU build elsewhere).
TORCH ?= torch==2.13.0
CORE := $(VENV)/.sb3-nfq-core
DEV := $(VENV)/.sb3-nfq-dev

LOWEST ?= .venv-lowest
#: The fast tests that need no extra: run against the lowest versions pyproject.toml declares.
LOWEST_TESTS := tests/test_fitting.py tests/test_contract.py tests/test_sb3_integration.py tests/test_sb3_usage.py \
	tests/test_variants.py tests/test_bad_input.py tests/test_save_load.py tests/test_callbacks.py

.PHONY: setup solve test test-slow lint docs test-lowest check-zoo-extra check-sdist

setup: $(DEV)

$(CORE): pyproject.toml
	python3 -m venv $(VENV)
	$(PYTHON) -m pip install --quiet "$(TORCH)"
	$(PYTHON) -m pip install --quiet -e .
	touch $(CORE)

$(DEV): $(CORE)
	$(PYTHON) -m pip install --quiet --upgrade "pip>=25.1"
	$(PYTHON) -m pip install --quiet -e ".[zoo,offline]" --group dev
	touch $(DEV)

solve: $(CORE)
	$(PYTHON) examples/solve_cartpole.py

# The fast tier: everything but the tests marked slow (learning to a score, the zoo and Optuna in subprocesses, process
# pools). CI runs both tiers.
test: $(DEV)
	$(PYTHON) -m pytest -p no:cacheprovider -m "not slow"

test-slow: $(DEV)
	$(PYTHON) -m pytest -p no:cacheprovider -m slow

# The API documentation (Sphinx, SB3's layout), warnings as errors: docs/_build/html/index.html
docs: $(DEV)
	$(PYTHON) -m sphinx -W --keep-going -q -b html docs docs/_build/html

lint: $(DEV)
	$(PYTHON) -m ruff check .
	$(PYTHON) -m ruff format --check .
	$(PYTHON) -m mypy

# A fresh venv with the lowest declared versions of the core dependencies (torch stays the CPU build above).
test-lowest:
	rm -rf $(LOWEST)
	python3 -m venv $(LOWEST)
	$(LOWEST)/bin/python -m pip install --quiet "$(TORCH)"
	$(LOWEST)/bin/python .ci/lowest_versions.py pyproject.toml > $(LOWEST)/lowest.txt
	$(LOWEST)/bin/python -m pip install --quiet -r $(LOWEST)/lowest.txt "pytest>=8"
	$(LOWEST)/bin/python -m pip install --quiet --no-deps -e .
	$(LOWEST)/bin/python -m pip list 2>/dev/null | grep -i -E "^(stable.baselines3|gymnasium|numpy|torch) "
	$(LOWEST)/bin/python -m pytest -p no:cacheprovider -q -m "not slow" $(LOWEST_TESTS)

# The wheel with only the [zoo] extra, in a fresh venv outside the repository: every command of docs/zoo.md.
check-zoo-extra:
	bash .ci/check_zoo_extra.sh

# The sdist unpacked outside the repository: its own fast tests run there.
check-sdist: $(DEV)
	PYTHON=$(abspath $(PYTHON)) bash .ci/check_sdist.sh
