"""Input encodings for neural fields, all differentiable with respect to their inputs."""

from sp_plugins.encodings.hashgrid import HashGrid, resolve_backend, tcnn_available

__all__ = ["HashGrid", "resolve_backend", "tcnn_available"]
