# Two entry points for a newcomer: `make demo` and `make test`. Both do all set-up themselves,
# idempotently (a stamp file records the installed state), and are fast once set up.
SHELL := /bin/bash
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.ms3d-installed
APT_STAMP := $(VENV)/.ms3d-apt
DEMO_OUT ?= ms3d-work/demo-input
DEMO_WORK ?= ms3d-work/demo
# test files run in this many pytest-xdist processes (a file stays in one process: its module fixtures once)
TEST_WORKERS ?= 2
APT_PACKAGES := libusb-1.0-0 libgl1 libgomp1 chromium
NPM_STAMP := viewer/node_modules/.ms3d-installed

.PHONY: install demo test bench clean-demo lint

$(APT_STAMP): Makefile
	@missing=""; for p in $(APT_PACKAGES); do dpkg -s $$p >/dev/null 2>&1 || missing="$$missing $$p"; done; \
	if [ -n "$$missing" ]; then \
	  echo "installing Debian packages:$$missing"; \
	  SUDO=""; [ "$$(id -u)" = 0 ] || SUDO=sudo; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$missing; \
	fi
	@mkdir -p $(VENV) && touch $@

$(PY):
	python3 -m venv $(VENV)

# The viewer and the glTF validator (node >= 20: the machine's, or Debian's when it is new enough);
# nothing downloads a browser: the headless tests drive Debian's chromium.
$(NPM_STAMP): viewer/package.json viewer/package-lock.json $(APT_STAMP)
	@command -v node >/dev/null || { SUDO=""; [ "$$(id -u)" = 0 ] || SUDO=sudo; \
	  $$SUDO apt-get update -qq && DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq nodejs npm; }
	@node -e 'process.exit(parseInt(process.versions.node) >= 20 ? 0 : 1)' || \
	  { echo "ms3d needs Node.js >= 20 for the viewer (found $$(node --version))"; exit 1; }
	npm ci --prefix viewer --no-audit --no-fund --loglevel=error
	@touch $@

$(STAMP): pyproject.toml $(APT_STAMP) | $(PY)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[dev]" --config-settings editable_mode=compat
	$(PY) -c "import open3d, torch, prefect, laspy; print('ms3d environment ready: torch', torch.__version__, 'open3d', open3d.__version__, 'prefect', prefect.__version__)"
	@touch $@

install: $(STAMP) $(NPM_STAMP)

demo: $(STAMP) $(NPM_STAMP)
	$(VENV)/bin/ms3d demo --out $(DEMO_OUT) --work $(DEMO_WORK)

test: $(STAMP) $(NPM_STAMP)
	$(PY) -m pytest -q --durations=15 -n $(TEST_WORKERS) --dist loadfile tests

bench: $(STAMP)
	$(PY) benchmarks/synth_bench.py
	$(PY) benchmarks/partition_bench.py

lint: $(STAMP)
	$(VENV)/bin/ruff check .

clean-demo:
	rm -rf ms3d-work
