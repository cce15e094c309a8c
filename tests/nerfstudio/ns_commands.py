"""Only for ``test_guest.py`` (it imports ``ns_commands`` by its bare name): the runner lives in
:mod:`tests.helpers.ns_commands`. Delete this file once that import names ``tests.helpers``."""

from tests.helpers.ns_commands import ENV  # noqa: F401
