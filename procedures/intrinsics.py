"""Measuring a camera from pictures of a plate, as a lab script calls it (``selfview intrinsics --images``).

    from selfview.files.cell import load_plate
    from selfview.procedures.intrinsics import measure_intrinsics
    res = measure_intrinsics(pictures, load_plate("plate.yaml"))

and on a cell, the robot taking the views (``selfview experiment --intrinsics``, ``selfview grasp``):

    camera, info = measure_camera(session)
"""

from __future__ import annotations

import time

from selfview.maths.camera import CameraModel
from selfview.files.cell import PlateSpec
from selfview.errors import ImageError
from selfview.estimation.intrinsics import IntrinsicsResult, calibrate_intrinsics, detect_views, guess_camera


def measure_intrinsics(images, plate: PlateSpec, camera: CameraModel | None = None, names=None, *,
                       skip_unusable: bool = False, plate_model: str = "auto") -> IntrinsicsResult:
    """``calibrate_intrinsics`` of (H, W) pictures of ``plate``; ``camera`` the starting camera (a cell's
    nominal one), or None: one from the pictures themselves (``intrinsics.guess_camera``; every picture
    of the first one's size). Raises ``ImageError`` or ``CalibrationError`` as ``calibrate_intrinsics``,
    ``ConfigError`` when ``names`` does not name every picture once."""
    from selfview.errors import ConfigError

    images = list(images)
    if names is not None:
        names = list(names)
        if len(names) != len(images):  # zipped, the pictures past the last name would be dropped unsaid
            raise ConfigError(f"intrinsics: {len(images)} picture(s) but {len(names)} name(s); give one name per picture")
    if camera is not None:
        return calibrate_intrinsics(images, plate, camera, names, skip_unusable=skip_unusable, plate_model=plate_model)
    names = names if names is not None else [f"view {i + 1}" for i in range(len(images))]
    if not images:
        raise ImageError("intrinsics: no pictures given")
    sizes = {tuple(getattr(im, "shape", (0, 0))[:2]) for im in images}
    if len(sizes) != 1:
        raise ImageError(f"intrinsics: the pictures have different sizes {sorted(sizes)}; one camera gives one size")
    h, w = sizes.pop()
    dets, kept, skipped = detect_views(images, plate, None, names, skip_unusable=skip_unusable)
    res = calibrate_intrinsics(None, plate, guess_camera(dets, w, h), kept, detections=dets, plate_model=plate_model)
    res.skipped = list(skipped) + list(res.skipped)
    return res


def intrinsics_warnings(res: IntrinsicsResult) -> list[str]:
    """What the operator must know about a measured camera: pictures not used, the stop rule not met (with
    the advice), the two halves of the views disagreeing."""
    warnings = [f"{sk['name']} not used: {sk['reason']}" for sk in res.skipped]
    if not res.stop_rule["met"]:
        warnings.append("stop rule not met: sigma of the centre {:.3f} px (limit {}), of the aspect {:.4f} % (limit {} %); {}".format(
            res.stop_rule["sigma_centre_px"], res.stop_rule["limit_centre_px"], res.stop_rule["sigma_aspect_pct"],
            res.stop_rule["limit_aspect_pct"], res.stop_rule.get("advice", "")))
    xc = res.cross_check
    if xc.get("done") and not xc.get("agree"):
        worst = max(xc["ratio"], key=xc["ratio"].get)
        warnings.append(f"the two halves of the views disagree: {worst} differs by {xc['ratio'][worst]:.1f} combined sigmas "
                        f"(limit {xc['limit_sigmas']:g}); a view may be blurred, or the camera moved between views")
    return warnings


def measure_camera(session, say=None, view=None, views: int = 12):
    """Measure the cell's camera as a lab does with a new one: the robot takes ``views`` views of the plate
    (``CellSession.intrinsics_views``, shown on ``view``, the command line's live page, with its live feed;
    None: no page), ``calibrate_intrinsics``; ``say`` (a callable taking a line, or None) hears the progress.
    Returns (the measured ``CameraModel``, {measured, sigma, views_used, stop_rule_met}), or (None, None) in
    a dry run. Raises as ``calibrate_intrinsics`` when the views do not measure it."""
    from selfview.procedures.livefeed import live_feed
    from selfview.procedures.view import ViewProgress, watch

    say = say or (lambda line: None)
    cell = session.cell
    t_cam = time.monotonic()
    progress = ViewProgress(say, views, session.engine, cell, view)
    with live_feed(view, session, progress) as feed:
        watch(view, session, progress, feed and feed.on_step)
        got = session.intrinsics_views(views)
    watch(view, session)
    if got is None:
        return None, None
    say(f"measuring the camera from {len(got[0])} views")
    intr = calibrate_intrinsics(got[0], cell.plate, cell.camera.guess(), skip_unusable=True)
    camera = intr.camera
    say(f"camera measured from {intr.views_used} views: centre ({camera.cx:.2f}, {camera.cy:.2f}) px, "
        f"aspect {camera.aspect:.5f}, f {camera.f:.2f} px (the camera took {time.monotonic() - t_cam:.1f} s)")
    return camera, {"measured": camera.to_dict(), "sigma": intr.sigma, "views_used": intr.views_used,
                    "stop_rule_met": intr.stop_rule["met"]}
