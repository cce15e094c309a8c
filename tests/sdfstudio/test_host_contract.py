"""The host contract (:mod:`tests.adapter.contract`) on sdfstudio, in its own environment:
the same items as nerfstudio and the toy host keep in ``tests/adapter/test_host_contract.py``."""

from __future__ import annotations

import pytest

from sp_plugins.adapter import hosts
from tests.adapter import contract

pytestmark = pytest.mark.usefixtures("patched")


@pytest.mark.parametrize("item", list(contract.ITEMS))
def test_sdfstudio_keeps_the_contract(item):
    contract.ITEMS[item](contract.SdfstudioDriver())


def test_sdfstudio_is_the_host_of_this_environment():
    assert {name for name, h in hosts.hosts().items() if h.available()} == {"sdfstudio"}
