# One command sets up and runs each job: `make demo` (the research's flight test in SITL, moving and static,
# with their report) and `make test` (the suite).
PYTHON ?= python3
DATA_DIR ?= ../shared/data
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test lint bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)

$(STAMP): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	@test -f "$${NAC_DATA_DIR:-$(DATA_DIR)}/forestfires.csv" || $(BIN)/nac-onboard data fetch
	NAC_DATA_DIR=$${NAC_DATA_DIR:-$(DATA_DIR)} $(BIN)/python -m sitl.experiment.demo

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest

bench: $(STAMP)
	$(BIN)/python benchmarks/sitl_scale.py
	$(BIN)/python benchmarks/mission_upload.py
	$(BIN)/python benchmarks/agent_load.py
	$(BIN)/python benchmarks/throughput_vs_iperf3.py
	$(BIN)/python benchmarks/compute_overhead.py
	$(BIN)/python benchmarks/log_parse.py

clean:
	rm -rf $(VENV) runs .pytest_cache .ruff_cache
