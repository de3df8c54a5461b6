# Two commands for a fresh machine that has only Python:
#   make run   -- create .venv, install, run the main job
#   make test  -- install the test extras, then ruff, mypy and pytest
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
export OPENBLAS_NUM_THREADS := 1
export OMP_NUM_THREADS := 1

.PHONY: run test test-peg fuzz install install-test system-deps build-deps bytecode bench clean-ipc

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

# pip builds the one compiled part (redistro._kernels: the C files beside
# their owners and the header setup.py generates from the declared layouts)
# with the machine's C compiler; a change to any of them rebuilds.
KERNELS := setup.py $(wildcard redistro/*.c redistro/*/*.c redistro/*.h redistro/*/*.h) \
	redistro/kernel_layouts.py $(wildcard redistro/*_layout.py redistro/*/*_layout.py)

$(VENV)/.installed: pyproject.toml $(KERNELS) | $(BIN)/python build-deps
	$(BIN)/python -m pip install -q -e .
	touch $@

$(VENV)/.installed-test: pyproject.toml $(KERNELS) | $(BIN)/python build-deps
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $@ $(VENV)/.installed

# What the kernels build with (Debian packages), installed when missing:
# the C compiler, libcrypto's headers (HMAC) and zlib's (crc32).
build-deps:
	@PKGS=; \
	command -v cc >/dev/null 2>&1 || command -v gcc >/dev/null 2>&1 || PKGS="$$PKGS gcc"; \
	[ -f /usr/include/openssl/evp.h ] || PKGS="$$PKGS libssl-dev"; \
	[ -f /usr/include/zlib.h ] || PKGS="$$PKGS zlib1g-dev"; \
	if [ -n "$$PKGS" ]; then \
	  if [ "$$(id -u)" = 0 ]; then SUDO=; else SUDO=sudo; fi; \
	  echo "installing$$PKGS with apt-get"; \
	  $$SUDO apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$PKGS >/dev/null; \
	fi

# Every node is a fresh interpreter: without the package's bytecode on disk
# (PYTHONDONTWRITEBYTECODE, or a tree never imported) each of a session's
# processes compiles redistro's sources again, about 0.1 s of CPU apiece.
# compileall writes what is missing or stale, whatever that variable says.
bytecode: | $(BIN)/python
	$(BIN)/python -m compileall -q redistro >/dev/null

install: $(VENV)/.installed
install-test: $(VENV)/.installed-test

# Debian packages the tests need: rt-tests gives cyclictest, the timer
# baseline; iproute2 gives ip, for the two-namespace node test (run as root);
# openssl makes the tests' own certificate authority (zenoh over TLS);
# util-linux gives unshare (tests/apart-python); chromium is the browser the
# page tests drive (Debian's, headless).
system-deps:
	@PKGS=; \
	command -v cyclictest >/dev/null 2>&1 || PKGS="$$PKGS rt-tests"; \
	command -v ip >/dev/null 2>&1 || PKGS="$$PKGS iproute2"; \
	command -v openssl >/dev/null 2>&1 || PKGS="$$PKGS openssl"; \
	command -v unshare >/dev/null 2>&1 || PKGS="$$PKGS util-linux"; \
	command -v chromium >/dev/null 2>&1 || PKGS="$$PKGS chromium"; \
	if [ -n "$$PKGS" ]; then \
	  if [ "$$(id -u)" = 0 ]; then SUDO=; else SUDO=sudo; fi; \
	  echo "installing$$PKGS with apt-get"; \
	  $$SUDO apt-get update -qq && \
	  DEBIAN_FRONTEND=noninteractive $$SUDO apt-get install -y -qq $$PKGS >/dev/null; \
	fi

# The main job: the peg insertion (a self-calibration runs first when the
# joint positions are unknown, as on a fresh machine).
run: install bytecode
	$(BIN)/redistro session tasks/peg_insertion.yaml

# As root, pytest runs three workers: the tests that start real-time sessions
# in one, the lockstep sessions in the second, whose Python (tests/apart-python)
# has a /dev/shm and SysV IPC of its own, the unit tests and the front door's in
# the third (tests/units-python: a network of its own too, below the others).
PYTEST_WORKERS := $(if $(filter 0,$(shell id -u)),--dist load --tx popen --tx popen//python=$(CURDIR)/tests/apart-python --tx popen//python=$(CURDIR)/tests/units-python)

test: install-test system-deps bytecode
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .
	$(BIN)/mypy redistro tools
	$(BIN)/pytest $(PYTEST_WORKERS)

# The front door's fuzzing at full strength: 2 000 hypothesis examples per
# input kind (make test runs 300 of each); about 3 minutes on two vCPUs.
fuzz: install-test
	REDISTRO_FUZZ_EXAMPLES=2000 $(BIN)/pytest tests/unit/test_fuzz_inputs.py -p no:cacheprovider

# Only the whole peg-insertion sessions (both transports, the starving and
# group e-stop faults): about 3 minutes on two vCPUs.
test-peg: install-test system-deps bytecode
	$(BIN)/pytest -m peg -s

clean-ipc: install
	$(BIN)/redistro clean
