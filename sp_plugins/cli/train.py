"""``sp-train METHOD [ns-train flags]``: nerfstudio's ``ns-train`` with SP on any registered method.

``sp-train --help`` lists them. Its runs keep the method's name (``outputs/<experiment>/<method>``):
nerfstudio's ``ns-eval``, ``ns-render`` and ``ns-export`` look the data manager up by that name, and
``config.yml`` names the SP classes and holds the ``sp`` block. Methods SP cannot reach are refused in
one line that says why (:func:`sp_plugins.nerfstudio.registration.refusal`). The process is ours: the
process-wide conveniences are installed here (:func:`train`), never by importing our method configs.
"""

from __future__ import annotations

import sys
from typing import Optional

from sp_plugins.adapter.safe_config import load_run_config, reading_configs_safely
from sp_plugins.nerfstudio.registration import sp_methods
from sp_plugins.patches import registry

PROG = "sp-train"


def _method_argument(argv: list) -> Optional[str]:
    return next((a for a in argv if not a.startswith("-")), None)


def train(argv: Optional[list] = None) -> None:
    """``sp-train METHOD [ns-train flags]``: nerfstudio's ``ns-train`` with SP on ``METHOD``."""
    _import_modules_that_keep_their_import_error()
    _train(argv)


def _import_modules_that_keep_their_import_error() -> None:
    """nerfstudio's ``utils.external`` keeps the ``ImportError`` of a missing tiny-cuda-nn in a module
    global; its traceback holds every frame that was importing it, locals included, for good. Imported
    here, that is this call and :func:`train`'s (which binds only ``argv``), not the frame that later
    holds the run config and trainer (they would outlive a ``train()`` called from Python, a notebook
    or a test, with the patches they hold)."""
    import nerfstudio.utils.external  # noqa: F401


def _train(argv: Optional[list]) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    # our own command: the process is ours, so the process-wide conveniences go in here
    from sp_plugins.nerfstudio.model import install_process_settings  # defers nerfstudio

    install_process_settings()
    registry.install_for_process("nerfstudio_external_methods", command="sp-train")
    registry.install_for_process("nerfstudio_parallel_seed", command="sp-train")  # a plugin's own parallel data manager too
    import tyro
    from nerfstudio.configs.config_utils import convert_markup_to_ansi
    from nerfstudio.configs.method_configs import all_descriptions, all_methods

    configs, texts, refused = sp_methods(all_methods, all_descriptions)
    method = _method_argument(argv)
    if method in refused:
        print(f"{PROG}: error: SP cannot be put on {method}: {refused[method]}", file=sys.stderr)
        raise SystemExit(2)
    if method is not None and method not in configs and not any(a in ("-h", "--help") for a in argv):
        print(f"{PROG}: error: no method {method!r}; sp-train --help lists them", file=sys.stderr)
        raise SystemExit(2)
    union = tyro.conf.SuppressFixed[
        tyro.conf.FlagConversionOff[tyro.extras.subcommand_type_from_defaults(defaults=configs, descriptions=texts)]
    ]
    tyro.extras.set_accent_color("bright_yellow")
    refused_text = "; ".join(f"{m}: {why}" for m, why in sorted(refused.items()))
    description = (
        "ns-train with stochastic preconditioning on any registered method (sp-plugins): the method's own flags, "
        f"plus --pipeline.model.sp.*. Not offered: {refused_text}."
    )
    config = tyro.cli(union, args=argv, prog=PROG, description=convert_markup_to_ansi(description))
    from nerfstudio.scripts import train as host_train

    if config.load_config is None:
        host_train.main(config)
        return
    # --load-config: read with the restricted loader (a refusal is one line before anything runs), also where main reads it
    load_run_config(config.load_config, "--load-config")
    with reading_configs_safely(host_train, f"--load-config {config.load_config}"):
        host_train.main(config)


def entrypoint() -> None:
    train()


if __name__ == "__main__":
    entrypoint()
