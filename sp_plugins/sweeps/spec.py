"""What a sweep is: a base command, a grid of flag values, SP on/off as a paired axis, seeds.

A spec is a small YAML (or JSON) file, or the same fields as ``sp-sweep`` flags::

    command: sp-fit pointcloud spot.ply --steps 300     # or: ns-train neus-hashgrid --max-num-iterations 300 ...
    data: blender-data --data scene/blender             # ns-train only: the dataparser, placed after every flag
    grid:                                               # flag -> values; every combination is one grid point
      lr: [1e-3, 1e-2]
      encoding.max-resolution: [256, 1024]
    sp: both                                            # both (paired: off and on per grid point), on, off
    seeds: [0]
    sample: 12                                          # optional: a random subset of the grid points
    success: ["sound == 1", "fscore >= 0.9"]            # optional: what counts as a successful trial
    metric: fscore                                      # the histogram's metric

:func:`expand` turns a spec into trials; a trial's key hashes its command line (without output
paths), so a restarted or grown sweep recognises the trials it has already run. A trial's device
(``cpu`` / ``cuda``: what ``--gpus-per-trial`` or a device flag in the command gives it) is part of
what it is: its result records it, and a result from another device is not this trial's.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import random
import re
import shlex
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Literal, Optional, Sequence, Tuple

PROGRAMS = ("ns-train", "sp-fit")

# how each program switches SP off / on and takes a seed
SP_FLAGS = {"ns-train": (["--pipeline.model.sp.enabled", "False"], ["--pipeline.model.sp.enabled", "True"]),
            "sp-fit": (["--no-sp"], [])}
SEED_FLAG = {"ns-train": "--machine.seed", "sp-fit": "--seed"}
DEVICE_FLAG = {"ns-train": "--machine.device-type", "sp-fit": "--device"}
DEFAULT_METRIC = {"ns-train": "psnr", "sp-fit": "chamfer"}
_CRITERION = re.compile(r"^\s*([A-Za-z_][\w.]*)\s*(>=|<=|==|!=|>|<)\s*(\S+)\s*$")


class SpecError(ValueError):
    """A spec that cannot run; the message names the field and what is allowed."""


@dataclass
class SweepSpec:
    command: List[str]
    """Program, method or task, and the flags every trial shares (ns-train METHOD ... | sp-fit TASK ...)."""
    data: List[str] = field(default_factory=list)
    """ns-train: the dataparser subcommand and its flags (e.g. blender-data --data DIR)."""
    grid: Dict[str, List[str]] = field(default_factory=dict)
    """Flag (with or without leading dashes) -> values."""
    sp: Literal["both", "on", "off"] = "both"
    sp_methods: Optional[Tuple[str, str]] = None
    """ns-train: (baseline method, SP method) instead of toggling --pipeline.model.sp.enabled."""
    sp_only: List[str] = field(default_factory=list)
    """Grid flags that only mean something with SP (e.g. sp.alpha0): baseline trials leave them out
    (shown as '-'), so grid points that differ only there share one baseline trial."""
    seeds: List[int] = field(default_factory=lambda: [0])
    sample: Optional[int] = None
    """Run only this many grid points, drawn at random (seeded by sample_seed) and run in that
    random order, so a sweep stopped early still covers the grid evenly; SP pairs stay together."""
    sample_seed: int = 0
    success: List[str] = field(default_factory=list)
    """Criteria a finished trial must all meet to count as a success, e.g. 'psnr >= 24'."""
    metric: Optional[str] = None
    """Metric of the histogram and the per-axis medians (default: psnr for ns-train, chamfer for sp-fit)."""
    eval: bool = True
    """ns-train: run ns-eval on the test split after training (PSNR / SSIM)."""

    @property
    def program(self) -> str:
        return self.command[0]

    @property
    def primary_metric(self) -> str:
        return self.metric or DEFAULT_METRIC[self.program]

    def validate(self) -> None:
        if not self.command or self.command[0] not in PROGRAMS:
            got = self.command[0] if self.command else "nothing"
            raise SpecError(f"command starts with {got!r}: it must start with one of {', '.join(PROGRAMS)}")
        if len(self.command) < 2 or self.command[1].startswith("-"):
            raise SpecError(f"command: name the {'method' if self.program == 'ns-train' else 'task'} after {self.program}")
        if self.data and self.program != "ns-train":
            raise SpecError("data: only ns-train takes a dataparser subcommand; put sp-fit's input in command")
        if self.program == "ns-train" and not self.data:
            raise SpecError("data: ns-train needs a dataparser, e.g. data: blender-data --data DIR")
        if self.sp not in ("both", "on", "off"):
            raise SpecError(f"sp={self.sp!r}: use both, on or off")
        if self.sp_methods is not None and (self.program != "ns-train" or len(self.sp_methods) != 2):
            raise SpecError("sp_methods: two ns-train methods (baseline, SP)")
        for flag, values in self.grid.items():
            if not values:
                raise SpecError(f"grid: {flag} has no values")
        names = [flag_name(f) for f in self.grid]
        if len(set(names)) != len(names):
            raise SpecError("grid: a flag is listed twice (with and without dashes?)")
        unknown = [f for f in self.sp_only if flag_name(f) not in {flag_name(g) for g in self.grid}]
        if unknown:
            raise SpecError(f"sp_only: {', '.join(unknown)} not in the grid")
        if not self.seeds:
            raise SpecError("seeds: give at least one seed")
        if self.sample is not None and self.sample < 1:
            raise SpecError(f"sample={self.sample}: must be at least 1")
        for c in self.success:
            parse_criterion(c)


def _as_list(value, name: str) -> List[str]:
    if value is None:
        return []
    if isinstance(value, str):
        return shlex.split(value)
    if isinstance(value, (list, tuple)):
        return [str(v) for v in value]
    raise SpecError(f"{name}: a string or a list, got {type(value).__name__}")


def _value(v) -> str:
    if isinstance(v, bool):
        return "True" if v else "False"
    return str(v)


def spec_from_dict(raw: dict) -> SweepSpec:
    """A spec from parsed YAML / JSON (strings or lists for commands, scalars for values)."""
    known = {f.name for f in dataclasses.fields(SweepSpec)}
    unknown = sorted(set(raw) - known)
    if unknown:
        raise SpecError(f"unknown field(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    if "command" not in raw:
        raise SpecError("command: missing (e.g. command: sp-fit pointcloud mesh.ply --steps 300)")
    grid = raw.get("grid") or {}
    if not isinstance(grid, dict):
        raise SpecError("grid: a mapping flag -> list of values")
    seeds = raw.get("seeds", [0])
    spec = SweepSpec(
        command=_as_list(raw["command"], "command"),
        data=_as_list(raw.get("data"), "data"),
        grid={str(k): [_value(v) for v in (vs if isinstance(vs, (list, tuple)) else [vs])] for k, vs in grid.items()},
        sp={True: "on", False: "off"}.get(raw.get("sp", "both"), raw.get("sp", "both")),  # YAML reads on/off as booleans
        sp_methods=tuple(raw["sp_methods"]) if raw.get("sp_methods") else None,
        sp_only=[str(f) for f in (raw.get("sp_only") or [])],
        seeds=[int(s) for s in (seeds if isinstance(seeds, (list, tuple)) else [seeds])],
        sample=raw.get("sample"),
        sample_seed=int(raw.get("sample_seed", 0)),
        success=[str(c) for c in (raw.get("success") or [])],
        metric=raw.get("metric"),
        eval=bool(raw.get("eval", True)),
    )
    spec.validate()
    return spec


def load_spec(path: Path) -> SweepSpec:
    import yaml  # JSON is YAML too

    path = Path(path)
    if not path.is_file():
        raise SpecError(f"spec file {path} does not exist")
    try:
        raw = yaml.safe_load(path.read_bytes().decode("utf-8"))
    except UnicodeDecodeError:
        raise SpecError(f"{path}: not a YAML or JSON text file (not UTF-8)") from None
    except yaml.YAMLError as err:
        raise SpecError(f"{path}: not valid YAML/JSON ({str(err).splitlines()[0]})") from None
    except RecursionError:
        raise SpecError(f"{path}: not valid YAML/JSON (nested too deeply)") from None
    if not isinstance(raw, dict):
        raise SpecError(f"{path}: expected a mapping with at least 'command'")
    try:  # every answer names the file
        return spec_from_dict(raw)
    except SpecError as err:
        raise SpecError(f"{path}: {err}") from None
    except (TypeError, ValueError) as err:  # a number or list field holding something else
        raise SpecError(f"{path}: a field holds a value of the wrong kind ({err}); expected e.g. seeds: [0, 1], "
                        "sample: 4, sp_methods: [neus-hashgrid, sp-neus-hashgrid]") from None


def flag_name(flag: str) -> str:
    """'lr' / '--lr' -> '--lr'."""
    return "--" + flag.lstrip("-")


def short_name(flag: str, others: Sequence[str]) -> str:
    """The last dotted part of a flag (``--pipeline.model.sdf-field.max-res`` -> ``max-res``), or
    more of it where two flags would share a name."""
    parts = flag.lstrip("-").split(".")
    for n in range(1, len(parts) + 1):
        name = ".".join(parts[-n:])
        if sum(1 for o in others if o.lstrip("-").split(".")[-n:] == parts[-n:]) <= 1:
            return name
    return flag.lstrip("-")


def parse_criterion(text: str) -> Tuple[str, str, float]:
    m = _CRITERION.match(text)
    if not m:
        raise SpecError(f"success criterion {text!r}: write METRIC OP VALUE, e.g. 'psnr >= 24' (OP: >= <= > < == !=)")
    try:
        return m.group(1), m.group(2), float(m.group(3))
    except ValueError:
        raise SpecError(f"success criterion {text!r}: {m.group(3)!r} is not a number") from None


@dataclass
class Trial:
    """One run: its grid point, SP side and seed, and the command line without output paths."""

    key: str
    params: Dict[str, str]
    sp: Optional[bool]
    seed: int
    argv: List[str]
    device: str = "cpu"
    """Where it runs: ``cpu`` or ``cuda`` (a result from another device is not this trial's)."""

    def label(self) -> str:
        sp = {None: "", True: "SP ", False: "base "}[self.sp]
        return sp + " ".join(f"{k.lstrip('-')}={v}" for k, v in self.params.items()) + f" seed={self.seed}"


def trial_device(argv: Sequence[str], gpus: float) -> str:
    """``cuda`` or ``cpu``: a device flag in the command wins, else GPUs reserved for the trial mean
    CUDA (``ns-train`` gets ``--machine.device-type cuda``; ``sp-fit --device auto`` finds the GPU)."""
    flag = DEVICE_FLAG.get(argv[0] if argv else "")
    named = None
    for i, a in enumerate(argv):
        if flag and a == flag and i + 1 < len(argv):
            named = argv[i + 1]
        elif flag and a.startswith(flag + "="):
            named = a.partition("=")[2]
    if named and named != "auto":
        return "cuda" if named.startswith("cuda") else named
    return "cuda" if gpus > 0 else "cpu"


def trial_key(argv: Sequence[str]) -> str:
    return hashlib.sha1(json.dumps(list(argv)).encode()).hexdigest()[:12]


def grid_points(spec: SweepSpec) -> List[Dict[str, str]]:
    flags = [flag_name(f) for f in spec.grid]
    points = [dict(zip(flags, combo)) for combo in itertools.product(*spec.grid.values())] or [{}]
    if spec.sample is not None and spec.sample < len(points):
        chosen = random.Random(spec.sample_seed).sample(range(len(points)), spec.sample)
        points = [points[i] for i in chosen]
    return points


def build_argv(spec: SweepSpec, params: Dict[str, str], sp: Optional[bool], seed: int) -> List[str]:
    """The trial's command line (its output flags are added by the runner)."""
    program, target, shared = spec.command[0], spec.command[1], spec.command[2:]
    sp_args: List[str] = []
    if sp is not None:
        if spec.sp_methods is not None:
            target = spec.sp_methods[int(sp)]
        else:
            sp_args = SP_FLAGS[program][int(sp)]
    grid_args = [a for flag, value in params.items() for a in (flag, value)]
    return [program, target, *shared, *grid_args, *sp_args, SEED_FLAG[program], str(seed), *spec.data]


def expand(spec: SweepSpec, gpus: float = 0.0) -> List[Trial]:
    """Every trial of the sweep, SP pairs next to each other (so partial results stay paired);
    ``gpus``: what each trial reserves (``--gpus-per-trial``), which decides its device."""
    spec.validate()
    sides = {"both": [False, True], "on": [True], "off": [False]}[spec.sp]
    sp_only = {flag_name(f) for f in spec.sp_only}
    trials, seen = [], set()
    for point in grid_points(spec):
        for seed in spec.seeds:
            for sp in sides:
                used = {k: v for k, v in point.items() if sp is not False or k not in sp_only}
                argv = build_argv(spec, used, sp, seed)
                key = trial_key(argv)
                if key in seen:  # a baseline shared by grid points that differ only in SP-only flags
                    continue
                seen.add(key)
                shown = {k: (v if k in used else "-") for k, v in point.items()}
                trials.append(Trial(key, shown, sp, seed, argv, trial_device(argv, gpus)))
    for flag, values in spec.grid.items():
        if len(set(values)) != len(values):
            raise SpecError(f"grid: {flag} repeats a value")
    return trials
