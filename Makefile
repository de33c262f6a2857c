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

# the GigE Vision panel driver (scanner.gige) and its fake (sim.gige_panel) use Aravis through
# Debian's GObject introspection (python3-gi, gir1.2-aravis-0.8): Debian's gi is linked into the
# venv when it is there and the venv's Python is 3.11 (without it the GigE tests skip)
$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	if [ -d /usr/lib/python3/dist-packages/gi ] && [ -d $(VENV)/lib/python3.11/site-packages ]; then \
		ln -sfn /usr/lib/python3/dist-packages/gi $(VENV)/lib/python3.11/site-packages/gi; fi
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/cbct demo --out $(DEMO_OUT)

# the suite on two workers of one thread each (pytest-xdist; a worker's numba and BLAS
# threads would fight the other's for the cores); the tests that bound real device times go
# to one worker first, beside one single-threaded test at a time (tests/conftest.py: REALTIME)
test: $(STAMP)
	NUMBA_NUM_THREADS=1 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 \
		$(BIN)/python -m pytest -n 2 --dist loadfile -m 'not slow'

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
