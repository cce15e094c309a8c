"""The test suite. A package, as are its folders, so that ``from tests.helpers import ...`` names our
helpers and a test file's module is named by its path (``tests.nerfstudio.test_x``): two folders may
hold files of the same name (tests/bench, tests/patches and tests/sweeps have no ``__init__.py`` yet:
their files are still imported by their bare names). pytest's ``pythonpath = ["."]`` in
pyproject.toml puts the checkout first: torch-fidelity installs a top-level ``tests`` package of its own."""
