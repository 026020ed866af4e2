# Two commands on a fresh machine: `make demo` and `make test` (see README.md).
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
# re-install whenever pyproject.toml changes
STAMP_RUN  := $(VENV)/.installed-run
STAMP_TEST := $(VENV)/.installed-test
PROTOS := $(wildcard proto/cell/v1/*.proto)

.PHONY: demo test test-slow test-tools perf lint proto bench clean bpf bpf-if-possible
# the XDP data plane ([dataplane] backend = "xdp"): its BPF object, built with clang from the C source
BPF_SRC := cell/dataplane/xdp/dataplane.bpf.c
BPF_OBJ := cell/dataplane/xdp/dataplane.bpf.o
BPF_CFLAGS := -O2 -g -Wall -target bpf -I/usr/include/$(shell uname -m)-linux-gnu

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
	@$(MAKE) -s bpf-if-possible
	$(BIN)/cell demo

# the Debian tools the tests use, installed where apt and root allow (a skip for one fails under CI)
test-tools:
	@# the two-host test needs `ip` (iproute2) and root; installed here where apt and root allow
	@command -v ip >/dev/null || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && \
		apt-get install -y -q iproute2 >/dev/null 2>&1; } || true
	@# the modular robot's cycle in C (cell/snp/cycle.c) is built with cc on first use
	@command -v cc >/dev/null || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && \
		apt-get install -y -q gcc libc6-dev >/dev/null 2>&1; } || true
	@# the web viewer's test opens the printed address in a real browser (Debian's headless Chromium)
	@command -v chromium >/dev/null || { [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && \
		{ apt-get install -y -q --no-install-recommends chromium >/dev/null 2>&1 || \
		{ apt-get update -q >/dev/null 2>&1 && \
		apt-get install -y -q --no-install-recommends chromium >/dev/null 2>&1; }; }; } || true
	@$(MAKE) -s bpf-if-possible

test: $(STAMP_TEST) test-tools
	$(BIN)/ruff check cell services tests examples
	$(BIN)/lint-imports
	$(BIN)/mypy
	$(BIN)/python -m pytest -m 'not perf and not slow'

# the end-to-end runs of many seconds each (marked slow: campaigns, benches' harnesses, the demo, whole
# cells through long scenarios); CI runs them after `make test` (.ci/run)
test-slow: $(STAMP_TEST) test-tools
	$(BIN)/python -m pytest -m 'slow and not perf'

# throughput and timing checks that need a quiet machine (tests/perf, and the SnP cycle's end-to-end
# runs: marked perf), then the benches' quick checks
perf: $(STAMP_TEST)
	@$(MAKE) -s bpf-if-possible
	$(BIN)/python -m pytest -m perf
	$(BIN)/cell bench bus --messages 50000 --rounds 1 --json | tail -1
	$(BIN)/cell bench snp --seconds 1 --json | tail -1

bpf: $(BPF_OBJ)

# clang and libbpf's headers, installed where apt and root allow (the package lists updated once if
# they are empty), then the object
$(BPF_OBJ): $(BPF_SRC)
	@{ command -v clang >/dev/null && [ -e /usr/include/bpf/bpf_helpers.h ]; } || \
		{ [ "$$(id -u)" = 0 ] && command -v apt-get >/dev/null && \
		{ apt-get install -y -q clang llvm libbpf-dev >/dev/null 2>&1 || \
		{ apt-get update -q >/dev/null 2>&1 && apt-get install -y -q clang llvm libbpf-dev >/dev/null 2>&1; }; }; } || true
	clang $(BPF_CFLAGS) -c $< -o $@

# the object when this machine can build it; without it the XDP backend refuses to start, saying so
bpf-if-possible:
	@$(MAKE) -s bpf 2>/dev/null || echo "note: $(BPF_OBJ) not built (needs clang and libbpf-dev); the XDP backend and its tests are off"

lint: $(STAMP_TEST)
	$(BIN)/ruff check cell services tests examples
	$(BIN)/ruff format --check cell services tests examples
	$(BIN)/lint-imports

# regenerate the committed protobuf code (tests/bus/test_proto.py fails when it is stale)
proto: $(STAMP_TEST)
	$(BIN)/python -m cell.protogen

bench: $(STAMP_RUN)
	$(BIN)/cell bench bus

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache $(BPF_OBJ)
