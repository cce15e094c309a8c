"""The docs' method tables: what SP does to every method a host registers, as markdown.

    python -m sp_plugins.method_table            # print the table of the host installed here
    python -m sp_plugins.method_table --write    # from a checkout's root: refresh that table in its docs page

Each row is read from the host's registered methods, through the same ``sp_methods`` that
``sp-train`` / ``sp-sdfstudio-train`` use, and from the host's table module
(:mod:`sp_plugins.nerfstudio.table`, :mod:`sp_plugins.sdfstudio.table`). nerfstudio 1.x and
sdfstudio install the same package name and never share an environment, so each host's table is
made in that host's environment (here ``.venv`` and ``.venv-sdfstudio``), and a test in each
host's suite fails when the page's copy drifts (``docs/guides/any-method.md``, ``docs/guides/sdfstudio.md``).
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path
from typing import Dict, List, Optional, Tuple

from sp_plugins.adapter import hosts
from sp_plugins.adapter.tables import lookup, merged
from sp_plugins.adapter.variants import target_class
from sp_plugins.nerfstudio import table as nerfstudio_table
from sp_plugins.nerfstudio.registration import sp_methods
from sp_plugins.patches.sdfstudio_import_hook import install_all
from sp_plugins.sdfstudio.conversion import replaces_coarse_to_fine
from sp_plugins.sdfstudio.detect import is_sdfstudio, nerfstudio_dir
from sp_plugins.sdfstudio.registration import REFUSED, add_methods
from sp_plugins.sdfstudio.table import FINAL_FD_STEP

PROG = "python -m sp_plugins.method_table"
ROOT = Path(__file__).resolve().parent.parent
def page(host: str, root: Path = ROOT) -> Path:
    """The docs page holding ``host``'s table under ``root`` (a checkout's root): the host's
    registry entry names it (:attr:`sp_plugins.adapter.hosts.Host.docs_page`)."""
    docs_page = hosts.get(host).docs_page
    if docs_page is None:
        raise ValueError(f"host {host!r} names no docs page for its method table (Host.docs_page)")
    return root / docs_page
HEADS = {
    "nerfstudio": "| nerfstudio method | under `sp-train METHOD` |",
    "sdfstudio": "| sdfstudio method | under `sp-sdfstudio-train sp-<method>` |",
}


def markers(host: str) -> Tuple[str, str]:
    return f"<!-- sp-methods:{host}:begin -->", f"<!-- sp-methods:{host}:end -->"


def installed_host() -> str:
    """The host whose ``nerfstudio`` package is importable here (``ValueError`` when none is)."""
    if nerfstudio_dir() is None:
        raise ValueError("neither nerfstudio nor sdfstudio is installed in this environment: run it in a host's environment")
    return "sdfstudio" if is_sdfstudio() else "nerfstudio"


def _alpha(sp) -> str:
    end = f"to 0 over the first {sp.end:.0%}" if sp.end <= 1 else f"to 0 by step {sp.end:g}"
    return f"alpha0 {sp.alpha0:g} {end}, boundary `{sp.boundary}`"


def nerfstudio_outcomes() -> Dict[str, Tuple[int, str]]:
    """Method -> (row order, what ``sp-train`` does with it), for every registered nerfstudio method."""
    from nerfstudio.configs.method_configs import all_descriptions, all_methods

    configs, _, refused = sp_methods(all_methods, all_descriptions)
    out: Dict[str, Tuple[int, str]] = {}
    for method, config in all_methods.items():
        model_config = getattr(getattr(config, "pipeline", None), "model", None)
        host = target_class(model_config) if model_config is not None else None
        cuda = lookup(nerfstudio_table.NEEDS_CUDA, host)
        if cuda:  # the same row on every machine
            out[method] = (2, f"refused without CUDA: {cuda[1]}")
        elif method in refused:
            out[method] = (3, f"refused: {refused[method]}")
        elif method in nerfstudio_table.SP_OFF_METHODS:
            out[method] = (1, f"offered (ours, SP off by default): {nerfstudio_table.SP_OFF_METHODS[method]}")
        elif getattr(model_config, "sp", None) is not None:
            out[method] = (1, "offered (ours, SP on already: its settings: Choosing SP's settings)")
        else:
            out[method] = (0, _nerfstudio_offered(configs[method].pipeline.model.sp, host))
    return out


def _nerfstudio_offered(sp, host: type) -> str:
    preset = lookup(nerfstudio_table.PRESETS, host)
    notes = [f"{_alpha(sp)} ({'the preset of ' + preset[0].rsplit('.', 1)[-1] if preset else 'the default preset'})"]
    notes += [f"`{name}` stays plain ({why})" for name, why in merged(nerfstudio_table.PLAIN_FIELDS, host).items()]
    grid = lookup(nerfstudio_table.ALPHA_GRID_UNREACHABLE, host)
    if grid:
        notes.append(f"`--pipeline.model.sp.alpha-grid True` refused ({grid[1][1]})")
    contracted = lookup(nerfstudio_table.CONTRACTED_MODELS, host)
    if contracted:
        flag = contracted[1]
        unless = f", unless `--pipeline.model.{flag.replace('_', '-')} True`" if flag else ""
        notes.append(f"`--pipeline.model.sp.boundary` must stay `none` (contracted scene{unless})")
    return "offered: " + "; ".join(notes)


def sdfstudio_outcomes() -> Dict[str, Tuple[int, str]]:
    """Host method -> (row order, what ``sp-sdfstudio-train sp-<method>`` does), for every method
    sdfstudio registers (our methods are its ``sp-`` entries)."""
    install_all()
    import scripts.train  # noqa: F401  (sdfstudio's own import order: base_config before method_configs)

    import nerfstudio.configs.method_configs as host

    add_methods()
    out: Dict[str, Tuple[int, str]] = {}
    for method, config in host.method_configs.items():
        if hasattr(config.pipeline.model, "sp"):
            continue  # ours: the sp- entry of a host method
        ours = host.method_configs.get(f"sp-{method}")
        if ours is None:
            out[method] = (1, f"refused: {REFUSED[f'sp-{method}']}")
            continue
        model_config = config.pipeline.model
        text = f"offered: {_alpha(ours.pipeline.model.sp)}"
        if replaces_coarse_to_fine(model_config):
            text = f"offered: coarse-to-fine (progressive hash encoding) replaced by SP, {_alpha(ours.pipeline.model.sp)}"
            fd = lookup(FINAL_FD_STEP, target_class(model_config))
            if fd and getattr(model_config, "enable_numerical_gradients_schedule", False):
                text += f"; finite-difference step fixed where sdfstudio's schedule ends ({fd[1]:g} / max_res)"
        out[method] = (0, text)
    return out


def table(host: str, outcomes: Optional[Dict[str, Tuple[int, str]]] = None) -> str:
    """The markdown table of ``host`` between its markers (of ``outcomes``, default: today's): methods
    with the same outcome share a row."""
    if outcomes is None:
        outcomes = nerfstudio_outcomes() if host == "nerfstudio" else sdfstudio_outcomes()
    groups: Dict[Tuple[int, str], List[str]] = defaultdict(list)
    for method in sorted(outcomes, key=str.lower):
        groups[outcomes[method]].append(method)
    rows = [f"| {', '.join(f'`{m}`' for m in methods)} | {text} |"
            for (_, text), methods in sorted(groups.items(), key=lambda g: (g[0][0], g[1][0].lower()))]
    begin, end = markers(host)
    return "\n".join([begin, HEADS[host], "|---|---|", *rows, end])


def write(root: Path, host: str) -> Path:
    """Refresh ``host``'s table in its docs page under ``root`` (its registry entry's ``docs_page``). Raises ``ValueError`` (one
    line) when the page has no such table; checked before the host is imported."""
    doc = page(host, root)
    text = doc.read_text() if doc.is_file() else ""
    begin, end = markers(host)
    if begin not in text or end not in text.partition(begin)[2]:
        raise ValueError(f"{doc} has no {begin} ... {end} table: run --write from the root of a sp-plugins checkout")
    head, _, rest = text.partition(begin)
    doc.write_text(head + table(host) + rest.partition(end)[2])
    return doc


def main(argv=None) -> None:
    """Print what SP does to each method of the host installed here; --write puts it into its docs page."""
    parser = argparse.ArgumentParser(prog=PROG, description=main.__doc__)
    parser.add_argument("--write", action="store_true", help="refresh the table in its docs page (docs/guides/) under the current folder (a checkout's root)")
    try:
        host = installed_host()
        message = f"wrote {write(Path.cwd(), host)} ({host})" if parser.parse_args(argv).write else table(host)
    except ValueError as err:
        parser.exit(2, f"{PROG}: error: {err}\n")
    print(message)


if __name__ == "__main__":
    main()
