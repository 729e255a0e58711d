"""The pieces of `research/benchmarks/bench_speed.py`, imported as `speed.*` (the script puts `research/benchmarks/` on the path)."""
