"""The wheel a package index would serve: built with ``python -m build`` from a copy of this checkout,
installed into a fresh environment, then used as a user would (``ns-train --help``, ``sp-fit --help``,
``sp-demo``, the bundled assets).

The fresh environment reuses the torch / nerfstudio already installed for the suite instead of
installing them again (minutes and gigabytes): it is a venv *without* system site packages whose one
``.pth`` file adds, as site directories, a farm of symlinks to everything in this interpreter's
site-packages except our own editable install (its ``__editable__`` finder and ``.pth``, its
``sp_plugins-*.dist-info``). So ``import sp_plugins`` there can only find the wheel's copy, and every
check below also asserts that it did. Every command runs with its working directory outside the checkout
(``python -c`` would otherwise import ``./sp_plugins`` from the source tree).

About a minute and a half on one busy core: the build (an isolated build environment for the sdist,
another for the wheel), ``ns-train --help`` (nerfstudio imports every method), ``sp-demo`` shortened to
a few steps (``--budget quick`` is 300 steps, 1-2.5 minutes on its own; ``tests/cli/test_demo.py``
checks what the demo writes).
"""

from __future__ import annotations

import email.parser
import os
import re
import shutil
import site
import subprocess
import sys
import sysconfig
import tomllib
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
PACKAGE_DIRS = PYPROJECT["tool"]["setuptools"]["package-dir"]  # import name -> folder in the checkout
DEMO_STEPS = 20


def _run(cmd, cwd, env, timeout=300):
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{' '.join(map(str, cmd))} exited {proc.returncode}:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc


def _clean_env(**extra):
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "PYTHONSTARTUP")}
    env.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", COLUMNS="200", **extra)
    return env


def _source_copy(dest: Path) -> Path:
    """What a build reads, copied: the checkout's build/ and egg-info are left alone (a stale build/lib
    would put deleted modules into the wheel, and the suite's other workers read the egg-info)."""
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")
    for name in ("pyproject.toml", "README.md", "LICENSE"):
        shutil.copy2(ROOT / name, dest / name)
    for folder in sorted({Path(d).parts[0] for d in PACKAGE_DIRS.values()}):
        shutil.copytree(ROOT / folder, dest / folder, ignore=ignore)
    return dest


def _is_our_editable_install(name: str) -> bool:
    low = name.lower()
    return low.startswith("__editable__") or re.fullmatch(r"sp[-_]plugins-[^/]*\.(dist-info|egg-info|egg-link)", low) is not None


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    try:
        import build  # noqa: F401
    except ImportError:
        pytest.fail("`build` is missing: it is in the dev extra (pip install -e '.[dev]')")
    work = tmp_path_factory.mktemp("wheel")
    (work / "src").mkdir()
    src = _source_copy(work / "src")
    dist = work / "dist"
    # sdist first, then the wheel from the unpacked sdist: also checks that the sdist holds every file
    _run([sys.executable, "-m", "build", "--outdir", str(dist), str(src)], cwd=work, env=_clean_env(), timeout=600)
    (whl,) = dist.glob("sp_plugins-*.whl")
    return src, whl


@pytest.fixture(scope="module")
def fresh_env(wheel, tmp_path_factory):
    """A venv without system site packages, our wheel installed in it, the suite's other packages reachable."""
    _, whl = wheel
    work = tmp_path_factory.mktemp("fresh")
    env_dir = work / "venv"
    venv.EnvBuilder(with_pip=False, symlinks=os.name != "nt").create(env_dir)
    bindir = env_dir / ("Scripts" if os.name == "nt" else "bin")
    python = bindir / ("python.exe" if os.name == "nt" else "python")
    purelib = Path(_run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                        cwd=work, env=_clean_env()).stdout.strip())
    lines = []
    ours = {os.path.realpath(p) for p in (sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"])}
    for i, sitedir in enumerate(dict.fromkeys([*site.getsitepackages(), *ours])):
        if not os.path.isdir(sitedir):
            continue
        farm = work / f"site-{i}"
        farm.mkdir()
        for entry in os.listdir(sitedir):
            if not _is_our_editable_install(entry):
                (farm / entry).symlink_to(os.path.join(sitedir, entry))
        lines.append(f"import site; site.addsitedir({str(farm)!r})")
    (purelib / "zz-reuse-suite-packages.pth").write_text("\n".join(lines) + "\n")
    env = _clean_env()
    # pip comes from the farm; nothing named sp-plugins is installed there, so this is a first install
    _run([str(python), "-m", "pip", "install", "--no-deps", "--no-index", "--disable-pip-version-check", "-q", str(whl)],
         cwd=work, env=env)
    return python, bindir, purelib, env, work


def _assert_wheel_copy(text: str, purelib: Path):
    """Every ``FILE <path>`` line the command printed lies in the fresh environment's site-packages."""
    paths = [Path(line[5:]) for line in text.splitlines() if line.startswith("FILE ")]
    assert paths, "the command printed no FILE lines"
    for path in paths:
        assert purelib.resolve() in path.resolve().parents, f"imported {path}, not the wheel's copy under {purelib}"


def test_the_wheel_ships_every_module_the_assets_and_no_direct_reference(wheel):
    src, whl = wheel
    with zipfile.ZipFile(whl) as zf:
        names = set(zf.namelist())
        (metadata_name,) = [n for n in names if n.endswith(".dist-info/METADATA")]
        metadata = email.parser.Parser().parsestr(zf.read(metadata_name).decode())
        (ep_name,) = [n for n in names if n.endswith(".dist-info/entry_points.txt")]
        entry_points = zf.read(ep_name).decode()
    # every module of the mapped folders, under its import path (a package missing from pyproject's
    # list ships nothing while the editable install still imports it)
    expected = set()
    for package, folder in PACKAGE_DIRS.items():
        for f in (src / folder).rglob("*"):
            if f.is_file() and "__pycache__" not in f.parts and (f.suffix == ".py" or "assets" in f.parts):
                expected.add("/".join([*package.split("."), *f.relative_to(src / folder).parts]))
    missing = sorted(expected - names)
    assert not missing, f"the wheel lacks {missing}: list their packages in pyproject.toml [tool.setuptools]"
    assert "sp_plugins/data/assets/spot.ply" in names
    # nothing but sp_plugins at the top level: patches/ and method_configs/ ship inside it
    assert {n.split("/")[0] for n in names} == {"sp_plugins", metadata_name.split("/")[0]}
    # a package index refuses an upload whose metadata holds a direct reference, extras included
    requires = metadata.get_all("Requires-Dist") or []
    assert requires, "no Requires-Dist in METADATA"
    direct = [r for r in requires if " @ " in r or "@ git+" in r or "://" in r]
    assert not direct, f"direct references in Requires-Dist (the index refuses them): {direct}"
    for name in PYPROJECT["project"]["scripts"]:
        assert re.search(rf"^{re.escape(name)} = ", entry_points, re.M), f"console script {name} missing"
    for group, eps in PYPROJECT["project"]["entry-points"].items():
        assert f"[{group}]" in entry_points
        for name in eps:
            assert re.search(rf"^{re.escape(name)} = ", entry_points, re.M), f"{group}: {name} missing"


def test_the_installed_wheel_imports_from_its_own_copy_with_its_assets(fresh_env):
    python, _, purelib, env, work = fresh_env
    code = """
import sys, importlib.metadata as md
from importlib.resources import files
import sp_plugins, sp_plugins.method_configs.nerfstudio, sp_plugins.patches, sp_plugins.data.assets
for m in (sp_plugins, sp_plugins.method_configs.nerfstudio, sp_plugins.patches):
    print("FILE", m.__file__)
assert not any("__editable__" in type(f).__module__ for f in sys.meta_path), sys.meta_path
dist = md.distribution("sp-plugins")
print("FILE", dist.locate_file("sp_plugins/__init__.py"))
assets = files("sp_plugins.data.assets")
plys = sorted(p.name for p in assets.iterdir() if p.name.endswith(".ply"))
assert "spot.ply" in plys, plys
data = (assets / "spot.ply").read_bytes()
assert data.startswith(b"ply"), data[:20]
print("FILE", str(assets / "spot.ply"))
import trimesh
mesh = trimesh.load(str(assets / "spot.ply"), force="mesh")
assert len(mesh.faces) > 100, len(mesh.faces)
from sp_plugins.data.mesh import ASSETS
print("FILE", ASSETS / "spot.ply")
print("OK", plys, len(mesh.faces))
"""
    out = _run([str(python), "-c", code], cwd=work, env=env).stdout
    assert "OK" in out
    _assert_wheel_copy(out, purelib)
    assert str(ROOT) not in out, out


def test_ns_train_lists_our_methods_from_the_wheel(fresh_env):
    python, _, purelib, env, work = fresh_env
    # nerfstudio's own ns-train script runs the suite's interpreter: run its entry point in the fresh one
    code = """
import sys
from importlib.metadata import entry_points
(ep,) = [e for e in entry_points(group="console_scripts") if e.name == "ns-train"]
import sp_plugins; print("FILE", sp_plugins.__file__, flush=True)
sys.argv = ["ns-train", "--help"]
try:
    ep.load()()
except SystemExit as e:
    assert e.code in (0, None), e.code
for name, mod in sorted(sys.modules.items()):
    if name.startswith("sp_plugins") and getattr(mod, "__file__", None):
        print("FILE", mod.__file__)
"""
    out = _run([str(python), "-c", code], cwd=work, env=env).stdout
    _assert_wheel_copy(out, purelib)
    assert f"{os.sep}method_configs{os.sep}nerfstudio.py" in out, "ns-train loaded none of our method configs"
    for name in PYPROJECT["project"]["entry-points"]["nerfstudio.method_configs"]:
        assert re.search(rf"(?<![\w-]){re.escape(name)}(?![\w-])", out), f"ns-train --help does not list {name}"
    for name in ("sp-neus-hashgrid", "sp-mipnerf", "sp-relu-field"):
        assert name in out


def test_console_scripts_run_from_the_wheel(fresh_env):
    python, bindir, purelib, env, work = fresh_env
    for name in PYPROJECT["project"]["scripts"]:
        script = bindir / name
        assert script.is_file(), f"{name} not installed"
        first = script.read_text().splitlines()[0]
        assert str(bindir) in first, f"{name} runs {first}, not the fresh environment's python"
    out = _run([str(bindir / "sp-fit"), "--help"], cwd=work, env=env).stdout
    assert "usage" in out.lower() and "sp-fit" in out
    demo_help = _run([str(bindir / "sp-demo"), "--help"], cwd=work, env=env).stdout
    assert "--budget" in demo_help and "quick" in demo_help
    # the quick budget, cut to a few steps: the point is that the installed demo finds its scene and runs
    out_dir = work / "demo"
    proc = _run([str(bindir / "sp-demo"), "--budget", "quick", "--steps", str(DEMO_STEPS), "--mesh-resolution", "48", "--threads", "1",
                 "--out", str(out_dir)], cwd=work, env=env, timeout=400)
    assert "| metric | baseline | SP | SP / baseline |" in proc.stdout
    assert (out_dir / "results.json").is_file()
    assert (out_dir / "meshes" / "sp.ply").stat().st_size > 0


def test_the_readme_cpu_recipe_prints_from_the_wheel(fresh_env):
    """The README's fox line runs ``$(python -m sp_plugins.nerfstudio.recipes nerfacto-cpu)``: an installed
    user has no ``bench/``, so the recipe must come from the wheel."""
    python, _, purelib, env, work = fresh_env
    out = _run([str(python), "-m", "sp_plugins.nerfstudio.recipes", "nerfacto-cpu"], cwd=work, env=env).stdout
    assert out.split()[:2] == ["--pipeline.datamanager.train-num-rays-per-batch", "256"], out
    code = "import sp_plugins.nerfstudio.recipes as r; print('FILE', r.__file__)"
    _assert_wheel_copy(_run([str(python), "-c", code], cwd=work, env=env).stdout, purelib)
