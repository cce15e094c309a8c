"""A plugin method that downloads backbone weights while its model is built (as some plugins on
the package index do), run without network: the download raises ``URLError``. Simulated here
without touching the network, so the test is the same on a machine that has one."""

from __future__ import annotations

import urllib.error
from dataclasses import dataclass, field
from typing import Type

from toyplugin.model import ToyModel, ToyModelConfig


def fetch_backbone() -> None:
    """What ``urllib.request.urlopen`` raises for a weights URL when no name resolves."""
    raise urllib.error.URLError(OSError(-3, "Temporary failure in name resolution"))


class DownloadModel(ToyModel):
    def populate_modules(self) -> None:
        super().populate_modules()
        fetch_backbone()


@dataclass
class DownloadModelConfig(ToyModelConfig):
    _target: Type = field(default_factory=lambda: DownloadModel)
