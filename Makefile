# Set-up, tests, demo and benchmarks of cva_confidence_ros on a fresh machine.
# `make demo` and `make test` are the two commands of the README; both install what they need.

PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# torch is pinned: 2.13.0 is the CPU build that lies on this machine's disk; a bare `torch`
# pulls a multi-GB CUDA build from the index. lifecycle_msgs (cva-lifecycle-node, cva-lifecycle)
# comes with a ROS install of rclpy, not with its wheel.
TORCH := torch==2.13.0
DEPS := numpy scipy opencv-python-headless scikit-image numba matplotlib tqdm \
	rosbags pyyaml 'ros-jazzy-rclpy[fastrtps]' ros-jazzy-common-interfaces \
	ros-jazzy-lifecycle-msgs mccnn onnx onnxruntime
TEST_DEPS := pytest pytest-timeout colcon-core colcon-python-setup-py colcon-ros ruff mypy
DEMO_OUT ?= out/demo

.PHONY: setup test demo bench bench-fast lint clean

setup: $(STAMP)

$(STAMP): setup.py setup.cfg package.xml Makefile
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q $(TORCH)
	$(BIN)/python -m pip install -q $(TORCH) $(DEPS) $(TEST_DEPS)
	$(BIN)/python -m pip install -q --no-deps -e .
	touch $@

test: setup
	$(BIN)/python -m pytest -q -p no:cacheprovider --timeout=900 test

demo: setup
	$(BIN)/cva-demo --out $(DEMO_OUT)

bench: setup
	$(BIN)/cva-benchmark --json out/bench.json

# CVA-Net fast paths at 320x240, D = 64, 1 thread; auc_rel needs the develop split.
bench-fast: setup
	OMP_NUM_THREADS=1 MKL_NUM_THREADS=1 NUMBA_NUM_THREADS=1 $(BIN)/cva-benchmark --suite fast \
		$(if $(wildcard ../shared/data),--data-root ../shared/data,) --json out/bench_fast.json

lint: setup
	$(BIN)/ruff check cva_confidence_ros msg_tools test
	$(BIN)/mypy  # the package and msg_tools, as setup.cfg lists them

clean:
	rm -rf $(VENV) build install log *.egg-info out
