"""What the nerfbaselines specs know about single methods (their names, which get SP, which presets): the one
place :mod:`~sp_plugins.nerfbaselines.specs` reads them from. Plain data: imports nothing."""

from __future__ import annotations

from typing import Dict

NERFSTUDIO_BASELINES = ("mipnerf", "vanilla-nerf")
"""nerfstudio methods nerfbaselines 1.2.12 has no spec for (its ``nerf`` and ``tensorf`` are other code)."""

SP_ON = ("nerfacto", "mipnerf", "vanilla-nerf")
"""``<id>+sp`` (and ``<id>+sp-off``): nerfbaselines' nerfstudio-backed ``nerfacto`` and the two above."""

NERFACTO_FAMILY = ("nerfacto", "sp-nerfacto")
"""nerfstudio methods that train on ``sp-scene`` folders with nerfbaselines' own Blender preset of nerfacto (near and
far planes, no scene contraction, a white background)."""

SIZE_PRESETS: Dict[str, Dict[str, str]] = {"nerfacto": {"big": "nerfacto-big", "huge": "nerfacto-huge"}}
"""nerfbaselines' size presets of a method (preset name -> the nerfstudio method it trains), kept by its ``+sp`` id."""
