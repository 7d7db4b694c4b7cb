# Two commands for a fresh Debian machine with Python 3.11 (see README):
#   make run    install into .venv if needed, then generate the default episode
#   make test   install the test extras if needed, then run the whole suite (on TEST_WORKERS xdist workers)
#   make test-fast  the unit tests only: no engines, no `cosim run` processes (a few minutes)
#   make image  build the Docker image (README, "Containers")
SHELL := /bin/bash
.DEFAULT_GOAL := help

VENV        := .venv
VPY         := $(VENV)/bin/python
STAMP       := $(VENV)/.cosim-installed
TEST_STAMP  := $(VENV)/.cosim-test-installed
PYTHON      ?= $(shell command -v python3.11 2>/dev/null || command -v python3 2>/dev/null)
SYSTEM_LIBS := libusb-1.0-0 libgl1 libegl1 libgomp1 libatomic1 libxrender1
APT_LINE    := apt-get update && apt-get install -y --no-install-recommends $(SYSTEM_LIBS)
SCENARIO    ?= scenarios/default.yaml
PYTEST_ARGS ?=
# pytest-xdist workers: 3 on the product's 2-core machine. A test waits part of its time (processes starting, Zenoh
# handshakes, SUMO and the engines loading), so one worker per core leaves the cores idle; with 3 both stay busy
# from the first minute to the last. From a fresh clone on a quiet machine the suite took 728, 800 and 827 s with
# 3, 828 and 837 s with 4 (the same tests cost 1,145 to 1,310 CPU-s from run to run: this machine is shared); on a
# slower 2-core machine (a tiny episode 1.6x the CPU) 1,074 to 1,147 s with 3; on a faster quiet one 641 s with 3
# (1,137 tests, 1,397 machine CPU-s; the whole .ci/run 711 s with the Docker base image already made).
# tests/conftest.py keeps tests that share a module or session fixture, or a resource, on one worker;
# tests/scheduling.py runs the `exclusive` tests (timing deadlines) first with no engine test beside them,
# compiles the numba kernels in the background and hands out the engine tests costliest first; every time bound
# in a test grows with the measured load. PYTEST_ARGS='-n 0' runs one test at a time.
TEST_WORKERS ?= 3
XDIST       := -n $(TEST_WORKERS) --dist loadgroup
# make image: BASE is the image to build on (docker/base.sh makes cosim-base:bookworm without a
# registry); WHEELHOUSE=1 (default) fills wheelhouse/ on the host first so the build needs no network;
# WHEELHOUSE=0 leaves wheelhouse/ as it is (empty in a fresh clone: pip in the build uses PyPI);
# EXTRAS e.g. ray (`make clean` before changing it: the wheelhouse is rebuilt only when pyproject.toml changes).
IMAGE       ?= cosim
BASE        ?= python:3.11-slim
WHEELHOUSE  ?= 1
EXTRAS      ?=
DOCKER      ?= docker
WHEEL_STAMP := wheelhouse/.stamp

.PHONY: help run test test-fast test-under-load sysdeps lint bench clean image base-image wheelhouse

help:
	@echo "make run    generate the default episode ($(SCENARIO)) into out/"
	@echo "make test   run the whole test suite ($(TEST_WORKERS) xdist workers: TEST_WORKERS=N)"
	@echo "make test-fast  unit tests only (no engines, no cosim run processes)"
	@echo "make test-under-load  the whole suite beside BUSY=2 busy-loop processes (a busy machine)"
	@echo "make lint   ruff"
	@echo "make bench  co-simulation overhead benchmark"
	@echo "make image  Docker image $(IMAGE) (BASE=$(BASE) WHEELHOUSE=$(WHEELHOUSE) EXTRAS=$(EXTRAS))"
	@echo "make base-image  cosim-base:bookworm from Debian packages (root, debootstrap; no registry)"

# The Open3D and SUMO wheels (libsumo, netconvert) link against these system libraries; install them
# when we can, else say how.
sysdeps:
	@missing=""; \
	for lib in libusb-1.0.so.0 libGL.so.1 libEGL.so.1 libgomp.so.1 libatomic.so.1 libXrender.so.1; do \
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

# setuptools announces every editable install of a mapped layout (cosim.sensors from sensors/) with a
# boxed warning that is not a problem here: EDITABLE_QUIET hides that one message, nothing else.
EDITABLE_QUIET := PYTHONWARNINGS="ignore:Editable installation"

$(STAMP): pyproject.toml | $(VPY)
	$(VPY) -m pip install --quiet --upgrade pip
	$(EDITABLE_QUIET) $(VPY) -m pip install --quiet -e .
	@touch $@

$(TEST_STAMP): $(STAMP)
	$(EDITABLE_QUIET) $(VPY) -m pip install --quiet -e '.[test,learn]'
	@touch $@

run: sysdeps $(STAMP)
	$(VENV)/bin/cosim run $(SCENARIO)

# Bytecode for every source up front: where PYTHONDONTWRITEBYTECODE is set (this workplace's machines), each of the
# suite's few hundred processes compiled the package's modules again (about 0.5 CPU-s a `cosim run`).
COMPILE     := $(VPY) -m compileall -q -j 0 cosim sensors exporters tests benchmarks examples >/dev/null

# pytest exits 5 when it collected no test: that is a failure here, never a pass.
test: sysdeps $(TEST_STAMP)
	@$(COMPILE)
	@set +e; $(VPY) -m pytest $(XDIST) $(PYTEST_ARGS); rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests: failing"; exit 1; fi; exit $$rc

# The fast lane: tests not marked integration, container or cluster. tests/conftest.py makes a test of this
# lane fail when it starts SUMO, JSBSim, PyBullet or a `cosim run` process.
FAST_MARKS := not integration and not container and not cluster
test-fast: sysdeps $(TEST_STAMP)
	@$(COMPILE)
	@set +e; COSIM_TEST_FAST=1 $(VPY) -m pytest $(XDIST) -m "$(FAST_MARKS)" $(PYTEST_ARGS); rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests: failing"; exit 1; fi; exit $$rc

# The whole suite on a simulated busy machine: BUSY processes spinning beside it (tests/under_load.py).
BUSY ?= 2
test-under-load: sysdeps $(TEST_STAMP)
	@$(COMPILE)
	@set +e; $(VPY) -m tests.under_load --busy $(BUSY) -- $(XDIST) $(PYTEST_ARGS); rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest collected no tests: failing"; exit 1; fi; exit $$rc

lint: $(TEST_STAMP)
	$(VENV)/bin/ruff check .

bench: sysdeps $(STAMP)
	$(VPY) benchmarks/cosim_overhead.py

# Every dependency as a wheel (plus the build backend), for `pip install --no-index` in the image.
$(WHEEL_STAMP): pyproject.toml | $(VPY)
	find wheelhouse -name '*.whl' -delete
	$(VPY) -m pip wheel --quiet --wheel-dir wheelhouse '.$(if $(EXTRAS),[$(EXTRAS)])' 'setuptools>=77' wheel
	rm -f wheelhouse/cosim-*.whl
	@touch $@

wheelhouse: $(WHEEL_STAMP)

base-image:
	docker/base.sh cosim-base:bookworm

image: $(if $(filter 1,$(WHEELHOUSE)),$(WHEEL_STAMP))
	$(DOCKER) build --build-arg BASE=$(BASE) --build-arg EXTRAS=$(EXTRAS) -t $(IMAGE) .
	@$(DOCKER) image ls $(IMAGE) --format '{{.Repository}}:{{.Tag}} {{.Size}}'

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .ruff_cache
	find wheelhouse -name '*.whl' -delete; rm -f $(WHEEL_STAMP)
