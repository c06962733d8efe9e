# Two commands set everything up from nothing: `make demo` and `make test`.
# The venvs install exactly the lock files (every package and version, --no-deps: the lock is the whole
# environment, pip check proves it complete); `make lock` regenerates them.
PY ?= python3
VENV := .venv
QC := .venv-qc
TOOLS := .venv-tools
BIN := $(VENV)/bin
LOCK := requirements.lock
QC_LOCK := requirements-qc.lock
UV_VERSION := 0.13.9
# The locks are resolved for the machines the project supports: CPython 3.11 on x86_64 Linux
# (glibc >= 2.31, which open3d 0.19 needs), Debian 12's python3.
LOCK_TARGET := --python-version 3.11 --python-platform x86_64-manylinux_2_31
PIP := python -m pip install -q --no-input
# SUMO comes from the PyPI package eclipse-sumo in the lock: check.py finds its netconvert and data
# by itself, so SUMO_HOME is left to the user (set it to use another SUMO installation).

.PHONY: all demo test bench sweep lint setup lock clean
all: test

$(VENV)/.stamp-system: scripts/install-system-deps.sh
	bash scripts/install-system-deps.sh
	@mkdir -p $(VENV) && touch $@

$(VENV)/.stamp: $(LOCK) pyproject.toml $(VENV)/.stamp-system
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/$(PIP) --no-deps -r $(LOCK)
	$(BIN)/$(PIP) --no-deps -e .
	$(BIN)/python -m pip check
	touch $@

# The ASAM quality checkers pin numpy<2, so they live in their own venv and run as a process.
$(QC)/.stamp: $(QC_LOCK)
	test -x $(QC)/bin/python || $(PY) -m venv $(QC)
	$(QC)/bin/$(PIP) --no-deps -r $(QC_LOCK)
	$(QC)/bin/python -m pip check
	touch $@

setup: $(VENV)/.stamp $(QC)/.stamp

# Regenerate both locks from pyproject.toml (main + dev extras) and requirements-qc.txt with uv.
$(TOOLS)/bin/uv:
	test -x $(TOOLS)/bin/python || $(PY) -m venv $(TOOLS)
	$(TOOLS)/bin/$(PIP) uv==$(UV_VERSION)

lock: $(TOOLS)/bin/uv
	$(TOOLS)/bin/uv pip compile --quiet pyproject.toml --extra dev $(LOCK_TARGET) -o $(LOCK)
	$(TOOLS)/bin/uv pip compile --quiet requirements-qc.txt $(LOCK_TARGET) -o $(QC_LOCK)

demo: setup
	$(BIN)/lidar2xodr demo -o demo-out

test: setup
	$(BIN)/python -m pytest -q

bench: setup
	$(BIN)/python bench/run.py

# issue #13: every shared map x 3 seeds + 20 random roadgen corridors x 2 seeds, one table and the done-when check
# (hours on 2 cores; resumable, JOBS=2 runs two cases at once). sweep-quick: the fixed ~20 min subset.
JOBS ?= 1
sweep: setup
	$(BIN)/python bench/sweep.py --jobs $(JOBS)

# issue #16: the paper's reproducibility protocol (four drives of one road, GNSS bias 0-2 m, three against the fourth)
# issue #14: whole-build speed, memory and scaling, and the extraction side by side with Open3D
.PHONY: bench-speed
bench-speed: setup
	$(BIN)/python bench/speed.py

.PHONY: bench-repro
bench-repro: setup
	$(BIN)/python bench/reproducibility.py

.PHONY: sweep-quick
sweep-quick: setup
	$(BIN)/python bench/sweep.py --quick --jobs $(JOBS)

lint: $(VENV)/.stamp
	$(BIN)/ruff check src tests bench

clean:
	rm -rf $(VENV) $(QC) $(TOOLS) demo-out .pytest_cache
