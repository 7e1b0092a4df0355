# Two commands do all the set-up on a fresh machine with Python 3.11+ and make:
#   make run    build .venv from uv.lock, then run the main job on embedded defaults
#   make test   build .venv from uv.lock, install the system packages (chromium), then run the test suite
# and, while working: make test-quick (the unit tests, 2-3 minutes), make lint (ruff, import contracts, mypy).
PYTHON ?= python3
VENV := .venv
UV_VERSION := 0.13.9
RUN_DIR ?= runs/quick

.PHONY: run test test-quick system-deps lint bench clean-venv

run: $(VENV)/.installed
	$(VENV)/bin/mpi-lidar pipeline --preset quick --out $(RUN_DIR)

# pytest exits 5 when it collected no test: a failure here, said out loud (CI must never pass or fail on nothing).
NO_TESTS = { rc=$$?; [ $$rc -ne 5 ] || echo "pytest collected no tests (exit 5): check testpaths and markers" >&2; exit $$rc; }

# Two worker processes, each taking whole files (a module's fixtures stay in one process) in collection order, the
# files with slow tests first (tests/conftest.py): the integration tests wait on servers, subprocesses and
# browsers, so two cores run the suite in about three quarters of the time.
test: $(VENV)/.installed system-deps
	$(VENV)/bin/python -m pytest -n 2 --dist loadfile --no-loadscope-reorder || $(NO_TESTS)

# The unit tests only (every test is marked unit or integration; tests/conftest.py refuses one that is not), on two
# worker processes: 3 min 11 s against 4 min 4 s in one on the slowest 2-core machine seen (2026-11-29).
test-quick: $(VENV)/.installed
	$(VENV)/bin/python -m pytest -m unit -q -n 2 || $(NO_TESTS)

# System packages the tests need: chromium renders the HTML reports (tests/reporting/test_browser.py); libllvm19
# is the CPU backend of Mitsuba's path tracer (the render group: benchmarks/mitsuba_render.py, whose Dr.Jit needs an
# LLVM of version 19 or later). Installed here, as root, where missing; never by a test. Azurite (npm), the Azure
# Blob server of the az:// tests (tests/azurite_server.py), goes into .tools/azurite once per version: 3.35 is the
# last that runs on Node 20.
CHROMIUM ?= /usr/bin/chromium
LIBLLVM ?= libllvm19
AZURITE_VERSION := 3.35.0
AZURITE_DIR := .tools/azurite
system-deps: $(AZURITE_DIR)/.installed-$(AZURITE_VERSION)
	@missing=""; \
	[ -x $(CHROMIUM) ] || missing="chromium"; \
	if command -v dpkg-query >/dev/null && ! dpkg-query -W -f='$${Status}' $(LIBLLVM) 2>/dev/null | grep -q "ok installed"; then \
	  missing="$$missing $(LIBLLVM)"; \
	fi; \
	if [ -n "$$missing" ]; then \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    DEBIAN_FRONTEND=noninteractive apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q $$missing; \
	  else \
	    echo "make system-deps: missing $$missing; install as root (apt-get install -y $$missing)" >&2; \
	  fi; \
	fi

$(AZURITE_DIR)/.installed-$(AZURITE_VERSION):
	@command -v npm >/dev/null || { echo "make system-deps: npm is missing; install Node.js 20+ and npm (apt-get install -y npm)" >&2; exit 1; }
	rm -rf $(AZURITE_DIR) && mkdir -p $(AZURITE_DIR)
	npm install --prefix $(AZURITE_DIR) --no-audit --no-fund --save-exact --loglevel=error azurite@$(AZURITE_VERSION)
	@touch $@

lint: $(VENV)/.installed
	$(VENV)/bin/ruff check .
	$(VENV)/bin/lint-imports
	$(VENV)/bin/mypy

bench: $(VENV)/.installed
	$(VENV)/bin/python -m benchmarks.sensor

# uv installs exactly what uv.lock pins; it is bootstrapped into .venv with the interpreter's own pip.
$(VENV)/.installed: pyproject.toml uv.lock
	@test -x $(VENV)/bin/uv || { $(PYTHON) -m venv $(VENV) && $(VENV)/bin/python -m pip install -q "uv==$(UV_VERSION)"; }
	$(VENV)/bin/uv sync --frozen --compile-bytecode --python $(VENV)/bin/python
	@touch $@

clean-venv:
	rm -rf $(VENV)
