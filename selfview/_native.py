"""The optional compiled kernels of the on-line per-frame step, and the switch between them and the
pure-Python reference.

Three C extension modules, built by ``pip install`` when a C compiler is present (``setup.py``; a failed
build leaves the package working on the Python code):

- ``selfview._cnpu``: the on-line solves for the common case (finite input, points in front of the
  camera, a system well enough conditioned that the cheap bound settles it): ``np_u``, the paper's
  differential update (``online.differential_update``, eq. 15-17 and the least squares), and ``np_i``,
  the Gauss-Newton on SE(3) of NP-I and of NP-R's refinement (``online._gauss_newton``);
- ``selfview._ctrack``: the tracker's profile sampling, step location and robust line fits
  (``tracking.FingertipTracker``);
- ``selfview._csil``: the model-based measurement's edge sampling, candidates, IRLS and vote
  (``silhouette._sample``, ``_candidates``, ``_solve``, ``_coarse_shift``; their numpy code
  ``_sample_py``, ``_candidates_np``, ``_solve_py``, ``_votes_py`` the reference).

Each computes what the Python code beside it computes (``_cnpu`` and ``_ctrack`` in the same order of
operations, ``_csil`` to rounding: its sums in another order), and hands any
case it does not handle (bad input, a degenerate system, no convergence) back to the Python code, which
raises the errors. The Python code is the reference: the tests run both on the same input and compare them.

Set ``SELFVIEW_PURE_PYTHON=1`` in the environment to run the Python code only. The modules are looked
up when this module is first imported; ``npu``, ``track`` and ``sil`` are the modules or None, read at each call
(a test may set them to None)."""

from __future__ import annotations

import importlib
import os

PURE_PYTHON_ENV = "SELFVIEW_PURE_PYTHON"


def _load(name: str):
    """The compiled module ``selfview.<name>``, or None (not built, or pure Python asked for)."""
    if os.environ.get(PURE_PYTHON_ENV, "").strip() not in ("", "0"):
        return None
    try:
        return importlib.import_module(f"selfview.{name}")
    except ImportError:
        return None


npu = _load("_cnpu")
track = _load("_ctrack")
sil = _load("_csil")


def status() -> dict[str, bool]:
    """Which compiled kernels are in use: {'_cnpu': bool, '_ctrack': bool, '_csil': bool}."""
    return {"_cnpu": npu is not None, "_ctrack": track is not None, "_csil": sil is not None}
