# convbki_ros: set-up, tests and demo. See README.md.
SHELL := /bin/bash
PYTHON := .venv/bin/python
# -q: one line per module; -ra: say why tests were skipped or failed.
PYTEST_FLAGS ?= -q -ra --durations=20  # the slowest tests listed: the suite has a 12-minute budget on 2 cores

.PHONY: setup test lint demo clean distclean

## setup: .venv/ with every dependency, then colcon build into install/ (idempotent)
setup:
	@scripts/setup.sh

## test: set-up, lint, then the test suite under test/
test: setup
	@.venv/bin/ruff check --quiet . && echo "ruff: clean"
	@scripts/venv_exec.sh $(PYTHON) -m pytest $(PYTEST_FLAGS) test

## lint: ruff over the whole tree (config in ruff.toml)
lint: setup
	@.venv/bin/ruff check .

## demo: set-up, then synthetic drive -> rosbag2 -> mapper node + play_bag over DDS -> map, PNG, mIoU (out/demo)
demo: setup
	@scripts/venv_exec.sh $(PYTHON) -m convbki_ros.tools.demo --out out/demo

## clean: remove colcon output, caches and out/ (keeps .venv/)
clean:
	rm -rf build install log out .pytest_cache .hypothesis
	find . -path ./.venv -prune -o -name __pycache__ -type d -prune -exec rm -rf {} +

## distclean: clean, and remove .venv/ too
distclean: clean
	rm -rf .venv
