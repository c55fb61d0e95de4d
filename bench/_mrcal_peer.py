"""mrcal as a peer of the intrinsics benchmark, run in whichever interpreter has it.

mrcal ships as Debian's ``python3-mrcal`` for the system interpreter, built against that interpreter's
numpy; it is not on PyPI for this project's environment. So ``fit`` hands the observations to this same
file run as a script under an interpreter that imports mrcal (``find_python``), and reads one JSON object
back. That script part (``_solve``) needs numpy and mrcal only: it imports nothing of selfview.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np

LENSMODEL = "LENSMODEL_OPENCV4"
_CHECK = "import mrcal, numpy, scipy"


def find_python(timeout_s: float = 30.0) -> str | None:
    """An interpreter that imports mrcal, or None: ``SELFVIEW_MRCAL_PYTHON`` if set; else this one if it
    imports mrcal; else ``python3`` on the PATH and Debian's system interpreter ``/usr/bin/python3``
    (where ``python3-mrcal`` installs), the first that imports mrcal."""
    env = os.environ.get("SELFVIEW_MRCAL_PYTHON")
    candidates = [env] if env else [sys.executable, shutil.which("python3"), "/usr/bin/python3"]
    seen = set()
    for exe in candidates:
        if not exe or exe in seen or not os.path.exists(exe):
            continue
        seen.add(exe)
        try:
            r = subprocess.run([exe, "-c", _CHECK], capture_output=True, timeout=timeout_s)
        except (OSError, subprocess.TimeoutExpired):
            continue
        if r.returncode == 0:
            return exe
    return None


def mrcal_version(python: str) -> str | None:
    """mrcal's version as the module or its package says it (Debian's module carries none; its package
    manager does), or None."""
    r = subprocess.run([python, "-c", "import mrcal; print(getattr(mrcal, '__version__', ''))"],
                       capture_output=True, text=True, timeout=30)
    if r.returncode == 0 and r.stdout.strip():
        return r.stdout.strip()
    try:
        r = subprocess.run(["dpkg-query", "-W", "-f", "${Version}", "python3-mrcal"], capture_output=True, text=True,
                           timeout=30)
    except OSError:
        return None
    return f"{r.stdout.strip()} (Debian's python3-mrcal)" if r.returncode == 0 and r.stdout.strip() else None


#: how far a disc's plate coordinates may lie from the pitch grid [fraction of the pitch]: the detections'
#: plate coordinates are the grid's own; a quarter pitch off is another plate or a mislabelled disc
GRID_TOL = 0.25


def _grid(p_W_views, pitch):
    """(indices per view as (i, j) int arrays, W, H): the discs' grid positions from their plate coordinates.
    ``ValueError`` naming the view when a disc is off the pitch grid or two discs of a view share a place."""
    allp = np.vstack([np.asarray(p, float)[:, :2] for p in p_W_views])
    lo = allp.min(axis=0)
    idx = []
    for k, p in enumerate(p_W_views):
        g = (np.asarray(p, float)[:, :2] - lo) / pitch
        ij = np.rint(g).astype(int)
        off = np.abs(g - ij).max(initial=0.0)
        if off > GRID_TOL:
            raise ValueError(f"mrcal peer: view {k}: a disc lies {off:.2f} pitch off the plate's {pitch:g} mm grid")
        if len({(int(a), int(b)) for a, b in ij}) != len(ij):
            raise ValueError(f"mrcal peer: view {k}: two discs at one grid place")
        idx.append(ij)
    hi = np.vstack(idx).max(axis=0)
    return idx, int(hi[0]) + 1, int(hi[1]) + 1


def fit(p_W_views, uv_views, pitch: float, cam0, size, *, python: str | None = None, timeout_s: float = 300.0):
    """mrcal's calibration of the views: dict with ``f`` (fy), ``cx``, ``cy``, ``aspect`` (fy / fx, as the
    cv2 peer), ``dist`` [k1, k2, p1, p2], ``K`` (3x3), ``sigma`` of f, cx, cy, aspect, ``rms_px``, ``seconds``
    (mrcal's solve alone), ``outliers`` (disc centres mrcal's outlier rejection dropped), ``calobject_warp``; or None when no interpreter imports mrcal.
    Raises RuntimeError when mrcal ran and failed.

    The problem is the one ``cv2.calibrateCamera`` gets in ``bench/intrinsics.py``: the same views and
    detected disc centres. The plate is mrcal's calibration object (a regular grid at the plate's pitch,
    ``calobject_warp`` free: mrcal's model of a board that is not flat); discs hidden by the fingers or
    outside the picture are observations with a negative weight (mrcal's "ignore"). The lens model is
    ``LENSMODEL_OPENCV4``, the model its documentation starts from for a narrow lens; the poses are seeded
    by ``cv2.solvePnP`` with the cell's nominal camera (the cv2 peer's start). mrcal's outlier rejection
    and regularisation stay on, as in ``mrcal-calibrate-cameras``. Sigmas: mrcal reports projection
    uncertainty rather than parameter sigmas; here they are the square roots of the diagonal of
    sigma^2 (J^T J)^-1 at the solution (J: mrcal's own Jacobian, unpacked by its own scales), sigma the
    RMS reprojection error: the recipe of ours and OpenCV's."""
    import cv2

    python = python or find_python()
    if python is None:
        return None
    if len(p_W_views) != len(uv_views) or not p_W_views:
        raise ValueError(f"mrcal peer: {len(p_W_views)} views of plate points, {len(uv_views)} of pixels")
    for k, (p, uv) in enumerate(zip(p_W_views, uv_views)):
        if len(p) != len(uv) or len(p) < 4 or not np.all(np.isfinite(uv)):
            raise ValueError(f"mrcal peer: view {k}: {len(p)} plate points and {len(uv)} pixels (at least 4 finite "
                             "pairs wanted)")
    idx, W, H = _grid(p_W_views, pitch)
    n = len(uv_views)
    obs = np.zeros((n, H, W, 3))
    obs[..., 2] = -1.0  # not seen
    K0 = np.array([[cam0.f, 0, cam0.cx], [0, cam0.f, cam0.cy], [0, 0, 1.0]])
    frames = np.zeros((n, 6))
    for k, (ij, uv) in enumerate(zip(idx, uv_views)):
        uv = np.asarray(uv, float)
        obs[k, ij[:, 1], ij[:, 0], :2] = uv
        obs[k, ij[:, 1], ij[:, 0], 2] = 1.0
        board = np.column_stack([ij * pitch, np.zeros(len(ij))]).astype(np.float64)
        ok, rvec, tvec = cv2.solvePnP(board, uv.reshape(-1, 1, 2), K0, None, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            raise RuntimeError(f"mrcal peer: no seed pose for view {k}")
        frames[k] = np.r_[rvec.ravel(), tvec.ravel()]
    intr0 = np.array([cam0.f, cam0.f, cam0.cx, cam0.cy, 0, 0, 0, 0], float)
    with tempfile.TemporaryDirectory(prefix="selfview-mrcal-") as tmp:
        path = os.path.join(tmp, "problem.npz")
        np.savez(path, observations=obs, frames=frames, intrinsics=intr0, size=np.asarray(size, float),
                 spacing=np.float64(pitch))
        r = subprocess.run([python, os.path.abspath(__file__), path], capture_output=True, text=True,
                           timeout=timeout_s)
    if r.returncode != 0:
        raise RuntimeError(f"mrcal peer failed (exit {r.returncode}): {r.stderr.strip()[-600:]}")
    out = json.loads(r.stdout)
    fx, fy, cx, cy, k1, k2, p1, p2 = out["intrinsics"]
    s = out["sigma_intrinsics"]
    aspect = fy / fx
    return {
        "f": fy, "cx": cx, "cy": cy, "aspect": aspect, "dist": [k1, k2, p1, p2],
        "K": [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]],
        "sigma": {"f": s[1], "cx": s[2], "cy": s[3], "aspect": aspect * float(np.hypot(s[0] / fx, s[1] / fy))},
        "rms_px": out["rms_px"], "seconds": out["seconds"], "outliers": out["outliers"],
        "calobject_warp": out["calobject_warp"],
    }


def _solve(path: str) -> dict:
    """The script part: mrcal's solve of the problem in ``path`` (run under an interpreter with mrcal)."""
    import mrcal

    d = np.load(path)
    obs = np.ascontiguousarray(d["observations"], dtype=float)
    n = obs.shape[0]
    unseen = int(np.sum(obs[..., 2] < 0))  # mrcal counts these among its outliers
    intr = np.ascontiguousarray(d["intrinsics"][None, :], dtype=float)
    inputs = dict(
        intrinsics=intr,
        extrinsics_rt_fromref=np.zeros((0, 6)),
        frames_rt_toref=np.ascontiguousarray(d["frames"], dtype=float),
        points=None,
        observations_board=obs,
        indices_frame_camintrinsics_camextrinsics=np.array([[k, 0, -1] for k in range(n)], dtype=np.int32),
        observations_point=None,
        indices_point_camintrinsics_camextrinsics=None,
        lensmodel=LENSMODEL,
        imagersizes=np.array([d["size"]], dtype=np.int32),
        calobject_warp=np.zeros(2),
        do_optimize_intrinsics_core=True,
        do_optimize_intrinsics_distortions=True,
        do_optimize_extrinsics=False,
        do_optimize_frames=True,
        do_optimize_calobject_warp=True,
        calibration_object_spacing=float(d["spacing"]),
        do_apply_outlier_rejection=True,
        do_apply_regularization=True,
        verbose=False,
    )
    t = time.perf_counter()
    # as mrcal-calibrate-cameras: the core first (the distortion held at zero), then everything
    mrcal.optimize(**{**inputs, "do_optimize_intrinsics_distortions": False, "do_optimize_calobject_warp": False})
    stats = mrcal.optimize(**inputs)
    dt = time.perf_counter() - t
    rms = float(stats["rms_reproj_error__pixels"])
    inputs["do_apply_outlier_rejection"] = False
    _, _, J, _ = mrcal.optimizer_callback(**inputs, no_jacobian=False, no_factorization=True)
    J = J.toarray() if hasattr(J, "toarray") else np.asarray(J)
    cov_packed = np.linalg.pinv(J.T @ J) * rms**2
    scale = np.ones(J.shape[1])
    mrcal.unpack_state(scale, **inputs)
    i0 = mrcal.state_index_intrinsics(0, **inputs)
    ni = mrcal.num_states_intrinsics(**inputs)
    sig = np.sqrt(np.diag(cov_packed)[i0:i0 + ni]) * scale[i0:i0 + ni]
    return {
        "intrinsics": [float(v) for v in inputs["intrinsics"][0]],
        "sigma_intrinsics": [float(v) for v in sig],
        "rms_px": rms,
        "seconds": dt,
        "outliers": int(stats.get("Noutliers", unseen)) - unseen,
        "calobject_warp": [float(v) for v in inputs["calobject_warp"]],
    }


if __name__ == "__main__":
    print(json.dumps(_solve(sys.argv[1])))
