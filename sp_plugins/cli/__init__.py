"""Console entry points. Importing this package installs the host-warning filters: we own the
process of every ``sp-*`` command (see :mod:`sp_plugins.host_warnings`)."""

from sp_plugins.host_warnings import filter_host_warnings

filter_host_warnings()
