"""Former path of :mod:`sp_plugins.nerfstudio.relu_field.model`, kept because ``config.yml`` files written
before it moved name its classes here (they load unchanged)."""

from sp_plugins.nerfstudio.relu_field.model import *  # noqa: F401,F403
