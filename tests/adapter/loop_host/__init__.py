"""A fourth host of another shape: a plain PyTorch training loop on :class:`sp_plugins.SPRun`, no host
framework, no adapter base class. Everything it needs is in this folder (its method table, its registry
entry, its model, its contract driver); it passes the host contract (``tests/adapter/contract.py``) as the
adapters of nerfstudio and sdfstudio do (``test_contract.py``)."""
