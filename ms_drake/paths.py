"""Where the ms_drake_models package lives, a Drake Parser that finds it, and which code runs.

`models/` (with its package.xml) is found as `package://ms_drake_models/...` both from a
source checkout (the `models/` folder beside the `ms_drake/` folder) and from an installed
wheel (where it is installed as the Python package `ms_drake_models`).
"""

from __future__ import annotations

import functools
import importlib.metadata
import importlib.util
import subprocess
from pathlib import Path

from pydrake.multibody.parsing import Parser

PACKAGE_NAME = "ms_drake_models"


@functools.cache
def models_dir() -> Path:
    """The folder holding models/package.xml."""
    checkout = Path(__file__).resolve().parent.parent / "models"
    if (checkout / "package.xml").is_file():
        return checkout
    spec = importlib.util.find_spec(PACKAGE_NAME)
    if spec is not None and spec.submodule_search_locations:
        for loc in spec.submodule_search_locations:
            if (Path(loc) / "package.xml").is_file():
                return Path(loc)
    raise FileNotFoundError(
        "Cannot find the ms_drake_models package (models/package.xml). Reinstall ms_drake "
        "with `pip install -e .` from the checkout."
    )


def model_path(relative: str) -> Path:
    """Absolute path of a file inside models/, e.g. model_path('environments/bin.sdf')."""
    return models_dir() / relative


def make_parser(plant, scene_graph=None):
    """A Drake Parser that knows package://ms_drake_models and refuses drake_models.

    `package://drake_models/...` would download at run time; we remove it so an accidental
    use fails at once with "unknown package".
    """
    parser = Parser(plant, scene_graph) if scene_graph is not None else Parser(plant)
    pm = parser.package_map()
    if pm.Contains("drake_models"):
        pm.Remove("drake_models")
    if not pm.Contains(PACKAGE_NAME):
        pm.Add(PACKAGE_NAME, str(models_dir()))
    return parser


def _git(root: Path, *args: str) -> str:
    try:
        p = subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, timeout=10)
    except (OSError, subprocess.SubprocessError):
        return ""
    return p.stdout.strip() if p.returncode == 0 else ""


@functools.cache
def code_version() -> str:
    """The code this process runs, for benchmark records: in a git checkout its short commit, with
    "+dirty" when ms_drake/ or models/ differ from it; otherwise the installed package's version
    ("ms_drake <version>")."""
    root = Path(__file__).resolve().parent.parent
    top = _git(root, "rev-parse", "--show-toplevel")
    if top and Path(top).resolve() == root:
        head = _git(root, "rev-parse", "--short", "HEAD")
        if head:
            return head + ("+dirty" if _git(root, "status", "--porcelain", "--", "ms_drake", "models") else "")
    try:
        return f"ms_drake {importlib.metadata.version('ms_drake')}"
    except importlib.metadata.PackageNotFoundError:
        return "unknown"
