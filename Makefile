# Two commands on a fresh machine: `make demo` and `make test` (see README.md).
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
# re-install whenever pyproject.toml changes
STAMP_RUN  := $(VENV)/.installed-run
STAMP_TEST := $(VENV)/.installed-test
PROTOS := $(wildcard proto/cell/v1/*.proto)

.PHONY: demo test lint proto bench clean

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip

$(STAMP_RUN): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q -e .
	touch $@

$(STAMP_TEST): pyproject.toml | $(BIN)/python
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $@ $(STAMP_RUN)

demo: $(STAMP_RUN)
	$(BIN)/cell demo

test: $(STAMP_TEST)
	@# the two-host test needs `ip` (iproute2) and root; installed here where apt and root allow
	@command -v ip >/dev/null || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && \
		apt-get install -y -q iproute2 >/dev/null 2>&1; } || true
	$(BIN)/ruff check cell services tests examples
	$(BIN)/python -m pytest

lint: $(STAMP_TEST)
	$(BIN)/ruff check cell services tests examples
	$(BIN)/ruff format --check cell services tests examples

# regenerate the committed protobuf code (tests/test_proto.py fails when it is stale)
proto: $(STAMP_TEST)
	$(BIN)/python -m cell.protogen

bench: $(STAMP_RUN)
	$(BIN)/cell bench bus

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache
