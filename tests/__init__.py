"""The test suite. A package so that ``from tests.helpers import ...`` names our helpers (pytest's
``pythonpath = ["."]`` in pyproject.toml puts the checkout first: torch-fidelity installs a
top-level ``tests`` package of its own)."""
