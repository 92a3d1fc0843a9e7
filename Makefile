# The two commands of the README. Both create .venv on first use.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
PORT ?= 8000

.PHONY: demo test install bytecode services browser lowest full-reference

$(BIN)/navsim-lb: pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -c constraints.txt -e ".[dev]"
	touch $(BIN)/navsim-lb

# An editable install leaves our modules uncompiled; where PYTHONDONTWRITEBYTECODE is set (many containers)
# every command would compile them again, a fifth of `navsim-lb score`'s start-up: compile them here, at every
# make (a pull changes modules; compileall skips those whose bytecode is up to date, in 0.2 s).
bytecode: $(BIN)/navsim-lb
	$(BIN)/python -m compileall -q navsim_lb scorer server worker web > /dev/null

install: bytecode

## make demo: SQLite + embedded broker + one worker + API and web on $(PORT); Ctrl-C stops everything.
demo: install
	PORT=$(PORT) $(BIN)/navsim-lb demo

## make test: everything CI runs (.ci/run calls exactly this): lint, types, the tests, the regression goldens.
## The suite runs on two processes, a module to each (module fixtures start once), in the collected order: the
## fault tests go first (tests/conftest.py), so that their waits (kills, outages, deadlines) overlap the rest.
## The slowest tests are listed.
test: install services browser
	$(BIN)/ruff check --quiet .
	$(BIN)/ruff format --check --quiet .
	$(BIN)/mypy
	$(BIN)/pytest -q -p no:cacheprovider -n 2 --dist loadscope --no-loadscope-reorder --durations=15 -m "not full_reference"
	$(BIN)/navsim-lb regress

## PostgreSQL and Redis must answer for the service tests; start them when they do not.
services:
	./.ci/services

## Debian's chromium for the browser tests (tests/test_web_browser.py); installed when missing.
browser:
	./.ci/browser

## make lowest: the suite on the lowest versions pyproject.toml allows (slow; run when a lower bound changes).
lowest: services browser
	./.ci/lowest

## make full-reference: every token of the official two-stage reference (../shared/reference/epdms-two-stage), scored
## from scenes with reactive traffic and compared bit for bit; about 20 minutes on 2 cores, so make test leaves it out.
full-reference: install
	$(BIN)/pytest -q -p no:cacheprovider -m full_reference tests/test_two_stage_full_reference.py
