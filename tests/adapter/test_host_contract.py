"""One host contract, checked on every host: the same items (:mod:`tests.adapter.contract`)
on the toy host and nerfstudio here, on sdfstudio in its own environment
(``tests/sdfstudio/test_host_contract.py``); and a host with a broken hook fails them."""

from __future__ import annotations

import pytest

from sp_plugins.adapter import hosts
from tests.adapter import contract
from tests.adapter.toy_host import HOST as TOY

DRIVERS = {"toy": contract.ToyDriver, "nerfstudio": contract.NerfstudioDriver}


@pytest.fixture(autouse=True)
def toy_registered():
    with contract.registered(TOY):
        yield


@pytest.mark.parametrize("item", list(contract.ITEMS))
@pytest.mark.parametrize("host", list(DRIVERS))
def test_the_host_keeps_the_contract(host, item):
    contract.ITEMS[item](DRIVERS[host]())


def test_every_host_this_environment_has_is_checked_here():
    """nerfstudio is the host of this environment (sdfstudio's has its own module), and the toy host is registered."""
    available = {name for name, h in hosts.hosts().items() if h.available()}
    assert available == {"nerfstudio", "toy"}, available
    assert set(DRIVERS) == available and set(contract.drivers_here()) - set(DRIVERS) == {"toy, broken sp_training_callback"}


def test_a_host_with_a_broken_hook_fails_the_items_that_need_it():
    """The toy host whose ``sp_training_callback`` makes callbacks no trainer runs: the schedule never
    moves and the reach check never runs; the rest of the contract still holds."""
    results = contract.run(contract.broken_toy_driver())
    failed = {item for item, result in results.items() if result != "pass"}
    assert failed == {"callbacks_every_step", "reach_check_fires"}, results
    with pytest.raises(AssertionError, match=r"^\[\(0, 0\.1\), \(0, 0\.1\)"):
        contract.callbacks_every_step(contract.broken_toy_driver())


def test_each_hosts_table_names_exactly_the_methods_its_entry_points_register():
    """The method lists other front ends read (nerfbaselines, the docs) are the tables'; a method
    registered but missing from its table, or listed but not registered, fails here."""
    import tomllib
    from pathlib import Path

    from sp_plugins.nerfstudio import table as ns_table
    from sp_plugins.sdfstudio import table as sdf_table

    eps = tomllib.loads((Path(__file__).resolve().parents[2] / "pyproject.toml").read_text())["project"]["entry-points"]
    assert sorted(ns_table.OUR_METHODS + ns_table.OUR_SDF_METHODS) == sorted(eps["nerfstudio.method_configs"])
    assert sorted(sdf_table.OUR_METHODS) == sorted(eps["sp_plugins.sdfstudio_methods"])
    assert sorted(eps["sp_plugins.hosts"]) == ["nerfstudio", "sdfstudio"]
