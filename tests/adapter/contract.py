"""The host contract: what every host adapter must do, as checks any host's driver runs.

A *driver* builds a small SP model the way its host does and runs it the way the host's trainer
does (:class:`Driver`); each contract item is a function of a driver that raises ``AssertionError``
when the host breaks it (:data:`ITEMS`). ``tests/adapter/test_host_contract.py`` runs every item on
the toy host and nerfstudio, ``tests/sdfstudio/test_host_contract.py`` on sdfstudio (its own
environment); ``python -m tests.adapter.contract`` prints the table, a host with a broken hook
included.
"""

from __future__ import annotations

import abc
import contextlib
import copy
import dataclasses
import functools
import importlib
from types import SimpleNamespace
from typing import Any, Callable, Dict, Iterator, List, Optional, Tuple

import torch
from torch import nn

from sp_plugins.adapter import hosts
from sp_plugins.adapter.errors import InputError
from sp_plugins.adapter.field import SPFieldMixin
from sp_plugins.adapter.model import unimplemented
from sp_plugins.core import SPConfig, StochasticPreconditioner

Observe = Callable[[int], None]


@contextlib.contextmanager
def registered(host: hosts.Host) -> Iterator[None]:
    """``host`` in the registry while the block runs (a test's host registers at run time)."""
    hosts.register(host)
    try:
        yield
    finally:
        hosts.unregister(host.name)


class Driver(abc.ABC):
    """What a host's driver provides (a toy host, nerfstudio, sdfstudio)."""

    host: str
    """The host's registry name."""
    reach_error: type = InputError
    """What the host raises when SP reached no field (an adapter's one-line ``InputError``; a plain loop on
    :class:`~sp_plugins.SPRun`: ``SPNotReached``)."""

    def sp_readers(self, model: nn.Module) -> List[nn.Module]:
        """The modules SP's moved positions are handed to: a host adapter's fields holding the model's
        preconditioner (a plain loop says which field its loop hands ``sp(x)`` to)."""
        return [m for m in model.modules() if isinstance(m, SPFieldMixin) and m.sp is model.sp]

    @abc.abstractmethod
    def model_class(self) -> type:
        """The SP model class the host builds (its hooks are checked)."""

    @abc.abstractmethod
    def build(self, **sp: Any) -> nn.Module:
        """A small SP model as the host builds it, its ``sp`` settings changed by ``sp``."""

    @abc.abstractmethod
    def method_sp(self) -> Tuple[SPConfig, Any]:
        """``(sp settings an SP method of the host gets, that method's host model config)``."""

    @abc.abstractmethod
    def train(self, model: nn.Module, steps: int, total: int, observe: Optional[Observe] = None) -> None:
        """``steps`` training iterations as the host's trainer runs them (its callbacks before and
        after each), ``observe(step)`` after each."""

    @abc.abstractmethod
    def evaluate(self, model: nn.Module) -> torch.Tensor:
        """The model's output on fixed inputs, as evaluation computes it."""

    @abc.abstractmethod
    def silence(self, model: nn.Module) -> None:
        """Make the model's fields silent no-ops for SP: handed SP, they never read what it moves."""

    @abc.abstractmethod
    def expected_box(self, model: nn.Module) -> torch.Tensor:
        """The box ``[2, 3]`` SP must fold into on this host."""


# -- the contract ---------------------------------------------------------------------------------
SETTINGS = dict(alpha0=0.1, schedule="exponential", end=0.5, seed=3)
"""SP settings of the contract's runs: alpha > 0 at the start, exactly 0 from half-way."""


def hooks_present(d: Driver) -> None:
    """The model class implements every hook SPModelBase declares, and names the host's steps flag."""
    cls = d.model_class()
    assert unimplemented(cls) == (), f"{cls.__name__} leaves {unimplemented(cls)} unimplemented"
    assert cls.steps_flag == hosts.get(d.host).flags.steps, (cls.steps_flag, hosts.get(d.host).flags.steps)


def sp_attached(d: Driver) -> None:
    """The built model owns one preconditioner (a submodule: checkpointed) and hands it to a field."""
    model = d.build(**SETTINGS)
    assert isinstance(model.sp, StochasticPreconditioner) and dict(model.named_children()).get("sp") is model.sp
    assert d.sp_readers(model), "no field is handed the model's preconditioner"


def reach_check_fires(d: Driver) -> None:
    """A field that never reads what SP moves stops the run after its first step, in one line;
    a run whose fields read it trains on."""
    model = d.build(**SETTINGS)
    d.train(model, 2, 10)
    silent = d.build(**SETTINGS)
    d.silence(silent)
    try:
        d.train(silent, 1, 10)
    except d.reach_error as err:
        assert "\n" not in str(err), str(err)
        return
    raise AssertionError("a field that never read what SP moved trained on without the reach check firing")


def preset_applied(d: Driver) -> None:
    """The SP settings a method gets are its host table's preset for the method's model config, and
    the model class's ``sp_preset`` agrees."""
    sp, host_config = d.method_sp()
    table = hosts.get(d.host).table_module()
    assert sp == table.preset_for(host_config), (sp, table.preset_for(host_config))
    assert d.model_class().sp_preset(host_config) == sp


def box_used(d: Driver) -> None:
    """The preconditioner folds into the host's box."""
    model = d.build(**SETTINGS)
    box = d.expected_box(model).float()
    assert torch.equal(model.sp.bounds_lo.float().flatten(), box[0]) and torch.equal(model.sp.bounds_hi.float().flatten(), box[1]), (
        model.sp.bounds_lo, model.sp.bounds_hi, box)


def callbacks_every_step(d: Driver) -> None:
    """The schedule follows the trainer's step at every iteration: alpha falls step by step to 0."""
    model = d.build(**{**SETTINGS, "schedule": "linear"})
    seen: List[Tuple[int, float]] = []
    d.train(model, 6, 10, observe=lambda step: seen.append((int(model.sp.step), float(model.sp.alpha))))
    assert [s for s, _ in seen] == list(range(6)), seen
    alphas = [a for _, a in seen]
    assert all(a > b for a, b in zip(alphas[:5], alphas[1:5])) and alphas[0] > 0 and alphas[5] == 0.0, alphas


def checkpoint_round_trip(d: Driver) -> None:
    """A model loaded from another's state dict continues its schedule and its noise exactly."""
    model = d.build(**SETTINGS)
    d.train(model, 2, 10)
    state = model.state_dict()
    assert any(k.startswith("sp.") for k in state), "no SP state in the checkpoint"
    restored = d.build(**SETTINGS)
    restored.load_state_dict(state)
    assert (int(restored.sp.step), int(restored.sp.total_steps), restored.sp.alpha) == (
        int(model.sp.step), int(model.sp.total_steps), model.sp.alpha)
    x = torch.rand(64, 3) * 0.5
    model.sp.train(), restored.sp.train()
    assert torch.equal(model.sp(x), restored.sp(x)), "the restored run draws other noise"


def eval_unperturbed(d: Driver) -> None:
    """Evaluation reads the plain field: the same output with alpha > 0 as with alpha 0."""
    model = d.build(**SETTINGS)
    d.train(model, 1, 10)
    model.sp.set_step(0, 10)
    assert model.sp.alpha > 0
    during = d.evaluate(model)
    model.sp.set_step(9, 10)
    assert model.sp.alpha == 0.0
    after = d.evaluate(model)
    assert torch.equal(during, after), float((during - after).abs().max())
    assert torch.equal(during, d.evaluate(model)), "evaluation is not deterministic"


ITEMS: Dict[str, Callable[[Driver], None]] = {f.__name__: f for f in (
    hooks_present, sp_attached, reach_check_fires, preset_applied, box_used, callbacks_every_step, checkpoint_round_trip,
    eval_unperturbed)}
"""Every contract item, by name, in the order the table shows them."""


# -- the toy host (tests/adapter/toy_host.py) -----------------------------------------------------
class ToyDriver(Driver):
    host = "toy"

    def __init__(self, model_class: Optional[type] = None) -> None:
        from tests.adapter.toy_host import ToySPModel

        self.cls = model_class or ToySPModel

    def model_class(self) -> type:
        return self.cls

    def build(self, **sp: Any) -> nn.Module:
        return self.cls(SimpleNamespace(sp=SPConfig(**{"boundary": "reflect", **sp})))

    def method_sp(self) -> Tuple[SPConfig, Any]:
        from tests.adapter.toy_host import preset_for

        return preset_for(None), None

    def train(self, model: nn.Module, steps: int, total: int, observe: Optional[Observe] = None) -> None:
        callbacks = model.get_training_callbacks(SimpleNamespace(config=SimpleNamespace(max_num_iterations=total)))
        g = torch.Generator().manual_seed(0)
        for step in range(steps):
            for c in callbacks:
                if c.where == "before":
                    c.func(step)
            model.train()
            model.field(torch.rand(8, 3, generator=g) * 2 - 1).sum().backward()
            for c in callbacks:
                if c.where == "after":
                    c.func(step)
            if observe:
                observe(step)

    def evaluate(self, model: nn.Module) -> torch.Tensor:
        model.eval()
        with torch.no_grad():
            return model.field(torch.linspace(-0.9, 0.9, 24).view(8, 3))

    def silence(self, model: nn.Module) -> None:
        model.field.use_preconditioner(None)  # the host forgot to hand SP to its field

    def expected_box(self, model: nn.Module) -> torch.Tensor:
        from tests.adapter.toy_host import BOX

        return BOX


class _NeverCalled(SimpleNamespace):
    """A callback at a place no trainer runs."""


def broken_toy_driver() -> ToyDriver:
    """The toy host with one broken hook: ``sp_training_callback`` makes callbacks no trainer runs."""
    from tests.adapter.toy_host import ToySPModel

    broken = type("BrokenCallbackToyModel", (ToySPModel,), {
        "sp_training_callback": lambda self, where, func: _NeverCalled(where="never", func=func)})
    return ToyDriver(broken)


class WithSpDriver(Driver):
    """A real host's driver: one of its registered methods (``HOST_METHOD``) through the host's ``with_sp``."""

    HOST_METHOD: str
    METHOD_CONFIGS: str
    """The dict of the host's own trainer configs by method name, as ``module:name``."""
    REGISTRATION: str
    """The host adapter's module that holds its ``with_sp``."""

    def host_method_config(self) -> Any:
        """The host's own trainer config of ``HOST_METHOD``."""
        module, _, name = self.METHOD_CONFIGS.partition(":")
        return getattr(importlib.import_module(module), name)[self.HOST_METHOD]

    def with_sp(self, config: Any) -> Any:
        """The host's ``with_sp`` of a trainer config (its ``MethodSpecification``)."""
        return importlib.import_module(self.REGISTRATION).with_sp(config)

    def sp_model_config(self, **sp: Any) -> Any:
        """A copy of the SP model config, its ``sp`` settings changed by ``sp`` (each driver then shrinks it)."""
        config = copy.deepcopy(self._configs[1])
        config.sp = dataclasses.replace(config.sp, **sp)
        return config

    @staticmethod
    def run_steps(model: nn.Module, callbacks: List[Any], steps: int, loss: Callable[[int], torch.Tensor],
                  observe: Optional[Observe] = None) -> None:
        """``steps`` iterations as the host's trainer runs them: its callbacks before, ``loss(step)``'s backward
        in training mode, its callbacks after, then ``observe(step)`` (both hosts share nerfstudio's loop)."""
        from nerfstudio.engine.callbacks import TrainingCallbackLocation

        for step in range(steps):
            for c in callbacks:
                c.run_callback_at_location(step, TrainingCallbackLocation.BEFORE_TRAIN_ITERATION)
            model.train()
            loss(step).backward()
            for c in callbacks:
                c.run_callback_at_location(step, TrainingCallbackLocation.AFTER_TRAIN_ITERATION)
            if observe:
                observe(step)

    @functools.cached_property
    def _configs(self) -> Tuple[Any, Any]:
        """``(the host's model config, its SP variant)``, built once per driver."""
        host = self.host_method_config()
        return host.pipeline.model, self.with_sp(host).config.pipeline.model

    def model_class(self) -> type:
        from sp_plugins.adapter.variants import target_class

        return target_class(self._configs[1])

    def method_sp(self) -> Tuple[SPConfig, Any]:
        host, ours = self._configs
        return ours.sp, host


# -- nerfstudio 1.x -------------------------------------------------------------------------------
class NerfstudioDriver(WithSpDriver):
    """vanilla-nerf through ``with_sp`` (what ``sp-train vanilla-nerf`` trains), with few samples."""

    host = "nerfstudio"
    HOST_METHOD = "vanilla-nerf"
    METHOD_CONFIGS = "nerfstudio.configs.method_configs:all_methods"
    REGISTRATION = "sp_plugins.nerfstudio.registration"
    BOX = torch.tensor([[-1.5, -1.5, -1.5], [1.5, 1.5, 1.5]])

    def build(self, **sp: Any) -> nn.Module:
        from nerfstudio.data.scene_box import SceneBox

        config = self.sp_model_config(**sp)
        config.num_coarse_samples, config.num_importance_samples = 8, 8
        return config.setup(scene_box=SceneBox(aabb=self.BOX), num_train_data=4, metadata={}, device="cpu", grad_scaler=None)

    @staticmethod
    def _rays(seed: int = 0) -> Any:
        from nerfstudio.cameras.rays import RayBundle

        g = torch.Generator().manual_seed(seed)
        n = 6
        directions = nn.functional.normalize(torch.tensor([0.0, 0.0, 1.0]) + 0.1 * torch.randn(n, 3, generator=g), dim=-1)
        return RayBundle(origins=torch.tensor([0.0, 0.0, -4.0]).expand(n, 3).contiguous(), directions=directions,
                         pixel_area=torch.full((n, 1), 1e-4), camera_indices=torch.zeros(n, 1, dtype=torch.long))

    def train(self, model: nn.Module, steps: int, total: int, observe: Optional[Observe] = None) -> None:
        from nerfstudio.engine.callbacks import TrainingCallbackAttributes

        trainer = SimpleNamespace(config=SimpleNamespace(max_num_iterations=total), _start_step=0)
        callbacks = model.get_training_callbacks(TrainingCallbackAttributes(optimizers=None, grad_scaler=None, pipeline=None,
                                                                            trainer=trainer))
        self.run_steps(model, callbacks, steps, lambda step: model(self._rays(step))["rgb_fine"].sum(), observe)

    def evaluate(self, model: nn.Module) -> torch.Tensor:
        model.eval()
        with torch.no_grad():
            return model(self._rays(99))["rgb_fine"]

    def silence(self, model: nn.Module) -> None:
        from nerfstudio.field_components.field_heads import FieldHeadNames

        class DirectionsOnly(nn.Module):
            """A field called with RaySamples that reads only their directions."""

            def __init__(self) -> None:
                super().__init__()
                self.linear = nn.Linear(3, 4)

            def forward(self, ray_samples, compute_normals: bool = False):
                h = self.linear(ray_samples.frustums.directions)
                return {FieldHeadNames.RGB: torch.sigmoid(h[..., :3]), FieldHeadNames.DENSITY: nn.functional.softplus(h[..., 3:])}

        model.field_coarse, model.field_fine = DirectionsOnly(), DirectionsOnly()
        model.attach_sp()

    def expected_box(self, model: nn.Module) -> torch.Tensor:
        return model.scene_box.aabb


# -- sdfstudio (its own environment) --------------------------------------------------------------
class SdfstudioDriver(WithSpDriver):
    """sdfstudio's NeuS through ``with_sp`` (what ``sp-sdfstudio-train sp-neus`` trains), tiny field;
    needs our methods registered in the process (``tests/sdfstudio/conftest.py``'s ``patched``)."""

    host = "sdfstudio"
    HOST_METHOD = "neus"
    METHOD_CONFIGS = "nerfstudio.configs.method_configs:method_configs"
    REGISTRATION = "sp_plugins.sdfstudio.registration"

    def build(self, **sp: Any) -> nn.Module:
        from nerfstudio.data.scene_box import SceneBox

        config = self.sp_model_config(**sp)
        f = config.sdf_field
        f.num_layers, f.hidden_dim, f.geo_feat_dim, f.hidden_dim_color = 2, 32, 15, 32
        f.num_levels, f.log2_hashmap_size, f.base_res, f.max_res = 4, 11, 8, 64
        config.background_model = "none"
        return config.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])), num_train_data=2,
                            world_size=1, local_rank=0)

    @staticmethod
    def _samples(seed: int = 0) -> Any:
        from nerfstudio.cameras.rays import Frustums, RaySamples

        g = torch.Generator().manual_seed(seed)
        n_rays, n = 4, 6
        origins = torch.tensor([0.2, -0.1, 2.5]).expand(n_rays, n, 3).contiguous()
        directions = nn.functional.normalize(torch.tensor([0.0, 0.0, -1.0]) + 0.1 * torch.randn(n_rays, 1, 3, generator=g), dim=-1)
        directions = directions.expand(n_rays, n, 3).contiguous()
        starts = torch.linspace(1.5, 3.5, n).view(1, n, 1).expand(n_rays, n, 1).contiguous()
        frustums = Frustums(origins=origins, directions=directions, starts=starts, ends=starts + 0.1, pixel_area=torch.ones_like(starts))
        return RaySamples(frustums=frustums, camera_indices=torch.zeros(n_rays, n, 1, dtype=torch.long),
                          deltas=torch.full_like(starts, 0.1))

    def train(self, model: nn.Module, steps: int, total: int, observe: Optional[Observe] = None) -> None:
        from nerfstudio.engine.callbacks import TrainingCallbackAttributes
        from nerfstudio.field_components.field_heads import FieldHeadNames

        attributes = TrainingCallbackAttributes(optimizers=None, grad_scaler=None, pipeline=None,
                                                config=SimpleNamespace(max_num_iterations=total))
        callbacks = model.get_training_callbacks(attributes)
        self.run_steps(model, callbacks, steps, lambda step: model.field(self._samples(step))[FieldHeadNames.RGB].sum(), observe)

    def evaluate(self, model: nn.Module) -> torch.Tensor:
        from nerfstudio.field_components.field_heads import FieldHeadNames

        model.eval()
        return model.field(self._samples(99))[FieldHeadNames.RGB].detach()

    def silence(self, model: nn.Module) -> None:
        model.field.spatial_distortion = model.field.spatial_distortion.inner  # the host's contraction, not the seam's

    def expected_box(self, model: nn.Module) -> torch.Tensor:
        from sp_plugins.sdfstudio.seam import CONTRACTED_BOUNDS

        lo, hi = CONTRACTED_BOUNDS
        return torch.tensor([[lo] * 3, [hi] * 3])


def run(driver: Driver) -> Dict[str, str]:
    """Every item on ``driver``: ``"pass"`` or ``"FAIL: <first line>"``."""
    out = {}
    for name, item in ITEMS.items():
        try:
            item(driver)
            out[name] = "pass"
        except Exception as err:  # noqa: BLE001  (the table reports every failure)
            out[name] = f"FAIL: {type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}"[:120]
    return out


def table(drivers: Dict[str, Driver]) -> str:
    """The host x item table (markdown)."""
    results = {name: run(d) for name, d in drivers.items()}
    lines = ["| contract item | " + " | ".join(results) + " |", "|---|" + "---|" * len(results)]
    for item in ITEMS:
        lines.append(f"| {item} | " + " | ".join(results[h][item].replace("|", "/") for h in results) + " |")
    return "\n".join(lines)


def drivers_here() -> Dict[str, Driver]:
    """A driver for each host available in this environment, the toy host and the broken toy host."""
    from tests.adapter.toy_host import HOST

    hosts.register(HOST)
    out: Dict[str, Driver] = {"toy": ToyDriver()}
    for name, cls in (("nerfstudio", NerfstudioDriver), ("sdfstudio", SdfstudioDriver)):
        if hosts.get(name).available():
            out[name] = cls()
    out["toy, broken sp_training_callback"] = broken_toy_driver()
    return out


if __name__ == "__main__":
    from sp_plugins.sdfstudio.detect import is_sdfstudio

    if is_sdfstudio():
        from sp_plugins.patches.sdfstudio_import_hook import install_all

        install_all()
        import scripts.train  # noqa: F401  (sdfstudio's own import order)

        from sp_plugins.sdfstudio.registration import add_methods

        add_methods()
    print(table(drivers_here()))
