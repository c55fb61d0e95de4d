"""``sil``: the silhouette fit's compiled kernel or None (not built, or SELFVIEW_PURE_PYTHON=1); read at each call."""

import importlib
import os

PURE_PYTHON_ENV = "SELFVIEW_PURE_PYTHON"


def _load(name: str):
    """The compiled module ``<name>`` beside this one, or None (not built, or pure Python asked for)."""
    if os.environ.get(PURE_PYTHON_ENV, "").strip() not in ("", "0"):
        return None
    try:
        return importlib.import_module(f"{__package__}.{name}")
    except ImportError:
        return None


sil = _load("_csil")


def status() -> dict[str, bool]:
    """Whether the compiled kernel is in use: {'_csil': bool}."""
    return {"_csil": sil is not None}
