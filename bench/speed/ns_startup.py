"""What nerfstudio's external-method list costs every ``ns-*`` command, with and without our patch.

nerfstudio 1.1.5 builds its 26 installable external methods while importing its method configs,
and each one calls ``inspect.stack()`` (:mod:`sp_plugins.patches.nerfstudio_external_methods`).
This times ``get_external_methods()`` with the host's ``__post_init__`` and with ours, alternating in
one process (A B B A ...) after everything is imported, so the module count is what a real
``ns-train`` sees, with ``inspect``'s module caches emptied before each run as in a fresh process; the result is the median of per-pair ratios.

Usage: ``python -m bench.speed.ns_startup [--repeats 4]``
"""

from __future__ import annotations

import argparse
import inspect
import statistics
import time


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=4)
    args = p.parse_args(argv)

    import sys

    import nerfstudio.configs.method_configs  # noqa: F401  (the whole host, with our configs: the patch is in)
    from nerfstudio.configs import external_methods as ns_external

    from sp_plugins.patches import registry

    with registry.scope("nerfstudio_external_methods") as active:  # (its guard first; nerfstudio's again after)
        assert active, "the patch does not apply to this nerfstudio"
        cls = ns_external.ExternalMethodDummyTrainerConfig
        ours = cls.__post_init__
        variants = {"nerfstudio": ours.__sp_original__, "patched": ours}
        times = {name: [] for name in variants}
        order = ["nerfstudio", "patched", "patched", "nerfstudio"]
        for _ in range(args.repeats):
            for name in order:
                cls.__post_init__ = variants[name]
                inspect._filesbymodname.clear()  # a fresh process has not filled inspect's module caches yet
                inspect.modulesbyfile.clear()
                t0 = time.perf_counter()
                ns_external.get_external_methods()
                times[name].append(time.perf_counter() - t0)
    pairs = [a / b for a, b in zip(times["nerfstudio"], times["patched"])]
    print(f"modules loaded: {len(sys.modules)}")
    for name, ts in times.items():
        print(f"get_external_methods() with {name:10s}: median {statistics.median(ts):.4f} s over {len(ts)} runs")
    print(f"speed-up (median of pairs): {statistics.median(pairs):.0f}x;"
          f" saved per ns-* command: {statistics.median(times['nerfstudio']) - statistics.median(times['patched']):.2f} s")


if __name__ == "__main__":
    main()
