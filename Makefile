# The two commands of the README: `make demo` runs the main job, `make test` runs the tests.
# Both set everything up first (Debian packages, .venv/, the project); a second run skips set-up.
VENV := .venv
export MUJOCO_GL ?= egl
export RAY_AUTH_MODE ?= disabled

.PHONY: setup demo test lint bench

setup:
	@bash scripts/setup.sh

demo: setup
	$(VENV)/bin/sygrid demo

test: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/python -m pytest -q

bench: setup
	$(VENV)/bin/sygrid bench physics
