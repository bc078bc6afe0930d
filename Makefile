# quasisim: `make demo` runs the pipeline on the bundled example, `make test` runs the tests.
# Both create .venv (Python 3.11) on first use.
PYTHON ?= python3.11
VENV := .venv
PY := $(VENV)/bin/python
SHARED ?= $(abspath ../shared)
export QUASISIM_ROBOT_PATH ?= $(SHARED)/robots
export QUASISIM_DATA ?= $(SHARED)/data
export MUJOCO_GL ?= egl

.PHONY: setup setup-lerobot demo demo-ours test test-all test-fast lint clean

setup: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml
	@sh scripts/system_deps.sh
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "error: $(PYTHON) not found (quasisim needs Python 3.11)"; exit 1; }
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q 'torch==2.13.0'  # the CPU build where pip finds it (PyPI's default is a CUDA build of GBs)
	$(PY) -m pip install -q -e '.[dev,cluster,viewer,rl]'
	@touch $@

# `quasisim export --format lerobot` in an environment of its own (lerobot pins torch < 2.11: pip takes a CUDA
# build of torch 2.10, about 8 GB, ~3 min; docs/dataset.md): run .venv-lerobot/bin/quasisim export ...
# It gets the main environment's numpy: the export replays each run and must reproduce it bit for bit, and
# another numpy's LAPACK may choose other principal axes for a symmetric object (a cube's inertia), which a
# contact-rich replay amplifies. pip then reports that opencv-python-headless (lerobot's) declares numpy < 2.3;
# the export does not use OpenCV (tests/test_lerobot_export.py runs there).
LEROBOT_VENV := .venv-lerobot
setup-lerobot: $(LEROBOT_VENV)/.installed

$(LEROBOT_VENV)/.installed: pyproject.toml $(VENV)/.installed
	$(PYTHON) -m venv $(LEROBOT_VENV)
	$(LEROBOT_VENV)/bin/python -m pip install -q --upgrade pip
	$(LEROBOT_VENV)/bin/python -m pip install -q -e '.[dev,lerobot]'
	$(LEROBOT_VENV)/bin/python -m pip install -q --no-deps "numpy==$$($(PY) -c 'import numpy; print(numpy.__version__)')"
	@touch $@

# The default method (the cascade: sampling MPC in MuJoCo first, the physics curriculum only where that fails
# strict success) on the bundled example, judged in MuJoCo beside the kinematic replay; ends with a short summary
# and the report's path. `demo-ours`: the full method (curriculum, sampling around its plan, select) on a
# 40-frame example, a few minutes.
demo: setup
	$(VENV)/bin/quasisim example --out out/example --name cube_lift --overwrite
	rm -rf out/example/cube_lift/transfer
	$(VENV)/bin/quasisim transfer out/example/cube_lift.npz --hand shadow --target mujoco --out out/example/cube_lift/transfer

demo-ours: setup
	$(VENV)/bin/quasisim example --out out/example40 --name cube_lift --frames 40 --overwrite
	rm -rf out/example40/cube_lift/ours
	$(VENV)/bin/quasisim transfer out/example40/cube_lift.npz --hand shadow --method ours \
		--target mujoco --out out/example40/cube_lift/ours

# Two test processes (one per core; a test module stays in one process, so its compiled programs are shared).
# Tests compile without XLA's backend (LLVM) optimisation and without its CPU fusion emitters (0.6x the
# compile time of the simulator's value and gradient, BENCHMARKS.md "Test programs compiled without the fusion
# emitters"): compilation is most of the end-to-end tests' time, and what they check (behaviour, resumes,
# errors against closed forms and MuJoCo) does not depend on it; the benchmarks (`quasisim bench ...`) measure
# the programs as users compile them.
TEST_XLA := --xla_backend_optimization_level=0 --xla_cpu_use_fusion_emitters=false
# `test` (CI) leaves out the extended tests (research paths outside the default method, ~25 min more on 2 cores);
# `test-all` runs every test.
# The LeRobot export's tests (marker `lerobot`) run in .venv-lerobot after the rest.
test: setup setup-lerobot
	@sh scripts/test_deps.sh
	XLA_FLAGS="$$XLA_FLAGS $(TEST_XLA)" $(VENV)/bin/pytest -q -n 2 --dist loadfile --durations=25 -m "not extended and not lerobot"
	XLA_FLAGS="$$XLA_FLAGS $(TEST_XLA)" $(LEROBOT_VENV)/bin/pytest -q -m lerobot tests/test_lerobot_export.py

test-all: setup setup-lerobot
	@sh scripts/test_deps.sh
	XLA_FLAGS="$$XLA_FLAGS $(TEST_XLA)" $(VENV)/bin/pytest -q -n 2 --dist loadfile --durations=25 -m "not lerobot"
	XLA_FLAGS="$$XLA_FLAGS $(TEST_XLA)" $(LEROBOT_VENV)/bin/pytest -q -m lerobot tests/test_lerobot_export.py

test-fast: setup
	XLA_FLAGS="$$XLA_FLAGS $(TEST_XLA)" $(VENV)/bin/pytest -q -n 2 --dist loadfile -m "not slow and not extended and not lerobot"

lint: setup
	$(VENV)/bin/ruff check src tests examples scripts

clean:
	rm -rf out bench_out .pytest_cache .ruff_cache
