# Two commands set everything up from nothing: `make demo` and `make test`.
PY ?= python3
VENV := .venv
QC := .venv-qc
BIN := $(VENV)/bin
export SUMO_HOME ?= /usr/share/sumo

.PHONY: all demo test bench sweep lint setup clean
all: test

$(VENV)/.stamp-system: scripts/install-system-deps.sh
	bash scripts/install-system-deps.sh
	@mkdir -p $(VENV) && touch $@

$(VENV)/.stamp: pyproject.toml $(VENV)/.stamp-system
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[dev]'
	touch $@

# The ASAM quality checkers pin numpy<2, so they live in their own venv and run as a process.
$(QC)/.stamp: requirements-qc.txt
	test -x $(QC)/bin/python || $(PY) -m venv $(QC)
	$(QC)/bin/python -m pip install -q --upgrade pip
	$(QC)/bin/python -m pip install -q -r requirements-qc.txt
	touch $@

setup: $(VENV)/.stamp $(QC)/.stamp

demo: setup
	$(BIN)/lidar2xodr demo -o demo-out

test: setup
	$(BIN)/python -m pytest -q

bench: setup
	$(BIN)/python bench/run.py

# every shared map, 1 km each: what check says about the built map (issue #6), no targets applied
sweep: setup
	$(BIN)/python bench/sweep.py

lint: $(VENV)/.stamp
	$(BIN)/ruff check src tests bench

clean:
	rm -rf $(VENV) $(QC) demo-out .pytest_cache
