"""The install claims only the project's own import name, and ships every package of the tree."""

from __future__ import annotations

import importlib
import importlib.metadata
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
FOLDERS = {"selfview": "selfview", "drivers": "selfview.drivers", "mocks": "selfview.mocks",
           "procedures": "selfview.procedures", "bench": "selfview.bench"}


def _project():
    return tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))


def test_every_folder_installs_under_selfview():
    tool = _project()["tool"]["setuptools"]
    assert tool["package-dir"] == {name: folder for folder, name in FOLDERS.items()}
    listed = set(tool["packages"])
    assert all(p == "selfview" or p.startswith("selfview.") for p in listed)
    found = set()
    for folder, name in FOLDERS.items():
        for init in (REPO / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(REPO / folder).parts
            found.add(".".join((name, *rel)))
    assert found == listed, f"packages missing from pyproject.toml: {sorted(found - listed)}; stale: {sorted(listed - found)}"


def test_the_installed_distribution_has_one_top_level_name():
    top = importlib.metadata.distribution("selfview").read_text("top_level.txt")
    assert top is not None and top.split() == ["selfview"]
    script = [e for e in importlib.metadata.entry_points(group="console_scripts") if e.name == "selfview"]
    assert [e.value for e in script] == ["selfview.procedures.cli:main"]


def test_no_generic_top_level_package_is_importable_outside_the_tree(tmp_path):
    """Outside the source tree (isolated mode: no working directory on the path), only selfview's names
    resolve; a lab's own ``procedures`` or ``drivers`` package cannot collide with ours."""
    code = ("import importlib\n"
            "for g in ('drivers', 'mocks', 'procedures', 'bench'):\n"
            "    try:\n"
            "        importlib.import_module(g)\n"
            "    except ModuleNotFoundError:\n"
            "        pass\n"
            "    else:\n"
            "        raise SystemExit(f'{g} is importable')\n"
            "import selfview.drivers.puma_val_serial, selfview.mocks.world, selfview.procedures.cli, selfview.bench\n"
            "print('ok')\n")
    res = subprocess.run([sys.executable, "-I", "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and res.stdout.strip() == "ok", res.stdout + res.stderr


@pytest.mark.parametrize("name", sorted(FOLDERS.values()))
def test_the_source_tree_imports_its_own_folders(name):
    mod = importlib.import_module(name)
    folder = {v: k for k, v in FOLDERS.items()}[name]
    assert Path(mod.__file__).resolve().parent == (REPO / folder).resolve()
