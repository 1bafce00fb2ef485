"""The wheel holds the code, the models and the scenarios, and works outside the checkout."""

import importlib.util
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def test_every_subpackage_is_listed_in_pyproject():
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {"ms_drake"} | {f"ms_drake.{p.parent.name}" for p in (ROOT / "ms_drake").glob("*/__init__.py")}
    assert found <= listed, f"add {sorted(found - listed)} to [tool.setuptools] packages"


def _wheel_runs_from_elsewhere(tmp_path, *build_options):
    """Build the wheel (no dependencies), install it with --no-deps into a folder of its own and
    build a station from a shipped scenario there, outside the checkout."""
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", *build_options, "-q", "-w", str(tmp_path),
                    str(ROOT)], check=True)
    (whl,) = tmp_path.glob("ms_drake-*.whl")
    names = zipfile.ZipFile(whl).namelist()
    assert "ms_drake_models/package.xml" in names
    assert "ms_drake_diagrams/scenarios.yaml" in names
    assert any(n.startswith("ms_drake_models/robots/") for n in names)
    target = tmp_path / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(target), str(whl)],
                   check=True)
    code = ("import ms_drake.paths as p, ms_drake.scenario as s; "
            "assert 'site' in str(p.models_dir()), p.models_dir(); "
            "sc = s.load_scenario(None, 'BinHeap15'); "
            "from ms_drake.station import MakeStation; MakeStation(sc); print('ok')")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True,
                         env={"PYTHONPATH": str(target), "PATH": "/usr/bin:/bin"})
    assert out.stdout.strip() == "ok", out.stderr


def test_wheel_contains_models_and_runs_from_elsewhere(tmp_path):
    """Built with this environment's setuptools (no isolated build environment: ~3 s less)."""
    if importlib.util.find_spec("setuptools") is None:
        pytest.fail("the fast wheel build uses the installed setuptools: pip install 'setuptools>=69'")
    _wheel_runs_from_elsewhere(tmp_path, "--no-build-isolation")


@pytest.mark.slow
def test_wheel_builds_in_an_isolated_environment_and_runs_from_elsewhere(tmp_path):
    """Built as a user's pip does, in a fresh environment with only the declared build requirements."""
    _wheel_runs_from_elsewhere(tmp_path)
