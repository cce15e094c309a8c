"""Former path of :mod:`sp_plugins.nerfstudio.host.schedulers`, kept because ``config.yml`` files written
before it moved name its classes here (they load unchanged)."""

from sp_plugins.nerfstudio.host.schedulers import *  # noqa: F401,F403
