# Two entry points for a newcomer: `make demo` and `make test`. Both do all set-up themselves,
# idempotently (a stamp file records the installed state), and are fast once set up. The set-up
# (deploy/install.sh) prints one line per step and writes the apt/pip/npm output to $(VENV)/install.log.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.ms3d-installed
APT_STAMP := $(VENV)/.ms3d-apt
DEMO_OUT ?= ms3d-work/demo-input
DEMO_WORK ?= ms3d-work/demo
# test files run in this many pytest-xdist processes (a file stays in one process: its module fixtures once)
TEST_WORKERS ?= 2
# Debian packages: those the pipeline needs (make demo), and chromium for the viewer tests (make test)
APT_PACKAGES := libusb-1.0-0 libgl1 libgomp1
APT_TEST_PACKAGES := chromium
APT_TEST_STAMP := $(VENV)/.ms3d-apt-test
NPM_STAMP := viewer/node_modules/.ms3d-installed
# each set-up step prints one line; apt/pip/npm output goes to this log, whose tail a failure prints
INSTALL_LOG ?= $(VENV)/install.log
INSTALL := VENV=$(VENV) MS3D_INSTALL_LOG=$(INSTALL_LOG) MS3D_RETRY="make $(or $(MAKECMDGOALS),install)" deploy/install.sh

.PHONY: install demo test view bench clean-demo lint

$(APT_STAMP): Makefile deploy/install.sh
	@$(INSTALL) apt "Debian packages" $(APT_PACKAGES)
	@touch $@

$(APT_TEST_STAMP): Makefile deploy/install.sh | $(APT_STAMP)
	@$(INSTALL) apt "Debian packages for the viewer tests" $(APT_TEST_PACKAGES)
	@touch $@

# The viewer and the glTF validator (node >= 20: the machine's, or Debian's when it is new enough);
# nothing downloads a browser: the headless tests drive Debian's chromium. The demo needs neither.
$(NPM_STAMP): viewer/package.json viewer/package-lock.json | $(APT_STAMP)
	@$(INSTALL) node
	@touch $@

# the venv, pip, ms3d[dev] editable (compat mode) and an import check
$(STAMP): pyproject.toml | $(APT_STAMP)
	@$(INSTALL) python
	@touch $@

install: $(STAMP) $(APT_TEST_STAMP) $(NPM_STAMP)
	@echo "ms3d install: all set up (full output of the set-up in $(INSTALL_LOG))"

demo: $(STAMP)
	$(VENV)/bin/ms3d demo --out $(DEMO_OUT) --work $(DEMO_WORK)

test: $(STAMP) $(APT_TEST_STAMP) $(NPM_STAMP)
	$(PY) -m pytest -q --durations=15 -n $(TEST_WORKERS) --dist loadfile tests

# the demo's 3D Tiles in the browser (installs the viewer's npm packages)
view: $(STAMP) $(NPM_STAMP)
	$(VENV)/bin/ms3d view $(DEMO_WORK)

bench: $(STAMP)
	$(PY) benchmarks/synth_bench.py
	$(PY) benchmarks/partition_bench.py

lint: $(STAMP)
	$(VENV)/bin/ruff check .

clean-demo:
	rm -rf ms3d-work
