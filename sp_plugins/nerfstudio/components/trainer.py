"""The trainer config of our methods: ``ns-train`` checks the input before it writes anything.

nerfstudio's ``ns-train`` writes ``<output-dir>/<experiment>/<method>/<timestamp>/config.yml``
(``TrainerConfig.save_config``) before it builds the data manager or the model, so a run refused
there (a wrong data folder or a damaged image, a damaged ``--load-dir`` checkpoint, CUDA on a CPU
machine, an SP option that cannot act on the model) would leave a run folder behind, or overwrite
the config of an earlier run with the same timestamp. :class:`CheckedTrainerConfig` (our methods
and every ``sp-train`` run) is nerfstudio's ``TrainerConfig`` whose ``save_config`` first runs
:func:`preflight`: every check that needs no data loaded, each an
:class:`~sp_plugins.adapter.errors.InputError` printed as one line (exit status 2) with nothing
written. The same checks run again where they always ran (data manager, model), for runs that
do not go through ``ns-train``.

Runs whose ``config.yml`` names nerfstudio's own ``TrainerConfig`` load as they are.
"""

from __future__ import annotations

import dataclasses
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from nerfstudio.configs.base_config import ViewerConfig
from nerfstudio.engine.trainer import TrainerConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipelineConfig

from sp_plugins.adapter.checks import check_checkpoint_file, check_device, check_known_settings
from sp_plugins.adapter.errors import InputError, write_failure
from sp_plugins.nerfstudio.host import HOST
from sp_plugins.nerfstudio.components.data_checks import LAYOUT_CHECKED, check_data_layout
from sp_plugins.nerfstudio.components.datamanagers import CheckedDataManagerConfig
from sp_plugins.nerfstudio.model import install_process_settings, refuse_unreachable_settings

_STEP_FILE = re.compile(r"^step-(\d+)\.ckpt$")


def checkpoint_to_load(config: TrainerConfig, dir_flag: str = "--load-dir"):
    """``(path, flag)`` of the checkpoint ``ns-train`` will load (``--load-dir`` [``--load-step``] or
    ``--load-checkpoint``), checked to exist as nerfstudio will look it up; None when none is loaded.
    ``dir_flag`` names where the folder came from in messages."""
    if config.load_dir is not None:
        load_dir = Path(config.load_dir)
        if not load_dir.is_dir():
            raise InputError(f"{dir_flag} {load_dir}: folder not found; expected the nerfstudio_models folder of a run "
                             "(step-NNNNNNNNN.ckpt files)")
        if config.load_step is not None:
            return load_dir / f"step-{config.load_step:09d}.ckpt", f"--load-step {config.load_step}:"
        names = sorted(os.listdir(load_dir))
        strays = [n for n in names if not _STEP_FILE.match(n)]
        if strays:  # nerfstudio parses every name in the folder as a step number
            raise InputError(f"{dir_flag} {load_dir}: holds {strays[0]!r}, which is not a step-NNNNNNNNN.ckpt checkpoint; "
                             "expected only the checkpoints ns-train wrote (move the other files out)")
        if not names:
            raise InputError(f"{dir_flag} {load_dir}: holds no checkpoint (step-NNNNNNNNN.ckpt); expected the "
                             "nerfstudio_models folder of a run that saved one")
        latest = max(names, key=lambda n: int(_STEP_FILE.match(n).group(1)))  # type: ignore[union-attr]
        return load_dir / latest, dir_flag
    if config.load_checkpoint is not None:
        return Path(config.load_checkpoint), "--load-checkpoint"
    return None


def preflight(config: TrainerConfig) -> None:
    """Everything that can be checked before the run writes its folder."""
    install_process_settings(config, run=True)  # while our run exists: one-line input errors, host warnings filtered
    pipeline = config.pipeline
    model = getattr(pipeline, "model", None)
    if model is not None and hasattr(model, "sp"):
        check_known_settings(model, "pipeline.model")  # a --load-config written by another version
        refuse_unreachable_settings(model)
    check_device(config.machine.device_type, config.machine.num_devices, flags=HOST.flags)
    dm = getattr(pipeline, "datamanager", None)
    # also a host's data manager on a dataparser we know (sp-train on a host method): its workers would
    # hang behind a damaged image's traceback
    ours = isinstance(dm, CheckedDataManagerConfig)
    if (ours and dm.check_data) or (not ours and isinstance(getattr(dm, "dataparser", None), LAYOUT_CHECKED)):
        data = getattr(dm, "data", None)
        check_data_layout(dm.dataparser, data if data is not None else getattr(dm.dataparser, "data", None))
    target = checkpoint_to_load(config)
    if target is not None:
        path, flag = target
        check_checkpoint_file(path, flag)


@dataclass
class CheckedTrainerConfig(TrainerConfig):
    """nerfstudio's ``TrainerConfig``, whose ``save_config`` (``ns-train`` calls it before it
    writes anything) first runs :func:`preflight`."""

    def save_config(self) -> None:
        """:func:`preflight`, then nerfstudio's ``config.yml``, written whole or not at all: a failed
        write (full disk, read-only folder) removes its partial file and the folders it created."""
        import yaml
        from nerfstudio.utils.rich_utils import CONSOLE

        preflight(self)
        base_dir = Path(self.get_base_dir())
        created = []
        folder = base_dir
        while not folder.exists():
            created.append(folder)
            folder = folder.parent
        path = base_dir / "config.yml"
        tmp = base_dir / f".config.yml.tmp-{os.getpid()}"
        CONSOLE.log(f"Saving config to: {path}")
        try:
            base_dir.mkdir(parents=True, exist_ok=True)
            tmp.write_text(yaml.dump(self), "utf8")
            os.replace(tmp, path)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            for made in created:  # deepest first
                try:
                    made.rmdir()
                except OSError:
                    break
            raise InputError(write_failure(exc, f"--output-dir {self.output_dir}", f"{base_dir}/config.yml")) from None


def checked(config: TrainerConfig) -> TrainerConfig:
    """``config`` as a :class:`CheckedTrainerConfig` (the same settings); a subclass of nerfstudio's
    that is not ours (another plugin's trainer) is kept as it is."""
    if type(config) is not TrainerConfig:
        return config
    values = {f.name: getattr(config, f.name) for f in dataclasses.fields(config) if f.init}
    return CheckedTrainerConfig(**values)


def checked_trainer(method_name: str, datamanager, model, optimizers: dict, *, viewer_rays: Optional[int] = None,
                    **settings) -> CheckedTrainerConfig:
    """A method's trainer config, built as nerfstudio's ``method_configs`` build theirs: a vanilla
    pipeline of ``datamanager`` and ``model``, the ``optimizers``, with ``viewer_rays`` the viewer's
    rays per chunk; ``settings`` are the trainer's own. ``--vis`` defaults to the viewer for every
    method of ours (``TrainerConfig``'s own default, ``wandb``, stops a user without a wandb account)."""
    settings.setdefault("vis", "viewer")
    if viewer_rays is not None:
        settings.update(viewer=ViewerConfig(num_rays_per_chunk=viewer_rays))
    return CheckedTrainerConfig(method_name=method_name, optimizers=optimizers,
                                pipeline=VanillaPipelineConfig(datamanager=datamanager, model=model), **settings)
