"""Console entry points. When this process is one of our ``sp-*`` commands (we own it), importing
this package keeps the host-warning filters and the one-line error hook for the process (registry
entries ``host_warnings`` and ``input_error_hook``); imported anywhere else it changes nothing."""

from sp_plugins.patches import registry as _registry

if _registry.our_console_command() in _registry.get("host_warnings").owned_commands:
    _registry.install_for_process("host_warnings")
    _registry.install_for_process("input_error_hook")
