"""Every name a core module lists in ``__all__`` is defined there (a name left behind by a move is not)."""

import importlib
import pkgutil

import pytest



def _core_modules():
    names = ["selfview", "selfview.api", "selfview.errors"]
    for pkg in ("measurement", "estimation", "estimation.intrinsics", "maths", "files"):
        m = importlib.import_module(f"selfview.{pkg}")
        names += [f"selfview.{pkg}"] + [f"selfview.{pkg}.{i.name}" for i in pkgutil.iter_modules(m.__path__)
                                         if not i.name.startswith("_")]
    return names


@pytest.mark.parametrize("name", _core_modules())
def test_every_public_name_is_defined(name):
    m = importlib.import_module(name)
    missing = [a for a in getattr(m, "__all__", ()) if not hasattr(m, a)]
    assert missing == [], f"{name}.__all__ lists {missing}, which it does not define"
