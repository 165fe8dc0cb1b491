# The two sacred commands: `make demo` and `make test` (each sets up .venv on first use).
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.rtctl-installed

.PHONY: demo test test-all fuzz bench docs golden clean

# Set-up, once per pyproject change: the system libraries of the audio path (tools/sysdeps.sh
# installs them where it can, else prints the command), then the package with its test extras,
# then the demo's kernels compiled into numba's cache (rtctl warm), so that the first `make demo`
# does not sit 20-40 s in the compiler. Every step that can take seconds says so first.
$(STAMP): pyproject.toml tools/sysdeps.sh
	@bash tools/sysdeps.sh
	@test -x $(PY) || { echo "setup: creating the virtual environment $(VENV)"; $(PYTHON) -m venv $(VENV); }
	@echo "setup: installing rtctl and its dependencies into $(VENV) (pip; a minute or more the first time)"
	@$(PY) -m pip install -q --disable-pip-version-check -e '.[test]'
	@$(VENV)/bin/rtctl warm
	@touch $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/rtctl run line-bimorph-5-closed --out out/demo

test: $(STAMP)
	$(PY) -m pytest -q

# The parsers' fuzz tests (scene TOML, --set/--vary, images, serial frames, traces) with
# FUZZ_EXAMPLES random examples per test; `make test` runs a fixed, derandomized few of each.
# Failing examples are kept in .hypothesis/ and tried first on the next run (docs/fuzzing.md).
FUZZ_EXAMPLES ?= 2000
fuzz: $(STAMP)
	RTCTL_FUZZ_EXAMPLES=$(FUZZ_EXAMPLES) $(PY) -m pytest -q --hypothesis-show-statistics tests/test_fuzz_*.py

# The suite on Python 3.10-3.13, each in a rebuilt .venv-3.X (fresh resolve), after the same
# system set-up as `make test`; one line per version at the end (tools/test_all.sh).
test-all:
	@bash tools/sysdeps.sh
	bash tools/test_all.sh $(PYTEST_ARGS)

bench: $(STAMP)
	$(PY) bench/loop.py

# Rewrite tests/golden/ (one compact golden per bundled scene) and print what changed (docs/golden.md).
golden: $(STAMP)
	$(PY) -m rtctl.engine.golden

docs: $(STAMP)
	$(PY) -m rtctl.schema > docs/scene.md

clean:
	rm -rf out .pytest_cache .hypothesis
