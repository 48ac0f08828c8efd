# Two commands on a fresh machine: `make demo` and `make test`. Both install into .venv first if needed.
# torch goes in first, pinned, so that pip takes the CPU build already on the machine instead of pulling
# several GB of CUDA packages; the project itself only asks torch>=2.1.

PYTHON ?= python3
VENV ?= .venv
TORCH ?= torch==2.13.0
# pytest-xdist processes for make test (the CI machine's 2 cores)
TEST_WORKERS ?= 2
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: install demo fleet-demo test bench docs clean

install: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q "$(TORCH)"
	$(PY) -m pip install -q -e ".[test]"
	touch $(STAMP)

demo: install
	rm -rf runs/demo
	$(VENV)/bin/cae-lcd detect --out runs/demo

fleet-demo: install
	$(VENV)/bin/cae-lcd fleet-demo --out runs/fleet-demo --hostile

test: install
	$(PY) -m pytest -q -n $(TEST_WORKERS)

bench: install
	$(VENV)/bin/cae-lcd bench

docs: install
	$(VENV)/bin/mkdocs build --strict

clean:
	rm -rf runs site .pytest_cache
