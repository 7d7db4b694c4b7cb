# Two commands for a fresh Debian machine with Python 3.11 (see README):
#   make run    install into .venv if needed, then generate the default episode
#   make test   install the test extras if needed, then run the whole suite
SHELL := /bin/bash
.DEFAULT_GOAL := help

VENV        := .venv
VPY         := $(VENV)/bin/python
STAMP       := $(VENV)/.cosim-installed
TEST_STAMP  := $(VENV)/.cosim-test-installed
PYTHON      ?= $(shell command -v python3.11 2>/dev/null || command -v python3 2>/dev/null)
SYSTEM_LIBS := libusb-1.0-0 libgl1 libegl1 libgomp1
APT_LINE    := apt-get update && apt-get install -y --no-install-recommends $(SYSTEM_LIBS)
SCENARIO    ?= scenarios/default.yaml
PYTEST_ARGS ?=

.PHONY: help run test sysdeps lint bench clean

help:
	@echo "make run    generate the default episode ($(SCENARIO)) into out/"
	@echo "make test   run the whole test suite"
	@echo "make lint   ruff"
	@echo "make bench  co-simulation overhead benchmark"

# Open3D's wheel links against these system libraries; install them when we can, else say how.
sysdeps:
	@missing=""; \
	for lib in libusb-1.0.so.0 libGL.so.1 libEGL.so.1 libgomp.so.1; do \
	  ldconfig -p 2>/dev/null | grep -q "$$lib" || missing="$$missing $$lib"; \
	done; \
	if [ -n "$$missing" ]; then \
	  echo "Open3D needs system libraries that are missing:$$missing"; \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "+ $(APT_LINE)"; \
	    DEBIAN_FRONTEND=noninteractive bash -c '$(APT_LINE)' >/dev/null || exit 1; \
	  else \
	    echo "Install them as root, then run make again:"; \
	    echo "    $(APT_LINE)"; \
	    exit 1; \
	  fi; \
	fi

$(VPY):
	@test -n "$(PYTHON)" || { echo "Python 3.11 not found (tried python3.11, python3)"; exit 1; }
	@$(PYTHON) -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' || \
	  { echo "cosim needs Python 3.11 (the only version with wheels for every dependency); $(PYTHON) is $$($(PYTHON) -V)"; exit 1; }
	@if ! $(PYTHON) -m venv $(VENV) 2>/dev/null; then \
	  rm -rf $(VENV); \
	  if [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null; then \
	    echo "+ apt-get install python3.11-venv"; \
	    DEBIAN_FRONTEND=noninteractive bash -c 'apt-get update && apt-get install -y --no-install-recommends python3.11-venv' >/dev/null || exit 1; \
	    $(PYTHON) -m venv $(VENV); \
	  else \
	    echo "python3 -m venv failed; as root: apt-get install -y python3.11-venv"; exit 1; \
	  fi; \
	fi

$(STAMP): pyproject.toml | $(VPY)
	$(VPY) -m pip install --quiet --upgrade pip
	$(VPY) -m pip install --quiet -e .
	@touch $@

$(TEST_STAMP): $(STAMP)
	$(VPY) -m pip install --quiet -e '.[test]'
	@touch $@

run: sysdeps $(STAMP)
	$(VENV)/bin/cosim run $(SCENARIO)

# pytest exits 5 when it collected no test: that is a failure here, never a pass.
test: sysdeps $(TEST_STAMP)
	@set +e; $(VPY) -m pytest $(PYTEST_ARGS); rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests: failing"; exit 1; fi; exit $$rc

lint: $(TEST_STAMP)
	$(VENV)/bin/ruff check .

bench: sysdeps $(STAMP)
	$(VPY) benchmarks/cosim_overhead.py

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
