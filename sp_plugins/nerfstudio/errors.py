"""Re-export of :mod:`sp_plugins.adapter.errors` (one ``InputError`` for both hosts)."""

from sp_plugins.adapter.errors import InputError, install_input_error_hook

__all__ = ["InputError", "install_input_error_hook"]
