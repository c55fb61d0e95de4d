"""The optional compiled kernel of the silhouette fit, ``selfview.measurement._csil`` (built by ``pip install`` when a
C compiler is present; see ``selfview.measurement.silhouette``). ``SELFVIEW_PURE_PYTHON=1`` selects the numpy code.
``sil`` is the module or None, read at each call (a test may set it to None)."""

from __future__ import annotations

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
