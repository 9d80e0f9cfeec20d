# The two commands: `make demo` and `make test`. Everything they need is installed here:
# uv comes from the package index into .tools/ when it is not on PATH, then `uv sync` builds .venv/.
SHELL := /bin/bash
PYTHON ?= python3
UV := $(shell command -v uv 2>/dev/null || echo .tools/bin/uv)
VENV := .venv
export ROS_AUTOMATIC_DISCOVERY_RANGE ?= LOCALHOST

.PHONY: demo test lint bench bench-profile sync clean wheels

# --inexact: the ROS wheels ship colcon *.egg-info folders that an exact sync would delete
# (taking std_msgs/ and friends with them). Bytecode is compiled here, the installed packages' and
# this tree's own: where PYTHONDONTWRITEBYTECODE is set, each process would otherwise compile every
# module it imports, every time (about half a second of each rosgate start).
sync: $(UV)
	$(UV) sync --inexact --quiet --compile-bytecode
	$(VENV)/bin/python -m compileall -q core/src plugins libs tools examples tests/thirdparty >/dev/null

.tools/bin/uv:
	$(PYTHON) -m venv .tools
	.tools/bin/pip install --quiet uv

# every distribution of this repository as a wheel, into $(DIST)/: what `pip install --find-links
# dist ...` (the README's install line) installs from, until they are on the package index
DIST ?= dist
wheels: $(UV)
	$(UV) build --all-packages --wheel --quiet --out-dir $(DIST)

demo: sync
	$(VENV)/bin/python examples/demo.py

# the tests on PYTEST_WORKERS processes at once (pytest-xdist): most of them wait on bridge
# processes and DDS discovery, not on the cores. Each worker takes a slice of the run's DDS
# domains (ROSGATE_TEST_DOMAINS, default 20-119) and the ports that go with them
# (tests/conftest.py); tests marked xdist_group share one worker. PYTEST_WORKERS=0: one process.
PYTEST_WORKERS ?= 3
test: sync lint
	$(VENV)/bin/pytest -n $(PYTEST_WORKERS) --dist loadgroup

# lint findings (ruff check), the core's layers and no import cycle in any package (import-linter
# contracts) nor among the scripts of bench/, tests/ and examples/ (tools/import_cycles.py), and
# types (mypy: core and plugins); the rules are in pyproject.toml
lint: sync
	$(VENV)/bin/ruff check .
	$(VENV)/bin/lint-imports --no-cache
	$(VENV)/bin/python tools/import_cycles.py
	$(VENV)/bin/mypy

# make bench [BASE=REV] [BENCH_ARGS="--quick --only 2.5kB"]: BASE also runs the bridged paths with
# the rosgate of git revision REV (a temporary worktree with its own .venv), row beside row.
bench: sync
	UV=$(abspath $(UV)) $(VENV)/bin/python bench/bench.py $(if $(BASE),--base $(BASE)) $(BENCH_ARGS)
	$(VENV)/bin/python bench/fleet.py
	UV=$(abspath $(UV)) $(VENV)/bin/python bench/constrained.py $(if $(BASE),--base $(BASE))
	$(VENV)/bin/python bench/serial_link.py
	$(VENV)/bin/python bench/idle_routes.py
	$(VENV)/bin/python bench/shaped.py

# py-spy profiles of bridge A and bridge B (udp/cdr/none, 2.5 kB) into bench/profiles/; the table
# goes to stdout only. Another path: BENCH_ARGS="--profile-path tcp/cdr/none".
bench-profile: sync
	UV=$(abspath $(UV)) $(VENV)/bin/python bench/bench.py --only 2.5kB --path bare --profile \
		--out - $(if $(BASE),--base $(BASE)) $(BENCH_ARGS)

# every decoder that takes bytes from the network, 10^6 generated and mutated inputs each
# (atheris, coverage-guided; tests/fuzz/). FUZZ_ARGS="--only cbor_codec --runs 100000" narrows it.
fuzz: sync
	$(VENV)/bin/python tests/fuzz/campaign.py $(FUZZ_ARGS)

# a client/server pair at 1,000 msg/s on four topics for 30 minutes under a garbage flood,
# reconnect churn and an idle-connection flood (tests/soak/); SOAK_ARGS="--minutes 5" shortens it
soak: sync
	$(VENV)/bin/python tests/soak/soak.py $(SOAK_ARGS)

clean:
	rm -rf $(VENV) .tools
