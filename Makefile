# The two sacred commands: `make demo` and `make test` (each sets up .venv on first use).
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.rtctl-installed

.PHONY: demo test bench docs clean

# Set-up, once per pyproject change: the system libraries of the audio path (tools/sysdeps.sh
# installs them where it can, else prints the command), then the package with its test extras.
$(STAMP): pyproject.toml tools/sysdeps.sh
	@bash tools/sysdeps.sh
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --disable-pip-version-check -e '.[test]'
	@touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/rtctl run line-bimorph-5 --out out/demo

test: $(STAMP)
	$(PY) -m pytest -q

bench: $(STAMP)
	$(PY) bench/loop.py

docs: $(STAMP)
	$(PY) -m rtctl.schema > docs/scene.md

clean:
	rm -rf out .pytest_cache .hypothesis
