"""Benchmarks, run by hand: `python -m benchmarks` (all) or `python -m benchmarks.bench_<name>`."""
