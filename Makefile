# Development workflow for cbcan_ros on a machine without a ROS install:
# ROS 2 Jazzy comes from PyPI wheels in .venv/, colcon builds into build/ install/ log/.
# On a real ROS 2 Jazzy install, a plain `colcon build` in a workspace works instead.

SHELL := /bin/bash
.SHELLFLAGS := -eu -o pipefail -c
.DEFAULT_GOAL := build

ROOT    := $(abspath $(dir $(lastword $(MAKEFILE_LIST))))
VENV    := $(ROOT)/.venv
PY      := $(VENV)/bin/python
PYTHON3 ?= python3
ROS_ENV := $(ROOT)/tools/ros-env
ARGS    ?=

VENV_STAMP  := $(VENV)/.installed
BUILD_STAMP := $(ROOT)/install/.cbcan_ros.built

# Everything that goes into the build.  Directories are listed too, so adding or
# removing a file (which changes the directory's mtime) also triggers a rebuild.
BUILD_INPUTS := $(ROOT)/package.xml $(ROOT)/CMakeLists.txt \
  $(shell cd $(ROOT) && find srv_defs cbcan_ros scripts config launch \
      -name __pycache__ -prune -o -print 2>/dev/null)

.PHONY: venv build test colcon-smoke run cli bench clean distclean

venv: $(VENV_STAMP)

$(VENV_STAMP): $(ROOT)/requirements.txt $(ROOT)/requirements-lock.txt
	test -x $(PY) || $(PYTHON3) -m venv $(VENV)
	_ROS_WHEELS_BOOTSTRAP_COMPLETE=1 $(PY) -m pip install --disable-pip-version-check -q \
	  -r $(ROOT)/requirements.txt -c $(ROOT)/requirements-lock.txt
	@# The wheels' exported CMake targets name the wheel builder's Python and NumPy
	@# include dirs; CMake refuses to configure an interface package until they
	@# point at this machine's.
	pyinc=$$(_ROS_WHEELS_BOOTSTRAP_COMPLETE=1 $(PY) -c 'import sysconfig; print(sysconfig.get_paths()["include"])'); \
	npinc=$$(_ROS_WHEELS_BOOTSTRAP_COMPLETE=1 $(PY) -c 'import numpy; print(numpy.get_include())'); \
	{ grep -rlZ --include='*.cmake' -e '/opt/python/cp311-cp311/' $(VENV)/share || true; } \
	  | xargs -0 -r sed -i \
	    -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include#$$npinc#g" \
	    -e "s#/opt/python/cp311-cp311/include/python3.11#$$pyinc#g"
	! grep -rl --include='*.cmake' -e '/opt/python/cp311-cp311/' $(VENV)/share
	touch $@

build: $(BUILD_STAMP)

# colcon in the workspace it is run in, with the PyPI-wheel ROS of .venv/.
COLCON_BUILD = env _ROS_WHEELS_BOOTSTRAP_COMPLETE=1 \
	  PATH="$(VENV)/bin:$$PATH" \
	  AMENT_PREFIX_PATH="$(VENV)" CMAKE_PREFIX_PATH="$(VENV)" \
	  LD_LIBRARY_PATH="$(VENV)/lib$${LD_LIBRARY_PATH:+:$$LD_LIBRARY_PATH}" \
	  $(VENV)/bin/colcon build --event-handlers console_direct- console_cohesion+ \
	    --cmake-args -DPython3_EXECUTABLE=$(PY) -DCMAKE_BUILD_TYPE=RelWithDebInfo

$(BUILD_STAMP): $(VENV_STAMP) $(BUILD_INPUTS)
	cd $(ROOT) && $(COLCON_BUILD)
	touch $@

# can_msgs (ros_canopen's can_msgs/msg/Frame, for the raw CAN topics) where no ROS install
# brings ros-jazzy-can-msgs: built from the released definition in a workspace of its own
# under test/, which a user's colcon build of this repository never finds (colcon does not
# look below a package). tools/ros-env puts it on the paths of the tests and `make run`.
CAN_MSGS_WS    := $(ROOT)/test/can_msgs_ws
CAN_MSGS_STAMP := $(CAN_MSGS_WS)/install/.can_msgs.built

build: $(CAN_MSGS_STAMP)
clean: clean-can-msgs

$(CAN_MSGS_STAMP): $(VENV_STAMP) $(shell find $(CAN_MSGS_WS)/src -print 2>/dev/null)
	cd $(CAN_MSGS_WS) && $(COLCON_BUILD)
	touch $@

.PHONY: clean-can-msgs
clean-can-msgs:
	rm -rf $(CAN_MSGS_WS)/build $(CAN_MSGS_WS)/install $(CAN_MSGS_WS)/log

# The `pytest` executable (not `python -m pytest`) leaves the working directory
# off sys.path, so the source cbcan_ros/ (no generated msg/srv) cannot shadow
# the installed package.
# Four worker processes (pytest-xdist) on 2 cores: most tests wait on devices, timeouts and
# node processes (with two workers the suite kept the cores busy about a third of its 12.5
# minutes), so four take about half the time. The tests that load both cores by themselves
# (conftest.HEAVY) share one worker, one after another.
test: build
	$(ROS_ENV) pytest -q -n 4 --dist loadgroup $(ROOT)/test $(ARGS)

# The repository built as a ROS user would (a fresh workspace, a plain `colcon build`), and
# the node run from that install: tools/colcon-smoke.
colcon-smoke: venv
	$(ROOT)/tools/colcon-smoke

run: build
	$(ROS_ENV) cbcan_node --ros-args -r __ns:=/can0 --params-file $(ROOT)/config/simulation.yaml $(ARGS)

cli: build
	$(ROS_ENV) cbcan_cli $(ARGS)

# Reports and node logs go to bench/out/ (ignored by git); bench/reference/ holds the
# results the docs compare against.
bench: build
	$(ROS_ENV) python $(ROOT)/bench/bench_sdo.py $(ARGS)
	$(ROS_ENV) python $(ROOT)/bench/bench_lss.py $(filter --quick,$(ARGS))
	$(ROS_ENV) python $(ROOT)/bench/bench_pdo.py $(ARGS)
	$(ROS_ENV) python $(ROOT)/bench/bench_drives.py $(filter --quick,$(ARGS))
	$(ROS_ENV) python $(ROOT)/bench/bench_control_rate.py $(filter --quick,$(ARGS))
	$(ROS_ENV) python $(ROOT)/bench/bench_raw.py $(filter --quick,$(ARGS))
	$(ROS_ENV) python $(ROOT)/bench/bench_shutdown.py $(filter --quick,$(ARGS))
	$(ROS_ENV) python $(ROOT)/bench/bench_boot.py $(filter --quick,$(ARGS))
	$(ROS_ENV) python $(ROOT)/bench/bench_program_download.py $(filter --quick,$(ARGS))

clean:
	rm -rf $(ROOT)/build $(ROOT)/install $(ROOT)/log $(ROOT)/.pytest_cache

distclean: clean
	rm -rf $(VENV)
