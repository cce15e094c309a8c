"""In-process checks of the nerfbaselines front end: the specs nerfbaselines finds through its entry
point, ``--set`` typing, the ``*_fine`` output aliases, the SDFStudio loader's refusals. (The commands
themselves run in test_nerfbaselines.py.)"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
from typing import Literal, Optional, Tuple

import pytest

from sp_plugins.nerfbaselines.overrides import OverrideError, apply_overrides


class Mode(enum.Enum):
    OFF = "off"
    ON = "on"


@dataclass
class Inner:
    enabled: bool = True
    alpha0: float = 0.01
    end: Optional[float] = None


@dataclass
class Model:
    sp: Inner = field(default_factory=Inner)
    num_samples: Tuple[int, int] = (8, 8)
    background: Literal["white", "black", "random"] = "white"
    mode: Mode = Mode.OFF
    steps: int = 10


@dataclass
class Config:
    model: Model = field(default_factory=Model)


def test_set_values_are_typed_to_their_field():
    config = Config()
    apply_overrides(config, {"model.sp.enabled": "False", "model.sp.alpha0": "0.03", "model.sp.end": "none",
                             "model.num_samples": "16,4", "model.background": "black", "model.mode": "on",
                             "model.steps": "1e3"}, "m")
    assert config.model.sp.enabled is False and config.model.sp.alpha0 == 0.03 and config.model.sp.end is None
    assert config.model.num_samples == (16, 4) and config.model.background == "black" and config.model.mode is Mode.ON
    assert config.model.steps == 1000 and isinstance(config.model.steps, int)
    apply_overrides(config, {"model.sp.enabled": True, "model.sp.end": "0.2"}, "m")  # a preset's own values too
    assert config.model.sp.enabled is True and config.model.sp.end == 0.2


@pytest.mark.parametrize("key, value, words", [
    ("model.sp.alpha00", "1", ["no key 'alpha00' at model.sp", "did you mean alpha0", "alpha0, enabled, end"]),
    ("model.sp.enabled", "maybe", ["takes True or False"]),
    ("model.num_samples", "1,2,3", ["takes 2 comma-separated values"]),
    ("model.background", "green", ["'white', 'black', 'random'"]),
    ("model.steps.x", "1", ["model.steps is a int"]),
])
def test_a_set_that_cannot_apply_is_one_line(key, value, words):
    with pytest.raises(OverrideError) as err:
        apply_overrides(Config(), {key: value}, "m")
    assert "\n" not in str(err.value) and str(err.value).startswith(f"--set {key}")
    for word in words:
        assert word in str(err.value), str(err.value)


def test_fine_outputs_are_read_as_the_plain_names():
    from sp_plugins.nerfbaselines.outputs import with_output_aliases

    class TwoPass:
        def get_outputs_for_camera_ray_bundle(self, bundle):
            return {"rgb_coarse": 0, "rgb_fine": 1, "accumulation_fine": 2, "depth_fine": 3}

    class OnePass:
        def get_outputs_for_camera_ray_bundle(self, bundle):
            return {"rgb": 5, "rgb_fine": 1}

    assert with_output_aliases(TwoPass)().get_outputs_for_camera_ray_bundle(None)["rgb"] == 1
    out = with_output_aliases(TwoPass)().get_outputs_for_camera_ray_bundle(None)
    assert (out["accumulation"], out["depth"]) == (2, 3)
    assert with_output_aliases(OnePass)().get_outputs_for_camera_ray_bundle(None)["rgb"] == 5


def test_specs_reach_nerfbaselines_through_its_entry_point():
    import nerfbaselines

    methods = nerfbaselines.get_supported_methods()
    for name in ("sp-nerfacto", "sp-mipnerf", "sp-vanilla-nerf", "sp-tensorf", "sp-neus-hashgrid", "sp-neuralangelo-lite",
                 "sp-relu-field", "mipnerf", "vanilla-nerf", "neus-hashgrid", "neuralangelo-lite", "relu-field",
                 "nerfacto+sp", "mipnerf+sp", "vanilla-nerf+sp"):
        assert name in methods, name
        assert nerfbaselines.get_method_spec(name)["backends_order"][0] == "python"
    assert {"sdfstudio-layout", "blender-layout"} <= nerfbaselines.get_supported_dataset_loaders()
    assert "sp-scene" in nerfbaselines.get_supported_evaluation_protocols()
    # nerfacto+sp keeps nerfbaselines' own nerfacto presets, so the two are a like-for-like pair
    ours, theirs = (nerfbaselines.get_method_spec(m)["presets"] for m in ("nerfacto+sp", "nerfacto"))
    assert ours["blender"] == theirs["blender"]
    assert {k: v for k, v in ours["sp-scene"].items() if not k.startswith("@")} == \
        {"pipeline.datamanager.dataparser": "blender-data",
         **{k: v for k, v in theirs["blender"].items() if not k.startswith("@") and k != "pipeline.datamanager.dataparser"}}


def test_sdfstudio_loader_refuses_other_folders_in_one_line(tmp_path):
    from sp_plugins.nerfbaselines.sdfstudio_loader import load_sdfstudio_dataset

    with pytest.raises(FileNotFoundError, match="no meta_data.json in"):
        load_sdfstudio_dataset(str(tmp_path), "train")
    (tmp_path / "meta_data.json").write_text("{}")
    with pytest.raises(FileNotFoundError, match=r"meta_data_test.json is missing in .* test split"):
        load_sdfstudio_dataset(str(tmp_path), "test")


def test_scenes_load_through_nerfbaselines_loaders(tmp_path):
    """sp-scene's Blender layout through nerfbaselines' own Blender loader (its nb-info.json; the image
    size from transforms_*.json, which the loader otherwise takes as 800 px), the SDFStudio layout
    through ours (with its box), the fox capture through nerfbaselines' nerfstudio loader."""
    import os

    from nerfbaselines.datasets import load_dataset

    from sp_plugins.data import make_tiny_scene
    from tests.helpers.fox_crop import FOX, fox_missing

    root = make_tiny_scene(tmp_path / "scene", mesh="sphere").root
    blender = load_dataset(str(root / "blender"), split="train", load_features=False)
    assert blender["metadata"]["id"] == "sp-scene" and blender["metadata"]["evaluation_protocol"] == "sp-scene"
    assert blender["cameras"].image_sizes.tolist() == [[32, 32]] * 8
    sdf = load_dataset(str(root / "sdfstudio"), split="test", load_features=False)
    assert len(sdf["image_paths"]) == 2 and sdf["metadata"]["scene_box"] == [[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]
    why = fox_missing()
    if why:
        if os.environ.get("CI") == "true":
            pytest.fail(why)
        pytest.skip(why)
    assert len(load_dataset(str(FOX), split="test", load_features=False)["image_paths"]) == 5
