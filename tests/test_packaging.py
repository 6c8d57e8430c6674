"""The package as installed and as the GPU scripts run it from the source tree: kernels/ is tlvg_warp.kernels.

kernels/ sits at the top level of the repository but belongs to the package; pyproject maps it (package-dir) and
lists every package explicitly, because a `packages.find` would not see it under its installed name (a wheel built
that way has no kernels and cannot render).
"""
import importlib.metadata
import importlib.util
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
    assert set(tool["packages"]) == _packages_on_disk() | {"tlvg_warp.configs"}  # configs/: data, no __init__.py
    assert tool["package-dir"]["tlvg_warp.kernels"] == "kernels"
    assert tool["package-dir"]["tlvg_warp.configs"] == "configs"


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


def test_a_wheel_carries_the_tuned_configs(tmp_path):
    """`pip install` from a wheel, run from a folder with no configs/: the default config is the wheel's copy of
    configs/tlvg.yaml (byte for byte), not the bare built-in defaults."""
    setuptools = pytest.importorskip("setuptools")
    if int(setuptools.__version__.split(".")[0]) < 71 and importlib.util.find_spec("wheel") is None:
        pytest.skip(f"setuptools {setuptools.__version__} builds wheels only with the `wheel` package, absent here")
    src = tmp_path / "src"
    for name in ("pyproject.toml", "README.md"):
        (src / name).parent.mkdir(parents=True, exist_ok=True)
        (src / name).write_bytes((REPO / name).read_bytes())
    import shutil

    for folder in ("tlvg_warp", "kernels", "configs"):
        shutil.copytree(REPO / folder, src / folder, ignore=shutil.ignore_patterns("__pycache__"))
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    subprocess.run(pip + ["wheel", "--no-deps", "--no-build-isolation", "-w", str(tmp_path / "whl"), str(src)],
                   check=True, capture_output=True, timeout=300)
    (wheel,) = (tmp_path / "whl").glob("*.whl")
    subprocess.run(pip + ["install", "--no-deps", "--target", str(tmp_path / "site"), str(wheel)],
                   check=True, capture_output=True, timeout=300)
    code = ("import sys\n"
            "sys.meta_path[:] = [f for f in sys.meta_path if 'ditable' not in repr(f)]\n"
            "from tlvg_warp.config_io import resolve_config\n"
            "print(resolve_config(None)); print(resolve_config('configs/abcgs.yaml'))\n")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env["PYTHONPATH"] = str(tmp_path / "site")
    r = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    default, preset = (Path(line) for line in r.stdout.split())
    assert default.is_relative_to(tmp_path / "site") and preset.is_relative_to(tmp_path / "site")
    assert default.read_bytes() == (REPO / "configs" / "tlvg.yaml").read_bytes()
    assert preset.read_bytes() == (REPO / "configs" / "abcgs.yaml").read_bytes()


def test_config_names_resolve_to_a_local_file_first_then_a_shipped_preset(tmp_path, monkeypatch):
    from tlvg_warp.config_io import resolve_config

    monkeypatch.chdir(tmp_path)
    shipped = (REPO / "configs" / "abcgs.yaml").read_bytes()
    for name in ("configs/abcgs.yaml", "abcgs.yaml", "abcgs"):
        assert resolve_config(name).read_bytes() == shipped, name
    (tmp_path / "configs").mkdir()
    (tmp_path / "configs" / "abcgs.yaml").write_text("iterations: 7\n")  # the user's own file wins
    assert resolve_config("configs/abcgs.yaml") == Path("configs/abcgs.yaml")
    for missing in ("configs/nosuch.yaml", str(tmp_path / "elsewhere" / "abcgs.yaml")):
        assert resolve_config(missing) == Path(missing)  # left for load_config to report
    # ... which names the shipped presets for a bare name (a retired or mistyped preset), not for a path elsewhere
    from tlvg_warp.config_io import read_yaml_mapping
    from tlvg_warp.errors import InputError

    shipped_names = sorted(f.stem for f in (REPO / "configs").glob("*.yaml") if not f.stem.startswith("study_"))
    with pytest.raises(InputError, match="shipped presets: " + ", ".join(shipped_names) + r"\)$"):
        read_yaml_mapping(resolve_config("tlvg_texture"))
    with pytest.raises(InputError) as e:
        read_yaml_mapping(resolve_config(str(tmp_path / "elsewhere" / "abcgs.yaml")))
    assert "presets" not in str(e.value) and str(e.value).endswith("config file does not exist")
    assert resolve_config(None, default=None) is None  # reconstruct: the class defaults
    assert resolve_config("reconstruct").read_bytes() == (REPO / "configs" / "reconstruct.yaml").read_bytes()
