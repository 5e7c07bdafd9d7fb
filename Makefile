# softgrasp: everything installs into a project-local virtual environment (.venv).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: run test install install-test bench clean

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

install: $(BIN)/python
	$(BIN)/python -m pip install --quiet -e ".[execute]"

install-test: $(BIN)/python
	$(BIN)/python -m pip install --quiet -e ".[test,execute]"

# The main job on the built-in default object.
run: install
	$(BIN)/softgrasp plan

# The whole test suite (slow tests included).
test: install-test
	$(BIN)/python -m pytest

bench: install
	$(BIN)/python benchmarks/bench_body.py
	$(BIN)/python benchmarks/bench_contact.py
	$(BIN)/python benchmarks/bench_plan.py --reference
	$(BIN)/python benchmarks/bench_dynamic.py
	$(BIN)/python benchmarks/bench_indent.py
	$(BIN)/python benchmarks/bench_execute.py

clean:
	rm -rf $(VENV) softgrasp-out .pytest_cache
