"""The old home of our sdfstudio method configs, now :mod:`sp_plugins.method_configs.sdfstudio`.

An environment installed before the move keeps entry points that name this module until it is reinstalled
(``pip install -e .``); it re-exports the configs, and nothing else imports it.
"""

from sp_plugins.method_configs.sdfstudio import *  # noqa: F401,F403
