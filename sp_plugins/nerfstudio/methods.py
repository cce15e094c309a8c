"""The old home of our nerfstudio method configs, now :mod:`sp_plugins.method_configs.nerfstudio`.

An environment installed before the move keeps entry points that name this module until it is reinstalled
(``pip install -e .``); nerfstudio loads every entry point in every ``ns-*`` command, so a missing module here
would stop nerfstudio for every method, ours or not. It re-exports the configs; nothing else imports it.
"""

from sp_plugins.method_configs.nerfstudio import *  # noqa: F401,F403
