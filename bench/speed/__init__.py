"""Speed benchmarks (no training study): ``python -m bench.speed.NAME`` or ``sp-bench NAME``."""
