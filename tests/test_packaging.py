"""The package as installed and as the GPU scripts run it from the source tree: kernels/ is tlvg_warp.kernels.

kernels/ sits at the top level of the repository but belongs to the package; pyproject maps it (package-dir) and
lists every package explicitly, because a `packages.find` would not see it under its installed name (a wheel built
that way has no kernels and cannot render).
"""
import importlib.metadata
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _packages_on_disk() -> set[str]:
    """Every folder holding an __init__.py, named as it installs."""
    names = set()
    for init in REPO.glob("tlvg_warp/**/__init__.py"):
        names.add(".".join(init.parent.relative_to(REPO).parts))
    for init in REPO.glob("kernels/**/__init__.py"):
        names.add(".".join(("tlvg_warp",) + init.parent.relative_to(REPO).parts))
    return names


def test_pyproject_lists_every_package_and_maps_kernels():
    tomllib = pytest.importorskip("tomllib", reason="tomllib is in the standard library from Python 3.11")
    tool = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert set(tool["packages"]) == _packages_on_disk()
    assert tool["package-dir"]["tlvg_warp.kernels"] == "kernels"


def _import_kernels(env: dict, cwd: Path, drop_editable: bool = False) -> str:
    code = ("import sys\n"
            + ("sys.meta_path[:] = [f for f in sys.meta_path if 'ditable' not in repr(f)]\n" if drop_editable else "")
            + "import tlvg_warp.kernels.blend as b\nprint(b.__file__)\n")
    r = subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    return r.stdout.strip()


def test_installed_package_has_its_kernels(tmp_path):
    """From a folder outside the repository, with nothing on PYTHONPATH: what `pip install` put in place."""
    try:
        importlib.metadata.distribution("tlvg_warp")
    except importlib.metadata.PackageNotFoundError:
        pytest.skip("tlvg_warp is not installed (pip install -e .)")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    found = Path(_import_kernels(env, tmp_path))
    assert found.name == "blend.py" and found.parent.name == "kernels"


def test_source_view_runs_the_tree_uninstalled(tmp_path):
    """benchmarks/source_view.sh: with the install's import hook removed, the view alone resolves the kernels to
    this tree's kernels/ (what the GPU machine, which installs nothing, relies on)."""
    view = subprocess.run(["bash", "-c", f"source benchmarks/source_view.sh && source_view {REPO}"], cwd=REPO,
                          capture_output=True, text=True, timeout=60, check=True).stdout.strip()
    env = dict(os.environ, PYTHONPATH=view)
    found = Path(_import_kernels(env, tmp_path, drop_editable=True))
    assert found.resolve() == (REPO / "kernels" / "blend.py").resolve()
    assert str(found).startswith(view)


def test_benchmark_scripts_do_not_shadow_the_package():
    """A benchmark that puts the repository root first on sys.path imports tlvg_warp from there, without its kernels
    when nothing is installed (the GPU machine): the root may only be appended."""
    for script in (REPO / "benchmarks").glob("*.py"):
        assert "sys.path.insert(0" not in script.read_text(), script.name
