"""Benchmarks: one driver (`python -m perf`), one module per subject; medians against a named peer, JSON out."""
