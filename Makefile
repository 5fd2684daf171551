# drake-rus: the two commands a new user needs.
#   make demo   set up .venv and run the main job, the autonomous scan (writes runs/demo/)
#   make test   set up .venv with the test extras, lint (ruff) and run the whole test suite
#   make notebooks   install the notebooks extra (JupyterLab) and open notebooks/ (127.0.0.1)
PYTHON ?= python3.11
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.drake_rus_installed
TEST_STAMP := $(VENV)/.drake_rus_test_installed
NOTEBOOKS_STAMP := $(VENV)/.drake_rus_notebooks_installed
# JupyterLab refuses to run as root unless told; the set-up may run as root (system packages).
JUPYTER_ROOT := $(if $(filter 0,$(shell id -u)),--allow-root,)
# make test runs the suite on this many processes (pytest-xdist; at most 4: each takes about
# a core and a GB), then, alone, the tests marked `wallclock` (they time a live loop).
TEST_WORKERS ?= $(shell n=$$(nproc 2>/dev/null || echo 1); [ $$n -gt 4 ] && n=4; echo $$n)

.PHONY: demo test lint setup setup-test notebooks diagrams benchmarks clean

$(STAMP): pyproject.toml scripts/install_system_deps.sh scripts/pip_install.sh
	bash scripts/install_system_deps.sh
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	bash scripts/pip_install.sh $(VENV) 2800 drake-rus -e .
	touch $(STAMP)

$(TEST_STAMP): $(STAMP)
	bash scripts/pip_install.sh $(VENV) 600 "the test extra" -e '.[test]'
	touch $(TEST_STAMP)

$(NOTEBOOKS_STAMP): $(STAMP)
	bash scripts/pip_install.sh $(VENV) 300 "the notebooks extra" -e '.[notebooks]'
	touch $(NOTEBOOKS_STAMP)

setup: $(STAMP)

setup-test: $(TEST_STAMP)

demo: $(STAMP)
	$(VENV)/bin/drake-rus scan --patient test:0 --out runs/demo

lint: $(TEST_STAMP)
	$(VENV)/bin/ruff check drake_rus tests benchmarks models notebooks
	$(VENV)/bin/ruff format --check drake_rus tests benchmarks models notebooks

# Both passes run even when the first fails; the target fails if either did.
test: lint
	@status=0; \
	echo "tests: $(TEST_WORKERS) processes, then the wallclock tests alone"; \
	$(PY) -m pytest -n $(TEST_WORKERS) -m "not wallclock" || status=$$?; \
	$(PY) -m pytest -m wallclock || status=$$?; \
	exit $$status

notebooks: $(NOTEBOOKS_STAMP)
	$(VENV)/bin/jupyter lab --ip=127.0.0.1 $(JUPYTER_ROOT) notebooks/

# Re-draws the committed diagram pictures (diagrams/*.svg) from the diagrams built now.
diagrams: $(STAMP)
	$(VENV)/bin/drake-rus render-diagram --all

benchmarks: $(STAMP)
	$(PY) -m benchmarks all

clean:
	rm -rf runs .pytest_cache
