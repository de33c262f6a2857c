# Two commands for a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DEMO_OUT ?= demo-output/run-$(shell date +%Y%m%d-%H%M%S)

.PHONY: demo test docs lint bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/cbct demo --out $(DEMO_OUT)

# the suite on two workers of one thread each (pytest-xdist; a worker's numba and BLAS
# threads would fight the other's for the cores), then the tests that bound real device
# times alone (tests/conftest.py: REALTIME)
test: $(STAMP)
	NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 \
		$(BIN)/python -m pytest -n 2 --dist loadfile -m 'not slow and not realtime'
	$(BIN)/python -m pytest -m 'not slow and realtime'

DOCS_STAMP := $(VENV)/.installed-docs

$(DOCS_STAMP): $(STAMP)
	$(BIN)/python -m pip install --quiet -e '.[dev,docs]'
	touch $(DOCS_STAMP)

# the documentation site into site/; a broken link, a missing page or a docstring the API
# reference cannot read fails the build
docs: $(DOCS_STAMP)
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict

lint: $(STAMP)
	$(BIN)/ruff check .

bench: $(STAMP)
	$(BIN)/python bench/all.py
	$(BIN)/python bench/table.py

clean:
	rm -rf $(VENV) $(DEMO_OUT) site
