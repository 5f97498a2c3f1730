# Every target creates .venv when missing and installs the project from pyproject.toml alone.
PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp

.PHONY: venv test test-slow demo bench fuzz clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[station,test]"
	touch $(STAMP)

test: $(STAMP)
	$(PY) -m pytest -q -m "not slow"

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow

demo: $(STAMP)
	$(PY) -m tools.demo_estimation --out runs/demo

bench: $(STAMP)
	$(PY) -m pip install --quiet -e ".[station,test,bench]"
	$(PY) -m tools.bench --out docs/benchmarks.md

clean:
	rm -rf $(VENV) runs .pytest_cache .hypothesis
