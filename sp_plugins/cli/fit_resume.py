"""``sp-fit --checkpoint-every N`` / ``--resume`` of one command (:mod:`sp_plugins.cli.fit`): the checks before any
work (a refusal is one line naming the flag, exit status 2, nothing written), the resume into the task's trainer, and
the checkpoint writes. The file format and its atomic writes are :mod:`sp_plugins.tasks.checkpoint`'s.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path
from typing import Any, Optional

from sp_plugins.adapter.errors import first_line, write_failure
from sp_plugins.tasks import checkpoint as checkpoint_io
from sp_plugins.tasks.common import prepare_output_dir


def jsonable(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj):
        return {f.name: jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj) if not f.name.startswith("_")}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    return obj


def flag_name(setting: str) -> str:
    """The flag behind a checkpointed setting (``config.sp.num_samples`` -> ``--sp.num-samples``)."""
    if setting == "config.sp.enabled":
        return "--sp.enabled (or --no-sp)"
    if setting == "files.input":
        return "INPUT"
    name = setting.split(".", 1)[1] if setting.startswith(("config.", "files.", "run.")) else setting
    return "--" + name.replace("_", "-")


class Checkpoints:
    """``--checkpoint-every`` / ``--resume`` of one sp-fit command: the checks before any work (a
    refusal is one line, exit status 2, nothing written), the resume, and the writes."""

    def __init__(self, cmd, task: str, config, device, run_settings: dict, files: dict) -> None:
        self.cmd, self.task, self.io = cmd, task, checkpoint_io
        self.path = checkpoint_io.checkpoint_path(cmd.out)
        if cmd.checkpoint_every is not None and cmd.checkpoint_every < 0:
            raise ValueError(f"--checkpoint-every {cmd.checkpoint_every}: give a number of steps >= 1 (or 0 for none)")
        # what the trajectory (and the results) depend on; --out, --quiet and the interval do not count
        self.settings = {"config": jsonable(config), "run": {"device": device.type, **run_settings}, "files": {}}
        self.files = files
        self.saved: Optional[dict] = None
        self.every = cmd.checkpoint_every or 0
        self.seconds_before = 0.0
        if cmd.resume:
            self.saved = checkpoint_io.load(self.path, task)
            self._refuse_differences(self.saved["settings"], only=("config", "run"))
            if cmd.checkpoint_every is None:
                self.every = int(self.saved.get("checkpoint_every") or 0)
            self.seconds_before = float(self.saved.get("seconds", 0.0))
        elif self.path.exists() and not cmd.overwrite:
            raise ValueError(f"--out {cmd.out}: holds the checkpoint of an earlier run ({self.path.name}); pass --resume to "
                             "continue it, --overwrite to start anew, or choose another --out")

    def _refuse_differences(self, saved: dict, only: tuple) -> None:
        current = {k: v for k, v in self.settings.items() if k in only}
        diffs = self.io.differences({k: v for k, v in saved.items() if k in only}, current)
        if not diffs:
            return
        parts = []
        for name, here, there in diffs:
            if name.startswith("files."):
                parts.append(f"{flag_name(name)} is not the file the checkpoint was trained on (its contents differ)"
                             if here is not None and there is not None else
                             f"{flag_name(name)} is {'given' if here is not None else 'not given'} here but "
                             f"{'was' if there is not None else 'was not'} in the checkpoint")
            else:
                parts.append(f"{flag_name(name)} is {here!r} here but {there!r} in the checkpoint")
        raise ValueError(f"--resume: {'; '.join(parts)} ({self.path}); a resume needs the checkpoint's settings: "
                         "give the same flags, or start anew with --overwrite")

    def check_files(self) -> None:
        """After the inputs loaded (so a missing file is the loader's error): their contents."""
        if self.every or self.saved is not None:
            self.settings["files"] = {name: self.io.file_digest(path) for name, path in self.files.items()}
        if self.saved is not None:
            self._refuse_differences(self.saved["settings"], only=("files",))

    def prepare(self, out: Path) -> None:
        """After ``--out`` is ready: drop what a killed writer left, and with --overwrite the old checkpoint."""
        self.io.remove_stale(out, checkpoint_too=self.saved is None)

    def train(self, outputs: tuple[str, ...], setup):
        """What every task does once its inputs are loaded: check their contents against a resumed
        checkpoint, make ``--out`` (after the inputs: a bad file leaves no empty --out), build the
        trainer with ``setup()``, restore the checkpoint into it and fit. Returns the trainer,
        the output folder and the training seconds."""
        self.check_files()
        out = prepare_output_dir(self.cmd.out, outputs, self.cmd.overwrite or self.cmd.resume)
        self.prepare(out)
        trainer = setup()
        self.restore(trainer)
        return trainer, out, self.fit(trainer)

    def restore(self, trainer) -> None:
        if self.saved is None:
            return
        trainer.load_state_dict(self.saved["trainer"])
        if not self.cmd.quiet:
            print(f"sp-fit: resuming from step {trainer.step_index} of {trainer.config.steps} ({self.path})",
                  file=sys.stderr, flush=True)
        self.saved = None  # free the tensors

    def fit(self, trainer) -> float:
        """Train to the end, writing checkpoints; the training seconds, those before a resume included."""
        start = time.perf_counter()

        def write(trainer, record) -> None:
            if self.every and (trainer.step_index % self.every == 0 or trainer.done):
                try:
                    self.io.save(self.path, {
                        "task": self.task, "settings": self.settings, "checkpoint_every": self.every,
                        "seconds": self.seconds_before + time.perf_counter() - start, "trainer": trainer.state_dict(),
                    })
                except (OSError, RuntimeError) as exc:  # torch's writer reports a failed write as a RuntimeError
                    if isinstance(exc, OSError):
                        raise ValueError(write_failure(exc, f"--out {self.cmd.out}") + f" (step {trainer.step_index} "
                                         "checkpoint; the previous one is intact)") from None
                    raise ValueError(f"--out {self.cmd.out}: cannot write the step {trainer.step_index} checkpoint "
                                     f"({first_line(exc, 120)}); the disk may be full (the previous checkpoint is intact)") from None

        trainer.fit(callback=write, progress=not self.cmd.quiet)
        return self.seconds_before + time.perf_counter() - start
