# PackPilot: two commands set everything up on a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
TEST_STAMP := $(VENV)/.test-extras-stamp
OUT    := out

.PHONY: demo test bench lint clean venv browser mutate soak faults

venv: $(STAMP)

# The demo needs only the package and its runtime dependencies; the test extras (pytest,
# PyBaMM, linters, ...) are installed by `make test` / `make lint` on top (TEST_STAMP).
# pip is not --quiet: it names each package as it goes; scripts/heartbeat.py (standard library,
# it runs before the venv exists) adds a line whenever a set-up command has been silent for 1.5 s
# (python -m venv, pip's "Installing collected packages" phase: 12.7 s of silence before it, fresh
# clone, quiet machine), so `make demo` is never more than 2 s without output (issue #25).
HEARTBEAT := $(PYTHON) scripts/heartbeat.py
$(STAMP): pyproject.toml
	@echo "setup: creating $(VENV) and installing packpilot (runtime dependencies only)" >&2
	$(HEARTBEAT) "creating $(VENV)" -- $(PYTHON) -m venv $(VENV)
	$(HEARTBEAT) "upgrading pip" -- $(PY) -m pip install --progress-bar off --upgrade pip
	$(HEARTBEAT) "installing packpilot and its dependencies" -- $(PY) -m pip install --progress-bar off -e .
	touch $(STAMP)

$(TEST_STAMP): $(STAMP) pyproject.toml
	@echo "setup: installing the test extras (pytest, PyBaMM, linters)" >&2
	$(HEARTBEAT) "installing the test extras" -- $(PY) -m pip install --quiet -e ".[test]"
	touch $(TEST_STAMP)

# Each demo starts a fresh telemetry file: a second `make demo` would otherwise append "run 2"
# to the same database and title its report "run 2" (the older run is replaced, not kept).
demo: $(STAMP)
	mkdir -p $(OUT)
	rm -f $(OUT)/demo.sqlite $(OUT)/demo.sqlite-wal $(OUT)/demo.sqlite-shm $(OUT)/demo_can.blf
	@echo "demo: simulating the 90-minute UAV mission (about 1 min; a first run on a machine runs the core interpreted while one background process compiles it, saying so)" >&2
	$(PY) -m packpilot.cli simulate examples/uav_mission.toml --progress \
		--db $(OUT)/demo.sqlite --report $(OUT)/report.html --plot $(OUT)/demo.png \
		--can-log $(OUT)/demo_can.blf --json > $(OUT)/demo_summary.json
	@echo "demo: full UAV mission (flight, dock, staged charging over CAN, balancing)"
	@echo "demo: wrote $(OUT)/report.html, $(OUT)/demo.png, $(OUT)/demo_summary.json,"
	@echo "      $(OUT)/demo.sqlite (telemetry) and $(OUT)/demo_can.blf (CAN frames)"
	@cat $(OUT)/demo_summary.json

# Headless Chromium for the HTML report's browser test (Debian package). A no-op when it is
# installed; when apt is unavailable (not root, no network) it only warns and that test skips.
CHROMIUM := /usr/bin/chromium
browser:
	@if [ -x $(CHROMIUM) ]; then :; \
	elif command -v apt-get >/dev/null 2>&1 && [ "$$(id -u)" = 0 ]; then \
		(apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium) \
		|| echo "browser: could not install chromium; the browser test will skip"; \
	else echo "browser: apt-get unavailable (or not root); the browser test will skip"; fi

# Compiled kernels are cached on disk next to their modules (__pycache__/*.nbi, *.nbc; the key
# covers everything a kernel imports, see packpilot/jit.py), so a second run starts in seconds
# instead of compiling again. A plain `make test` keeps that cache: the developer loop stays
# fast. CI must prove the kernels compile from source, so .ci/run calls `make test
# COLD_KERNELS=1`: NUMBA_CACHE_DIR then names a fresh empty directory for the whole run (every
# test process and subprocess compiles from scratch and shares what it compiled; the in-tree
# cache is neither read nor touched), removed afterwards. Before pytest, tests/precompile.py
# compiles every kernel the shipped examples run, each once, split over the 2 cores (#25: the two
# xdist workers used to compile the same kernels at the same time, and CLI subprocesses with
# them); the tests then load them from that cache. It does nothing when every example's kernels
# are compiled already (a warm in-tree cache). tests/timing.py ends the run with where its time
# went: per worker and per test, wall, CPU, subprocesses' CPU and numba compile CPU.
COLD_KERNELS ?=
test: $(TEST_STAMP) browser
	@set -e; \
	if [ -n "$(COLD_KERNELS)" ]; then \
		cache=$$(mktemp -d "$${TMPDIR:-/tmp}/packpilot-kernels.XXXXXX"); \
		trap 'rm -rf "$$cache"' EXIT; \
		export NUMBA_CACHE_DIR="$$cache"; \
		echo "test: no cached kernels (NUMBA_CACHE_DIR=$$cache)"; \
	fi; \
	echo "PYBAMM_DISABLE_TELEMETRY=true $(PY) -m tests.precompile --jobs 2"; \
	PYBAMM_DISABLE_TELEMETRY=true $(PY) -m tests.precompile --jobs 2; \
	echo "PYBAMM_DISABLE_TELEMETRY=true $(PY) -m pytest -n 2 -q -p no:cacheprovider -p tests.timing"; \
	PYBAMM_DISABLE_TELEMETRY=true $(PY) -m pytest -n 2 -q -p no:cacheprovider -p tests.timing

# Mutation testing (#18 §1, #26 item 4): every hand-listed mutant of a safety rule
# (tests/mutation/mutants.py) plus a seeded, stratified random sample of MUTATE_N tool-generated
# mutants of every rules module (tests/mutation/generate.py; docs/mutation.md), interpreted
# (NUMBA_DISABLE_JIT=1), on a private copy of the tree. A generated mutant runs only the tests
# that execute its line (a map built once per module, cached in $(OUT)/mutation_map/), fail-fast,
# in a forked child (tests/mutation/fast.py): a few seconds each. Kill rate per module on stdout
# and in $(OUT)/mutation.json / .md (hand-listed) and $(OUT)/mutation_generated.json / .md /
# .jsonl (generated). The first run builds the maps (one traced, interpreted run of every
# module's tests, as the old runner's baseline did: 40 s - 12 min per module on the loaded box
# of 2026-11-28, sequencing over 40 min); later runs reuse them until a rules or test file
# changes. MUTATE_SEED picks another sample.
MUTATE_JOBS ?= 2
MUTATE_N ?= 24
MUTATE_SEED ?= 26
mutate: $(TEST_STAMP)
	PYBAMM_DISABLE_TELEMETRY=true $(PY) -m tests.mutation.run --jobs $(MUTATE_JOBS) --out $(OUT) \
		--generated $(MUTATE_N) --seed $(MUTATE_SEED)
	$(PY) -m tests.mutation.web  # the dashboard's access rules (#18 §5), about a minute

# Property soak (#18 §2): every Hypothesis property under the `nightly` profile (tests/budget.py:
# at least 10,000 examples each, CI budget x 50), then every generated mutant of every rules
# module (#26 item 4; ~3,400 mutants, several hours on 2 cores; $(OUT)/mutation_generated.*).
# Hours, not minutes; not part of `make test`.
soak: $(TEST_STAMP)
	HYPOTHESIS_PROFILE=nightly PYBAMM_DISABLE_TELEMETRY=true \
		$(PY) -m pytest -n 2 -q -p no:cacheprovider -m hypothesis
	PYBAMM_DISABLE_TELEMETRY=true $(PY) -m tests.mutation.run --no-hand --all-generated \
		--jobs $(MUTATE_JOBS) --out $(OUT)

# Fault injection over the CAN runtime (#26): every fault of tests/fault_suite.py (lock-step
# `run` against `hil` on a real python-can bus; the slow ones included: frozen loaded battery,
# 30 s of 10x frame load, a frame flood) as a table on stdout; the frame load and the floods
# again in real time through the CAN hub (tests/fault_realtime.py: can-hub, run and the twin as
# processes, a third node flooding; ~4 min of wall time); then the fault tests (the CI
# subset, kill -9 of `run --db --can-log` through the CAN hub, the older bus faults). Needs the
# test extras installed (`make test` once); never runs pip.
faults: $(TEST_STAMP)
	PYBAMM_DISABLE_TELEMETRY=true $(PY) -m tests.fault_suite
	PYBAMM_DISABLE_TELEMETRY=true $(PY) -m tests.fault_realtime
	PYBAMM_DISABLE_TELEMETRY=true $(PY) -m pytest -q -p no:cacheprovider \
		tests/test_runtime_fault_suite.py tests/test_runtime_faults.py

# PyBOP, the fit's independent oracle (#27: "never worse than PyBOP on the same split"), in an
# environment of its own: PyBOP 26.3 needs numpy < 2.4 and PackPilot runs on 2.4. Bench-time only;
# benchmarks/bench_fit.py calls it through PACKPILOT_PYBOP_PYTHON (unset: no PyBOP columns).
PYBOP_VENV := .venv-pybop
PYBOP_STAMP := $(PYBOP_VENV)/.installed-stamp
$(PYBOP_STAMP):
	$(HEARTBEAT) "creating $(PYBOP_VENV) (PyBOP for make bench)" -- $(PYTHON) -m venv $(PYBOP_VENV)
	$(HEARTBEAT) "installing PyBOP" -- $(PYBOP_VENV)/bin/python -m pip install --quiet \
		"pybop==26.3" "numpy<2.4"
	touch $(PYBOP_STAMP)

# run_all.py runs every benchmarks/bench_*.py that has a run(): among them bench_soc_campaign
# (#28: 200 runs of the SOC acceptance on a 2-worker loopback Dask cluster, ~3 min).
bench: $(TEST_STAMP) $(PYBOP_STAMP)
	PYBAMM_DISABLE_TELEMETRY=true PACKPILOT_PYBOP_PYTHON=$(CURDIR)/$(PYBOP_VENV)/bin/python \
		$(PY) benchmarks/run_all.py
	PYBAMM_DISABLE_TELEMETRY=true $(PY) benchmarks/bench_report_memory.py --days 0.2
	PYBAMM_DISABLE_TELEMETRY=true $(PY) benchmarks/bench_coldstart.py
	PYBAMM_DISABLE_TELEMETRY=true $(PY) benchmarks/bench_power.py --append

lint: $(TEST_STAMP)
	$(VENV)/bin/ruff check src tests benchmarks
	$(VENV)/bin/mypy --strict src
	$(VENV)/bin/lint-imports

clean:
	rm -rf $(VENV) $(PYBOP_VENV) $(OUT) .mypy_cache .ruff_cache
