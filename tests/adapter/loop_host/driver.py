"""The plain loop's driver for the host contract (:class:`tests.adapter.contract.Driver`)."""

from __future__ import annotations

from typing import Any, List, Optional, Tuple

import torch
from torch import nn

from sp_plugins import SPConfig, SPNotReached
from tests.adapter.contract import Driver, Observe
from tests.adapter.loop_host.host import BOX, HOST, RUN_LENGTH, LoopModel, preset_for, train_loop


class LoopDriver(Driver):
    host = HOST.name
    reach_error = SPNotReached

    def model_class(self) -> type:
        return LoopModel

    def build(self, **sp: Any) -> nn.Module:
        return LoopModel(SPConfig(**{"boundary": "reflect", **sp}))

    def method_sp(self) -> Tuple[SPConfig, Any]:
        return preset_for(None), None

    def train(self, model: nn.Module, steps: int, total: int, observe: Optional[Observe] = None) -> None:
        assert total == RUN_LENGTH, f"the loop's runs are {RUN_LENGTH} steps long (SPRun is built with its length)"
        train_loop(model, steps, observe)

    def evaluate(self, model: nn.Module) -> torch.Tensor:
        model.eval()
        with torch.no_grad():
            return model.query(torch.linspace(-0.9, 0.9, 24).view(8, 3))

    def silence(self, model: nn.Module) -> None:
        model.hands_sp_to_field = False  # the loop forgot to hand sp(x) to its field

    def expected_box(self, model: nn.Module) -> torch.Tensor:
        return BOX

    def sp_readers(self, model: nn.Module) -> List[nn.Module]:
        return [model.field] if model.hands_sp_to_field else []
