"""A run's results folder: results.json, tables.md, annotated pictures and the error plot.

A run never overwrites an earlier run's folder: ``new_run_dir`` picks a fresh name.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import platform
import sys
from pathlib import Path

import numpy as np

from selfview import __version__
from selfview.files.cell import POINT_NAMES
from selfview.maths.geometry import transform_points

__all__ = ["new_run_dir", "write_json", "annotate_offline", "draw_offline", "draw_plate_points", "offline_residuals", "draw_tracked", "keep_pictures", "annotate_online", "plot_errors", "environment"]


def new_run_dir(out: str | os.PathLike | None, base: str | os.PathLike = "runs", prefix: str = "experiment") -> Path:
    """A folder for a new run's results. ``out`` given: it must not exist yet or be empty (never
    overwrite an earlier run); otherwise ``base/prefix-YYYYmmdd-HHMMSS[-k]``."""
    if out is not None:
        p = Path(out)
        if p.exists() and (not p.is_dir() or any(p.iterdir())):
            from selfview.errors import ConfigError

            raise ConfigError(f"{p}: already holds an earlier run's results; choose a new --out folder")
        p.mkdir(parents=True, exist_ok=True)
        return p
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    b = Path(base)
    b.mkdir(parents=True, exist_ok=True)
    for k in range(1000):
        p = b / (f"{prefix}-{stamp}" + (f"-{k}" if k else ""))
        try:
            p.mkdir()
            return p
        except FileExistsError:
            continue
    raise RuntimeError(f"no free run folder under {b}")


def write_json(path: Path, obj) -> None:
    """``obj`` as JSON in ``path``, written atomically (``selfview.files.io_safe.atomic_write``)."""
    from selfview.files.io_safe import atomic_write

    atomic_write(path, json.dumps(obj, indent=1, allow_nan=True, default=_default).encode("utf-8"), what="results file")


def _default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON-serialisable: {type(o).__name__}")


def environment() -> dict:
    """Software and machine a run used, recorded beside its results."""
    import cv2

    out = {
        "selfview": __version__,
        "python": sys.version.split()[0],
        "numpy": np.__version__,
        "opencv": cv2.__version__,
        "platform": platform.platform(),
        "machine": platform.machine(),
        "cpus": os.cpu_count(),
    }
    from importlib import metadata

    for dist in ("pymodbus", "pyserial", "matplotlib"):
        try:  # read from the installed metadata: pymodbus stays imported by its one adapter module only
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:  # pragma: no cover
            out[dist] = None
    return out


# --- annotated pictures ---------------------------------------------------------------------------
def _bgr(img):
    import cv2

    return cv2.cvtColor(np.asarray(img, np.uint8), cv2.COLOR_GRAY2BGR)


def _pt(uv, scale):
    return int(round((uv[0] + 0.5) * scale - 0.5)), int(round((uv[1] + 0.5) * scale - 0.5))


def annotate_offline(image, result, path: Path, scale: int = 2) -> Path:
    """``draw_offline`` written to ``path``."""
    from selfview.files.io_safe import write_picture

    write_picture(path, draw_offline(image, result, scale), what="annotated picture")
    return path


def offline_residuals(result) -> list[dict]:
    """Each disc's residual: grid row and column, model minus the bias-corrected centre the fit used [px]
    (``OfflineResult.disc_residuals_px``: their RMS is the calibration's ``rms_px``), and its size on the
    plate [mm] (the pixels times the disc's depth over f)."""
    cal = result.calibration
    det = result.discs
    pC = transform_points(cal.C_H_W, det.p_W)
    d = result.disc_residuals_px()
    px = np.hypot(d[:, 0], d[:, 1])
    return [{"disc": f"{int(r)},{int(c)}", "du [px]": float(a), "dv [px]": float(b), "|r| [px]": float(n),
             "|r| [mm]": float(n * z / cal.camera.f)}
            for (r, c), (a, b), n, z in zip(det.rc, d, px, pC[:, 2])]


def draw_offline(image, result, scale: int = 2, vector_scale: float = 50.0):
    """The picture (``scale`` times bigger, BGR) with what the off-line calibration used and found: the
    discs' bias-corrected centres the fit used, with their grid indices (green), the model's reprojection
    of each disc centre (red cross) and its residual vector ``vector_scale`` times longer (orange, the
    residuals of ``offline_residuals``), the fingertip corners (yellow circles), the gripper rectangle and
    the TCP with G's x and y axes (cyan/magenta)."""
    import cv2

    cam = result.calibration.camera
    big = cv2.resize(_bgr(image), None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    det = result.discs
    used = np.asarray(result.disc_uv_corrected, float)
    model = used + result.disc_residuals_px()
    for (u, v), (r, c), m in zip(used, det.rc, model):
        cv2.circle(big, _pt((u, v), scale), 3 * scale, (0, 200, 0), 1, cv2.LINE_AA)
        cv2.drawMarker(big, _pt(m, scale), (0, 0, 255), cv2.MARKER_CROSS, 4 * scale, 1, cv2.LINE_AA)
        cv2.putText(big, f"{r},{c}", _pt((u + 4, v - 4), scale), cv2.FONT_HERSHEY_PLAIN, 0.6 * scale,
                    (0, 160, 0), 1, cv2.LINE_AA)
        tip = (u + vector_scale * (m[0] - u), v + vector_scale * (m[1] - v))
        cv2.arrowedLine(big, _pt((u, v), scale), _pt(tip, scale), (0, 140, 255), 1, cv2.LINE_AA, tipLength=0.3)
    _draw_gripper(big, cam, result.calibration.C_H_G, result.calibration.points_G[result.calibration.state], scale)
    _draw_corners(big, result.fingertips, scale)
    s = result.summary()
    txt = (f"f={s['f']:.1f}px kappa={s['kappa']:.2e} rms={s['rms_px']:.3f}px discs={s['discs_used']} "
           f"corners={len(s['corners_found'])}")
    cv2.putText(big, txt, (10, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 3, cv2.LINE_AA)
    cv2.putText(big, txt, (10, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 0, 0), 1, cv2.LINE_AA)
    legend = [("green: disc centres the fit used (bias-corrected), row,col", (0, 200, 0)),
              ("red: the model's projection of each disc centre", (0, 0, 255)),
              (f"orange: disc residuals (model minus used centre) x{vector_scale:g}", (0, 140, 255)),
              ("yellow: fingertip corners found", (0, 230, 230)),
              ("cyan: gripper points and the TCP; magenta: G's x axis; blue: G's y axis", (255, 255, 0))]
    for k, (text, colour) in enumerate(legend):
        _label(big, text, (10, 48 + 20 * k), colour)
    return big


def draw_plate_points(image, det, title: str, scale: int = 2, found: bool = True):
    """The picture (``scale`` times bigger, BGR) with the plate points ``det`` found in it (``detect_plate``'s, or
    None) circled with their grid indices row,col (green) and ``title`` at the top (green when ``found``, else
    red): what the live feed shows of the camera's current frame."""
    import cv2

    big = cv2.resize(_bgr(image), None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    if det is not None:
        for (u, v), (r, c) in zip(det.uv, det.rc):
            cv2.circle(big, _pt((u, v), scale), 3 * scale, (0, 230, 0), 2, cv2.LINE_AA)
            org = _pt((u + 7, v - 7), scale)
            cv2.putText(big, f"{r},{c}", org, cv2.FONT_HERSHEY_PLAIN, 0.7 * scale, (0, 0, 0), 4, cv2.LINE_AA)
            cv2.putText(big, f"{r},{c}", org, cv2.FONT_HERSHEY_PLAIN, 0.7 * scale, (90, 255, 90), 1, cv2.LINE_AA)
    cv2.putText(big, title, (12, 34), cv2.FONT_HERSHEY_SIMPLEX, 1.0, (0, 0, 0), 5, cv2.LINE_AA)
    cv2.putText(big, title, (12, 34), cv2.FONT_HERSHEY_SIMPLEX, 1.0, (0, 220, 0) if found else (40, 40, 255), 2,
                cv2.LINE_AA)
    return big


def _draw_gripper(big, cam, C_H_G, pG, scale, colour=(255, 255, 0)):
    import cv2

    rect = np.asarray(pG)[[0, 1, 3, 2, 0]]
    try:
        uv = cam.project(transform_points(C_H_G, rect))
        tcp = cam.project(transform_points(C_H_G, np.array([[0, 0, 0], [10, 0, 0], [0, 10, 0]], float)))
    except Exception:  # a wildly wrong estimate may lie behind the camera: draw nothing for it
        return
    pts = np.array([_pt(p, scale) for p in uv], np.int32)
    cv2.polylines(big, [pts], False, colour, 1, cv2.LINE_AA)
    cv2.drawMarker(big, _pt(tcp[0], scale), colour, cv2.MARKER_TILTED_CROSS, 8 * scale, 2, cv2.LINE_AA)
    cv2.arrowedLine(big, _pt(tcp[0], scale), _pt(tcp[1], scale), (255, 0, 255), 1, cv2.LINE_AA, tipLength=0.2)
    cv2.arrowedLine(big, _pt(tcp[0], scale), _pt(tcp[2], scale), (255, 128, 0), 1, cv2.LINE_AA, tipLength=0.2)


def draw_tracked(image, camera, C_H_G, pG, fingertips, scale: int = 2, boxes=None):
    """A tracked frame (BGR, ``scale`` times bigger): the gripper where ``C_H_G`` puts it (cyan), the
    fingers' silhouette there (``boxes``: [(lo, hi)] in G, green outlines) and the fingertip corners found
    (yellow, numbered)."""
    import cv2

    big = cv2.resize(_bgr(image), None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    for lo, hi in boxes or ():
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        try:
            uv = camera.project(transform_points(C_H_G, corners))
        except Exception:  # a box partly behind the camera: no outline for it
            continue
        hull = cv2.convexHull(np.array([_pt(p, scale) for p in uv], np.int32))
        cv2.polylines(big, [hull], True, (0, 255, 0), 1, cv2.LINE_AA)
    _draw_gripper(big, camera, C_H_G, pG, scale)
    _draw_corners(big, fingertips, scale)
    return big


def _draw_corners(big, fingertips, scale):
    import cv2

    for i in range(len(POINT_NAMES)):
        if fingertips.found[i]:
            uv = fingertips.uv[i]
            cv2.circle(big, _pt(uv, scale), 5 * scale, (0, 230, 230), 1, cv2.LINE_AA)
            cv2.putText(big, str(i + 1), _pt((uv[0] + 6, uv[1] + 12), scale), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                        (0, 230, 230), 1, cv2.LINE_AA)


def annotate_online(image, camera, C_H_G_before, estimates: dict, fingertips, pG, path: Path, scale: int = 2) -> Path:
    """Second picture of a trial: the fingertip corners found (yellow), the gripper where the first
    calibration predicts it (grey) and where each on-line method puts it (one colour each, named in the
    legend). The methods agree to a fraction of a pixel, so an inset shows each one's TCP apart: its
    offset from their mean, magnified (the factor and the largest offset written in it)."""
    import cv2

    from selfview.errors import CalibrationError

    big = cv2.resize(_bgr(image), None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    _draw_gripper(big, camera, C_H_G_before, pG, scale, (160, 160, 160))
    colours = [(0, 0, 255), (0, 128, 255), (0, 200, 0), (255, 0, 0), (255, 0, 255), (0, 255, 255), (128, 0, 128), (0, 100, 0)]
    tcp = {}
    for k, (m, est) in enumerate(estimates.items()):
        c = colours[k % len(colours)]
        _draw_gripper(big, camera, est.C_H_G_orth, pG, scale, c)
        _label(big, m, (10, 50 + 20 * k), c)
        try:
            tcp[m] = (camera.project(transform_points(est.C_H_G_orth, np.zeros((1, 3))))[0], c)
        except CalibrationError:  # an estimate behind the camera has no TCP in the picture
            pass
    for i in range(6):
        if fingertips.found[i]:
            cv2.circle(big, _pt(fingertips.uv[i], scale), 5 * scale, (0, 230, 230), 1, cv2.LINE_AA)
    _label(big, "grey: before the disturbance; colours: each method's estimate after it; yellow: fingertip corners",
           (10, 24), (220, 220, 220))
    if len(tcp) > 1:
        _tcp_inset(big, tcp)
    from selfview.files.io_safe import write_picture

    write_picture(path, big, what="annotated picture")
    return path


def _tcp_inset(big, tcp: dict, size: int = 300) -> None:
    """An inset at the bottom right: each method's TCP (``tcp``: name -> (uv [px], colour)) as its offset
    from their mean, magnified so the largest reaches 40 % of the inset."""
    import cv2

    mean = np.mean([uv for uv, _ in tcp.values()], axis=0)
    off = {m: uv - mean for m, (uv, _) in tcp.items()}
    worst = max(float(np.hypot(*d)) for d in off.values())
    gain = 0.4 * size / max(worst, 1e-6)
    h, w = big.shape[:2]
    x0, y0 = w - size - 10, h - size - 10
    big[y0:y0 + size, x0:x0 + size] = (big[y0:y0 + size, x0:x0 + size] * 0.15).astype(big.dtype)
    cv2.rectangle(big, (x0, y0), (x0 + size, y0 + size), (220, 220, 220), 1)
    cx, cy = x0 + size // 2, y0 + size // 2
    cv2.drawMarker(big, (cx, cy), (220, 220, 220), cv2.MARKER_CROSS, 20, 1)
    for m, d in off.items():
        p = (int(round(cx + gain * d[0])), int(round(cy + gain * d[1])))
        cv2.circle(big, p, 5, tcp[m][1], -1, cv2.LINE_AA)
    for k, text in enumerate(("each method's TCP:", f"offset from the mean x{gain:.0f}", f"largest {worst:.3f} px")):
        _label(big, text, (x0 + 6, y0 + 20 + 20 * k), (220, 220, 220))


def _label(img, text, org, colour):
    """Text with a dark outline, legible over the light plate and the dark fingers alike."""
    import cv2

    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 4, cv2.LINE_AA)
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.6, colour, 1, cv2.LINE_AA)


def plot_errors(summary: dict, path: Path, methods) -> Path | None:
    """Bar chart (log scale): mean (bar) and max (whisker, named in the legend) TCP error per method and camera
    axis, per series, against the off-line reference and against the truth; the paper's means as black ticks.
    None (nothing written) when no series has a trial that ran (every trial failed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from selfview.procedures.paper import PAPER_TABLES

    series = [s for s, v in summary.items() if isinstance(v, dict) and "methods" in v]
    if not series:
        return None
    fig, axes = plt.subplots(len(series), 2, figsize=(13, 4.2 * len(series)), squeeze=False)
    axis_names = ("c_x", "c_y", "c_z")
    for i, s in enumerate(series):
        for j, against in enumerate(("reference", "truth")):
            ax = axes[i][j]
            ms = [m for m in methods if against in summary[s]["methods"].get(m, {})]
            x = np.arange(len(ms))
            for k, an in enumerate(axis_names):
                # a log axis shows the paper's 0.2 mm beside our 0.002 mm; 1e-4 mm is the floor drawn
                means = [max(summary[s]["methods"][m][against]["mean_mm"][k], 1e-4) for m in ms]
                maxs = [max(summary[s]["methods"][m][against]["max_mm"][k], 1e-4) for m in ms]
                xs = x + (k - 1) * 0.27
                ax.bar(xs, means, width=0.25, label=f"{an} mean", color=f"C{k}")
                ax.errorbar(xs, means, yerr=[np.zeros(len(ms)), np.subtract(maxs, means)], fmt="none",
                            ecolor="k", elinewidth=0.8, capsize=2,
                            label="whisker: max over the trials" if k == 0 else None)
                if against == "reference":
                    pm = [PAPER_TABLES.get(s, {}).get(m, ((np.nan,) * 3,))[0][k] for m in ms]
                    ax.scatter(xs, pm, marker="_", s=120, color="k", zorder=5,
                               label="paper mean" if k == 0 else None)
            ax.set_xticks(x)
            ax.set_xticklabels(ms)
            ax.set_ylabel("TCP error [mm]")
            ax.set_yscale("log")
            ax.set_ylim(1e-4, 2.0)
            ax.set_title(f"{s}: against the {'off-line reference' if against == 'reference' else 'truth'}")
            ax.grid(axis="y", alpha=0.3)
            ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def keep_pictures(out, image, draw, kind: str = "") -> dict:
    """Write the picture a result was computed from and its annotated copy (``draw(image)``, BGR) beside
    ``out``, named by the picture's SHA-256 (an earlier run's pictures are never overwritten); returns
    {picture, annotated}: the file names, relative to ``out``'s folder. ``kind`` starts the names
    (``track-``: a tracked picture beside its calibration file)."""
    from selfview.errors import ConfigError
    from selfview.files.io_safe import write_picture

    out = Path(out)
    tag = hashlib.sha256(image.tobytes()).hexdigest()[:12]
    names = {}
    for role, img in (("picture", image), ("annotated", draw(image))):
        path = out.with_name(f"{out.stem}.{kind}{role}-{tag}.png")
        write_picture(path, img, error=ConfigError, what=f"{role} (--out)")
        names[role] = path.name
    return names
