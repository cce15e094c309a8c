"""Paired baseline-vs-SP studies on a shared harness (``bench.harness``): run one with ``python -m bench.NAME``;
the speed benchmarks with ``python -m bench.speed.NAME``."""
