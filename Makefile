# The two commands a newcomer needs: `make demo` (main job on the built-in scene) and
# `make test`. Both build their own virtual environment first.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
# Pinned: any other torch requirement pulls several GB of CUDA packages (README, "Install").
TORCH := torch==2.13.0

.PHONY: demo test test-fast lint format env clean

env: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check $(TORCH)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -e ".[test]"
	touch $@

demo: env
	$(BIN)/dimslam demo

test: env lint
	$(BIN)/pytest -q

# The unit tier only (tests/conftest.py): no zenoh, no processes, no SLAM run; under a minute.
test-fast: env
	$(BIN)/pytest -q -m "not integration and not e2e"

lint: env
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: env
	$(BIN)/ruff check --fix .
	$(BIN)/ruff format .

clean:
	rm -rf $(VENV) out .pytest_cache .ruff_cache
