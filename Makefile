# The two commands of the README: `make demo` and `make test`. Both bootstrap .venv from the
# pinned requirements on a fresh machine (Python 3.11 or 3.12, no ROS distribution: Jazzy wheels from PyPI).
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
OUT    ?= out
PYTEST_ARGS ?=

.PHONY: venv demo test test-core lint bench clean readme

venv: $(STAMP)

$(STAMP): requirements.txt setup.py setup.cfg package.xml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -r requirements.txt
	$(BIN)/python -m pip install -q --no-deps --no-build-isolation -e .
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m nmpc_avoid_ros demo --out $(OUT)

# everything, on two processes (pytest-xdist): the offline tests (~950: 3.6 min instead of ~7), then the tests that
# talk DDS (real nodes; each worker its own block of domain ids, test/conftest.py: ~9 min instead of ~16), then the
# few DDS tests marked serial (their verdict is a real-time one that a test beside them would disturb) alone;
# with PYTEST_ARGS (a file, -k ...) one process runs what they select
test: $(STAMP)
	$(BIN)/ruff check nmpc_avoid_ros test
ifeq ($(strip $(PYTEST_ARGS)),)
	$(BIN)/python -m pytest -n 2 -m "not dds"
	$(BIN)/python -m pytest -n 2 -m "dds and not serial"
	$(BIN)/python -m pytest -m "dds and serial"
else
	$(BIN)/python -m pytest $(PYTEST_ARGS)
endif

# the quick subset (about a minute on 2 cores: 77 s measured, 114 s on one process): no ROS nodes / DDS,
# nothing that takes more than ~5 s (markers in pyproject.toml), on two processes (pytest-xdist);
# `make test` runs everything, on one
test-core: $(STAMP)
	$(BIN)/ruff check nmpc_avoid_ros test
	$(BIN)/python -m pytest -n 2 -m "not dds and not slow" $(PYTEST_ARGS)

lint: $(STAMP)
	$(BIN)/ruff check nmpc_avoid_ros test

# the README's parameter tables from the parameters' declarations (core/schema.py explains them)
readme: $(STAMP)
	$(BIN)/python -m nmpc_avoid_ros.tools.readme_tables

clean:
	rm -rf $(OUT) build install log *.egg-info
