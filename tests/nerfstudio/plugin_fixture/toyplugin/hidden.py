"""A model that builds its field through a module object, not a module-level class name: the seam is
attached to the field instance the model built, so the SP variant reaches it all the same
(tests/nerfstudio/test_with_sp.py)."""

from dataclasses import dataclass, field
from typing import Type

import toyplugin.fieldlib as fieldlib
from toyplugin.model import ToyModel, ToyModelConfig


class HiddenFieldModel(ToyModel):
    def populate_modules(self) -> None:
        super().populate_modules()
        self.field = fieldlib.PlainField(self.config.width)


@dataclass
class HiddenFieldModelConfig(ToyModelConfig):
    _target: Type = field(default_factory=lambda: HiddenFieldModel)
