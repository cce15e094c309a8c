"""Paired baseline-vs-SP benchmarks. Run one with ``python -m bench.NAME``."""
