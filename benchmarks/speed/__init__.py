"""The pieces of `benchmarks/bench_speed.py`, imported as `speed.*` (the script puts `benchmarks/` on the path)."""
