# Two commands do all the set-up on a fresh machine with Python 3.11+ and make:
#   make run    build .venv from uv.lock, then run the main job on embedded defaults
#   make test   build .venv from uv.lock, then run the test suite
PYTHON ?= python3
VENV := .venv
UV_VERSION := 0.13.9
RUN_DIR ?= runs/quick

.PHONY: run test lint bench clean-venv

run: $(VENV)/.installed
	$(VENV)/bin/mpi-lidar pipeline --preset quick --out $(RUN_DIR)

test: $(VENV)/.installed
	$(VENV)/bin/python -m pytest

lint: $(VENV)/.installed
	$(VENV)/bin/ruff check .
	$(VENV)/bin/lint-imports

bench: $(VENV)/.installed
	$(VENV)/bin/python -m benchmarks.sensor

# uv installs exactly what uv.lock pins; it is bootstrapped into .venv with the interpreter's own pip.
$(VENV)/.installed: pyproject.toml uv.lock
	@test -x $(VENV)/bin/uv || { $(PYTHON) -m venv $(VENV) && $(VENV)/bin/python -m pip install -q "uv==$(UV_VERSION)"; }
	$(VENV)/bin/uv sync --frozen --compile-bytecode --python $(VENV)/bin/python
	@touch $@

clean-venv:
	rm -rf $(VENV)
