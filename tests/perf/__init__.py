"""Throughput and timing checks that need a quiet machine and retry trials: `make perf`, not `make test`
(the benches report these figures; the default run asserts behaviour)."""
