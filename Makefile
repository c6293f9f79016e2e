# Two entry points for a fresh clone: `make demo` (the main job) and `make test`.
PYTHON ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint typecheck format install clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	# torch first and pinned: the CPU wheel of 2.13.0 lies on disk; anything looser pulls a CUDA build.
	$(BIN)/pip install --quiet torch==2.13.0
	# Every extra (pyproject.toml): training, the study's Gymnasium, SB3 and Ray, rosbags, Parquet.
	# pip must not replace the pinned torch: check it afterwards.
	$(BIN)/pip install --quiet -e '.[all,test]'
	$(BIN)/python -c "import torch, sys; sys.exit(0 if torch.__version__.startswith('2.13.0') else 'pip replaced torch 2.13.0 by ' + torch.__version__)"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/efficienttrack demo

# Two test workers: the machines and CI have 2 cores (each worker's torch uses one thread, tests/conftest.py).
test: $(STAMP) lint typecheck
	$(BIN)/pytest -q -n 2

lint: $(STAMP)
	$(BIN)/ruff check src tests benchmarks examples
	$(BIN)/ruff format --check src tests benchmarks examples

# The files and settings are in pyproject.toml ([tool.mypy]).
typecheck: $(STAMP)
	$(BIN)/mypy

format: $(STAMP)
	$(BIN)/ruff check --fix src tests benchmarks examples
	$(BIN)/ruff format src tests benchmarks examples

clean:
	rm -rf $(VENV) build *.egg-info src/*.egg-info .pytest_cache .ruff_cache .mypy_cache
