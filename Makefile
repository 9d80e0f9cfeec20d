# The two commands: `make demo` and `make test`. Everything they need is installed here:
# uv comes from the package index into .tools/ when it is not on PATH, then `uv sync` builds .venv/.
SHELL := /bin/bash
PYTHON ?= python3
UV := $(shell command -v uv 2>/dev/null || echo .tools/bin/uv)
VENV := .venv
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST

.PHONY: demo test bench sync clean

# --inexact: the ROS wheels ship colcon *.egg-info folders that an exact sync would delete
# (taking std_msgs/ and friends with them).
sync: $(UV)
	$(UV) sync --inexact --quiet

.tools/bin/uv:
	$(PYTHON) -m venv .tools
	.tools/bin/pip install --quiet uv

demo: sync
	$(VENV)/bin/python examples/demo.py

test: sync
	$(VENV)/bin/pytest

bench: sync
	$(VENV)/bin/python bench/bench.py
	$(VENV)/bin/python bench/fleet.py

clean:
	rm -rf $(VENV) .tools
