"""The camera model against Reg Willson's published Tsai run (``reference/tsai-willson``).

Projecting ``cc_cd.dat`` through the fitted model ``cc_cpcc.dat`` must give the error statistics that
``ccal.log`` prints for it (the "full optimization" section), in this project's pixel units:
f / dpy [px], kappa1 * dpy^2 [px^-2], centre (Cx, Cy), aspect dpx / (sx dpy), R = Rz Ry Rx.
"""

from __future__ import annotations

import numpy as np
import pytest

from selfview.maths.camera import CameraModel
from selfview.maths.geometry import R_from_rpy, make_H, transform_points
from selfview.estimation.tsai import load_willson_points
from selfview.estimation.tsai import parse_willson_log as willson_sections



def willson_camera(cpcc_path, width=576, height=384):
    """(CameraModel, C_H_W) from a Willson 'cp/cc' file of 19 numbers (see the reference README)."""
    c = np.loadtxt(cpcc_path)
    assert c.shape == (19,)
    _, _, _, _, dpx, dpy, cx, cy, sx, f, k1, tx, ty, tz, rx, ry, rz, _, _ = c
    cam = CameraModel(
        f=f / dpy, kappa=k1 * dpy**2, cx=cx, cy=cy, aspect=dpx / (sx * dpy), width=width, height=height
    )
    return cam, make_H(R_from_rpy(rx, ry, rz), [tx, ty, tz])


@pytest.fixture(scope="module")
def willson(willson_dir):
    d = willson_dir
    p_W, uv = load_willson_points(d / "cc_cd.dat")
    sections = willson_sections((d / "ccal.log").read_text())
    return d, p_W, uv, sections


def test_log_parser_finds_both_coplanar_runs(willson):
    _, _, _, sections = willson
    assert set(sections) == {
        "Coplanar calibration (Tz, f, kappa1 optimization)",
        "Coplanar calibration (full optimization)",
    }
    full = sections["Coplanar calibration (full optimization)"]
    assert full["f"] == 257.133427 and full["Cx"] == 262.156687 and full["distorted_sse"] == 1.213781


def test_projection_reproduces_the_published_errors_to_every_digit(willson):
    d, p_W, uv, sections = willson
    log = sections["Coplanar calibration (full optimization)"]
    cam, C_H_W = willson_camera(d / "cc_cpcc.dat")
    p_C = transform_points(C_H_W, p_W)

    # distorted image plane: observed pixels against the projection through eq. 1-4 (distortion inverted)
    e = np.linalg.norm(uv - cam.project(p_C), axis=1)
    assert round(float(e.mean()), 6) == log["distorted_mean"]
    assert round(float(e.max()), 6) == log["distorted_max"]
    assert round(float(np.sum(e**2)), 6) == log["distorted_sse"]
    assert round(float(e.std(ddof=1)), 6) == log["distorted_stddev"]

    # undistorted image plane: observed pixels corrected by eq. 4 against eq. 3
    eu = np.linalg.norm(cam.undistort_pixels(uv) - cam.project_undistorted(p_C), axis=1)
    assert round(float(eu.mean()), 6) == log["undistorted_mean"]
    assert round(float(eu.max()), 6) == log["undistorted_max"]
    assert round(float(np.sum(eu**2)), 6) == log["undistorted_sse"]


def test_model_parameters_match_the_log(willson):
    d, _, _, sections = willson
    log = sections["Coplanar calibration (full optimization)"]
    cam, C_H_W = willson_camera(d / "cc_cpcc.dat")
    assert cam.f * 0.023 == pytest.approx(log["f"], abs=5e-7)
    assert cam.kappa / 0.023**2 == pytest.approx(log["kappa1"], rel=1e-6)
    assert (cam.cx, cam.cy) == pytest.approx((log["Cx"], log["Cy"]), abs=5e-7)
    assert C_H_W[:3, 3] == pytest.approx([log["Tx"], log["Ty"], log["Tz"]], abs=5e-7)
    # the R printed in the log is Rz Ry Rx of the printed angles
    R = R_from_rpy(*np.radians([log["Rx"], log["Ry"], log["Rz"]]))
    assert np.abs(R - C_H_W[:3, :3]).max() < 1e-6
