"""What the tests read of a built model's SP fields (not part of the package: no user needs them)."""

from __future__ import annotations

from typing import List, Tuple

from torch import nn


def sp_fields(model: nn.Module) -> List[nn.Module]:
    """The fields of a nerfstudio model that carry the seam."""
    from sp_plugins.nerfstudio.seam import seam_fields

    return [f for _, f in seam_fields(model)]


def perturbed_calls(model: nn.Module) -> int:
    """Field calls the seam perturbed, over every field of ``model``."""
    return sum(f.sp_handle.perturbed_calls for f in sp_fields(model) if f.sp_handle is not None)


def installed_for_process() -> Tuple[str, ...]:
    """The patches installed for the whole process (our own console commands only)."""
    from sp_plugins.patches import registry

    return tuple(registry._installed)
