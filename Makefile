# The two commands: `make demo` (the main job) and `make test` (every test). Both bootstrap the
# project venv from requirements.lock and build the colcon workspace first, idempotently.
# `make lint`: ruff over the tree and mypy over the algorithm cores, in the same venv.
SHELL := /bin/bash
.SHELLFLAGS := -eo pipefail -c
ROOT := $(CURDIR)
VENV := $(ROOT)/.venv
ENV := . $(ROOT)/tools/env.sh
BUILD_INPUTS := $(shell find msg src -type f -not -path '*/__pycache__/*' -not -name '*.pyc' 2>/dev/null)
PYTEST_ARGS ?=
# `make ros2-tools`: the real ros2cli and launch for the pinned venv, which PyPI does not have,
# from a ros2-tools bundle (a directory with an install.sh) that ROS2_TOOLS_SRC names; .ci/run
# sets it. A ROS 2 Jazzy install has them already (docs/install.md).
ROS2_TOOLS_SRC ?=

.PHONY: all venv build demo test lint bench lock clean distclean ros2-tools

all: build

venv: $(VENV)/.lock.sha256
$(VENV)/.lock.sha256: requirements.lock tools/bootstrap.sh tools/fix_rosidl_paths.py
	bash tools/bootstrap.sh

build: install/.built
install/.built: $(VENV)/.lock.sha256 $(BUILD_INPUTS)
	$(ENV) && colcon --log-base log build --base-paths msg src --build-base build --install-base install \
	  --symlink-install --event-handlers console_direct- console_start_end+ \
	  --cmake-args -DBUILD_TESTING=OFF -DPython3_EXECUTABLE=$(VENV)/bin/python
	touch $@

demo: build
	@$(ENV) && python -c 'import launch_ros' 2>/dev/null || { echo "demo: the mission starts its launch file through launch, which this venv lacks: make ros2-tools ROS2_TOOLS_SRC=<bundle> (docs/install.md)" >&2; exit 1; }
	$(ENV) && python -m coop_bringup.mission --out out

test: build
	$(ENV) && python -m pytest -n 2 --dist loadfile --no-loadscope-reorder $(PYTEST_ARGS)

ros2-tools: venv
	@test -n "$(ROS2_TOOLS_SRC)" || { echo "ros2-tools: set ROS2_TOOLS_SRC to a ros2-tools bundle (docs/install.md)" >&2; exit 1; }
	@test -f "$(ROS2_TOOLS_SRC)/install.sh" || { echo "ros2-tools: no $(ROS2_TOOLS_SRC)/install.sh (ROS2_TOOLS_SRC)" >&2; exit 1; }
	set +u && $(ENV) && bash "$(ROS2_TOOLS_SRC)/install.sh" .ros2-tools

# mypy.ini says which modules are the cores
lint: venv
	$(ENV) && ruff check . && mypy

bench: build
	$(ENV) && for b in bench/*.py; do python $$b --json out/bench/$$(basename $$b .py).json; done

lock:
	python3 -m venv /tmp/coop-lock-venv && /tmp/coop-lock-venv/bin/pip install -q --dry-run \
	  --ignore-installed --report /tmp/coop-lock-report.json -r requirements.in
	python3 tools/lock.py /tmp/coop-lock-report.json > requirements.lock

clean:
	rm -rf build install log out

distclean: clean
	rm -rf $(VENV)
