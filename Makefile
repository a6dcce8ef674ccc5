# itk-nrreval: every dependency is installed by this file and pyproject.toml.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
TORCH_STAMP := $(VENV)/.installed-torch
ANTS_STAMP := $(VENV)/.installed-ants

.PHONY: install test demo bench lint clean

install: $(STAMP)

$(STAMP): pyproject.toml Makefile
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --upgrade pip
	$(PY) -m pip install -e '.[all]'
	# nilearn ships the MNI152 2009a template; we read its data files only, so skip its heavy deps.
	$(PY) -m pip install --no-deps 'nilearn>=0.10'
	touch $(STAMP)

# torch (the `gpu` extra, backend="torch" of specificity) is only for the tests, which exercise
# the torch path on the CPU: the CPU build, resolved from the machine's wheel cache. `make demo`
# does not need it.
$(TORCH_STAMP): $(STAMP)
	$(PY) -m pip install 'torch==2.13.0'
	touch $(TORCH_STAMP)

# antspyx (the `ants` extra: ANTs SyN as the fluid engine) is only for the tests, which check
# ANTs' transform lists against known motions: 0.4 GB, and it pins numpy < 2.4 and scipy < 1.16
# in this environment. `make demo` does not need it.
$(ANTS_STAMP): $(STAMP)
	$(PY) -m pip install -e '.[ants]'
	touch $(ANTS_STAMP)

# tests/test_report_browser.py lays the report out in a headless Chromium; Debian's chromium is
# installed when missing and apt-get is usable (root); otherwise those tests are skipped and
# the build goes on. tests/test_slurm.py starts a single-node SLURM on localhost (as root):
# Debian's slurm-wlm and munge (3.8 MB, about 10 s) are installed the same way.
test: install $(TORCH_STAMP) $(ANTS_STAMP)
	command -v chromium || command -v chromium-browser || command -v google-chrome \
	  || (command -v apt-get && [ "$$(id -u)" = 0 ] \
	      && (DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends chromium \
	          || (apt-get update && DEBIAN_FRONTEND=noninteractive \
	              apt-get install -y --no-install-recommends chromium))) \
	  || echo "chromium not installed: browser tests will be skipped"
	command -v slurmctld && command -v slurmd && command -v munged \
	  || (command -v apt-get && [ "$$(id -u)" = 0 ] \
	      && (DEBIAN_FRONTEND=noninteractive apt-get install -y --no-install-recommends slurm-wlm munge \
	          || (apt-get update && DEBIAN_FRONTEND=noninteractive \
	              apt-get install -y --no-install-recommends slurm-wlm munge))) \
	  || echo "slurm-wlm not installed: the real-SLURM tests will be skipped"
	# two test processes, one per core (pytest-xdist); a test file stays in one process, so its
	# module fixtures are made once
	$(PY) -m pytest -q -n 2 --dist loadfile

demo: install
	$(VENV)/bin/nrreval demo

bench: install
	$(PY) benchmarks/run_all.py

lint: install
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .

clean:
	rm -rf $(VENV) demo-output benchmarks/out
