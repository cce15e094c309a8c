"""Console entry points. When this process is one of our ``sp-*`` commands (we own it), importing
this package keeps the host-warning filters for the process (registry entry ``host_warnings``);
imported anywhere else (a test, a script, nerfstudio) it changes nothing."""

from sp_plugins.patches import registry as _registry

if _registry.our_console_command() in _registry.get("host_warnings").owned_commands:
    _registry.install_for_process("host_warnings")
