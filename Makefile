# Every target creates .venv when missing and installs the project from pyproject.toml alone.
PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp

.PHONY: venv test test-slow demo demo-estimation bench matrix stress one-wall fuzz clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e ".[station,test]"
	touch $(STAMP)

# Tests without processes or timing of their own run two at a time (pytest-xdist, one per core); the
# serial ones (real processes, sockets, wall-clock timing) then run alone, as a loaded machine would
# make them late. Both always run; the exit code is the first failure's (5 when none ran).
test: $(STAMP)
	status=0; \
	$(PY) -m pytest -q -n 2 -m "not slow and not serial" --durations=15 || status=$$?; \
	$(PY) -m pytest -q -m "not slow and serial" --durations=15 || { s=$$?; [ $$status -ne 0 ] || status=$$s; }; \
	exit $$status

test-slow: $(STAMP)
	$(PY) -m pytest -q -m slow

# A full mission on the simulated NAO: log, model, result.json and report figures in runs/demo/.
demo: $(STAMP)
	$(VENV)/bin/station start --robot sim --out runs/demo

# The estimation-only demo (a camera circling a cylinder, the EKF and its 3-sigma ellipses).
demo-estimation: $(STAMP)
	$(PY) -m tools.demo_estimation --out runs/demo-estimation

# Open3D (the carving baseline) is installed in the bench environment only; its wheel needs libusb.
bench: $(STAMP)
	$(PY) -m pip install --quiet -e ".[station,test,bench]"
	@$(PY) -c "import open3d" 2>/dev/null || { command -v apt-get >/dev/null && apt-get install -y -qq libusb-1.0-0 >/dev/null; } || true
	$(PY) -m tools.bench --out docs/benchmarks.md

# The randomized mission matrix (a benchmark: 40 missions through the NAOqi stand-in, about an hour
# on two cores); its table goes to the matrix section of docs/benchmarks.md. COUNT=3 for a quick look.
COUNT ?= 40
matrix: $(STAMP)
	$(PY) -m tools.matrix --count $(COUNT) --out runs/matrix --doc docs/benchmarks.md

# The same missions in harsher worlds (config/stress.yaml: every range widened), seeds 300 on; to the
# stress section of docs/benchmarks.md. What breaks first, not a promise.
STRESS_COUNT ?= 24
stress: $(STAMP)
	$(PY) -m tools.matrix --ranges config/stress.yaml --count $(STRESS_COUNT) --first-seed 300 --out runs/stress --doc docs/benchmarks.md

# The matrix's worlds with their landmarks on one wall only (a drawn layout cut to its most-marked
# wall), seeds 500 on; to the one_wall section of docs/benchmarks.md.
ONE_WALL_COUNT ?= 12
one-wall: $(STAMP)
	$(PY) -m tools.matrix --one-wall --count $(ONE_WALL_COUNT) --first-seed 500 --out runs/one_wall --doc docs/benchmarks.md

# Long fuzzing budget (the default suite runs a bounded one).
fuzz: $(STAMP)
	$(PY) -m pytest -q -m slow tests/test_fuzz.py

clean:
	rm -rf $(VENV) runs .pytest_cache .hypothesis
