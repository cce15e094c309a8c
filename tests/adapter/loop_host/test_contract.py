"""The plain loop keeps the host contract: every item, as the adapters of nerfstudio and sdfstudio do."""

from __future__ import annotations

import pytest

from tests.adapter import contract
from tests.adapter.loop_host.driver import LoopDriver
from tests.adapter.loop_host.host import HOST


@pytest.fixture(autouse=True)
def loop_registered():
    with contract.registered(HOST):
        yield


@pytest.mark.parametrize("item", list(contract.ITEMS))
def test_the_plain_loop_keeps_the_contract(item):
    contract.ITEMS[item](LoopDriver())


def test_a_loop_that_forgets_sp_stops_at_its_first_step():
    """The same loop without ``sp(x)`` handed to its field: every item that trains stops at the first step
    with ``SPNotReached`` (the reach check item's run among them), the attachment item fails; what needs no
    training (the table's preset, the box, the model class) holds."""

    class Forgetful(LoopDriver):
        def build(self, **sp):
            model = super().build(**sp)
            self.silence(model)
            return model

    results = contract.run(Forgetful())
    failed = {item for item, result in results.items() if result != "pass"}
    assert failed == {"sp_attached", "reach_check_fires", "callbacks_every_step", "checkpoint_round_trip", "eval_unperturbed"}, results
    assert all("SPNotReached" in results[item] for item in failed - {"sp_attached"}), results
