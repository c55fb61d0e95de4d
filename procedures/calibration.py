"""What an off-line calibration's result says, as ``selfview calibrate`` reports it and a lab script reads it."""

from __future__ import annotations


def calibration_summary(res, cell, *, camera=None, camera_file=None, cov3=None, fit=None, cam_path=None) -> dict:
    """``res.summary()`` (an ``OfflineResult``) with the checks that go with it: the camera file used
    (``camera_file``, its fit ``fit`` from ``runs.refuse_unfitting_camera``), the picture against the
    assumed camera (``intrinsics.camera_check``), the TCP's 1-sigma [mm] (``intrinsics.tcp_sigma``; ``cov3``
    a camera file's covariance), the pictures kept, and ``warnings`` (a camera that does not fit but was
    forced, a picture that disagrees with the camera)."""
    from selfview.intrinsics import camera_check, tcp_sigma

    s = res.summary()
    s["camera_file"] = camera_file
    s["camera_file_fit"] = fit
    s["pictures"] = dict(res.calibration.pictures)
    warnings = []
    if fit and not fit["fits"]:
        warnings.append(f"{fit['refusal']}; written because of --force (measure this camera with "
                        "'selfview intrinsics')")
    chk = camera_check(res, cell, camera)
    if chk.get("warning"):
        w = chk["warning"]
        if camera is not None:
            w = "the picture disagrees with the camera file " + str(cam_path) + ": " + w
        warnings.append(w)
    s["camera_check"] = {k: v for k, v in chk.items() if k != "warning"}
    s["tcp_sigma_mm"] = tcp_sigma(res, cell, cov3)["tcp_sigma_mm"]
    s["warnings"] = warnings
    return s
