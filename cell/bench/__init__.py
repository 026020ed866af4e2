"""Benchmarks behind `cell bench ...`: each measures a hot path next to a baseline in the same run."""
