"""Input encodings for neural fields, all differentiable (twice) with respect to their inputs."""

from sp_plugins.encodings.frequency import FrequencyEncoding
from sp_plugins.encodings.hashgrid import HashGrid, resolve_backend, tcnn_available, tcnn_usable
from sp_plugins.encodings.triplane import TriplaneEncoding

__all__ = ["FrequencyEncoding", "HashGrid", "TriplaneEncoding", "resolve_backend", "tcnn_available", "tcnn_usable"]
