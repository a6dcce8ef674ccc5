# itk-nrreval: every dependency is installed by this file and pyproject.toml.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: install test demo bench lint clean

install: $(STAMP)

$(STAMP): pyproject.toml Makefile
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --upgrade pip
	$(PY) -m pip install -e '.[all]'
	# nilearn ships the MNI152 2009a template; we read its data files only, so skip its heavy deps.
	$(PY) -m pip install --no-deps 'nilearn>=0.10'
	# torch (the `gpu` extra, backend="torch" of specificity): this is the CPU build, resolved from
	# the machine's wheel cache; it is installed so that the tests exercise the torch path on the CPU.
	$(PY) -m pip install 'torch==2.13.0'
	touch $(STAMP)

test: install
	$(PY) -m pytest -q

demo: install
	$(VENV)/bin/nrreval demo

bench: install
	$(PY) benchmarks/run_all.py

lint: install
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

clean:
	rm -rf $(VENV) demo-output benchmarks/out
