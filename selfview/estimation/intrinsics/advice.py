"""The stop rule (are the centre and the aspect pinned?) and how many more views of which kind would pin them."""

from __future__ import annotations

import numpy as np

from selfview.maths.camera import CameraModel
from selfview.files.cell import PlateSpec
from selfview.maths.geometry import R_from_rotvecs
from selfview.estimation.intrinsics.fit import JointFit, sigmas_of
from selfview.estimation.intrinsics.model import JointProblem, intrinsics_vector, project_points
from selfview.estimation.intrinsics.plate import PlateShape


#: Stop rule: the centre pinned to sigma below this in each axis [px], the aspect to this relative sigma.
STOP_CENTRE_PX = 0.3
STOP_ASPECT_REL = 0.0005

#: Most further views the advice considers per kind.
MAX_MORE_VIEWS = 60
#: Kinds of further views the advice weighs: (label, tilt of the plate from square-on [deg]).
VIEW_KINDS = (("tilted 35 deg", 35.0), ("tilted 20 deg", 20.0), ("square-on", 0.0))


def stop_met(sig: dict, aspect: float) -> bool:
    return bool(max(sig["cx"], sig["cy"]) < STOP_CENTRE_PX and sig["aspect"] / aspect < STOP_ASPECT_REL)


def _views_information(camera: CameraModel, plate: PlateSpec, distance: float, views, s2: float, ni: int = 5,
                       shape: "PlateShape | None" = None, y=None) -> dict:
    """{(tilt, azimuth): (ni, ni) information one view adds on the intrinsics, its pose eliminated; None under 8 discs
    in the picture}: the plate's centre at ``distance`` [mm] on the optical axis, tilted by each of ``views`` (tilt,
    azimuth) [deg] about an in-plane axis, all in one Jacobian. With ``shape`` (at parameters ``y``): (ni + n_shape)
    square, intrinsics and shape."""
    p = plate.disc_centres_W()
    x = intrinsics_vector(camera, ni)
    out, P, UV, R_in, idx, used = {}, [], [], [], [], []
    tilt, a = np.radians(views).T
    Rs, t = R_from_rotvecs(np.column_stack([np.cos(a), np.sin(a), np.zeros_like(a)]) * tilt[:, None]), (0, 0, distance)
    uvs = project_points(x, np.eye(3), np.zeros(3), (Rs @ p.T).transpose(0, 2, 1).reshape(-1, 3) + t,
                         camera.skew).reshape(len(Rs), len(p), 2)  # all views in one projection
    alone = np.isnan(uvs).all()  # a disc behind the camera or past the lens's fold in some view: each by itself
    for view, R, uv in zip(views, Rs, uvs):
        uv = project_points(x, R, t, p, camera.skew) if alone else uv
        ok = np.all(np.isfinite(uv), axis=1)
        ok[ok] = camera.in_image(uv[ok], margin=10)
        out[view] = None
        if ok.sum() >= 8:
            P.append(p[ok]), UV.append(uv[ok]), R_in.append(R), idx.append(np.flatnonzero(ok)), used.append(view)
    if not used:
        return out
    V = len(used)
    model = JointProblem(P, UV, R_in, shape, idx if shape is not None else None, ni=ni, skew=camera.skew)
    J = model.jacobian(np.concatenate([x, *[np.r_[0.0, 0.0, 0.0, t] for _ in R_in], y if shape is not None else []]))
    J = J[: model.m_data]
    keep = np.r_[0:ni, ni + 6 * V : J.shape[1]]
    for k, view in enumerate(used):
        rows = slice(model.off[k], model.off[k + 1])
        Jk, Jp = J[rows][:, keep], J[rows, ni + 6 * k : ni + 6 * k + 6]
        Ak, Akp, App = Jk.T @ Jk / s2, Jk.T @ Jp / s2, Jp.T @ Jp / s2
        out[view] = Ak - Akp @ np.linalg.solve(App, Akp.T)
    return out


def more_views_advice(fit: JointFit, plate: PlateSpec) -> dict:
    """How many more views of each kind (``VIEW_KINDS``) would meet the stop rule: {distance_mm, views_needed {label:
    number or None}}; with a fitted plate shape on the joint information, as a further view shares that plate."""
    ni, ns = len(fit.cov5), len(fit.shape) if fit.plate_model != "flat" else 0
    shape = PlateShape(plate, fit.plate_model, fit.prior_noise_px, fit.dot_sd_mm) if ns else None
    if shape is not None and shape.n == ns:
        n = len(fit.cov_full)
        idx = np.r_[0:ni, n - ns : n]
        cov0 = fit.cov_full[np.ix_(idx, idx)]
    else:
        shape, cov0 = None, fit.cov5
    m = len(cov0)
    try:
        info0 = np.linalg.inv(cov0)
    except np.linalg.LinAlgError:
        info0 = np.zeros((m, m))
    if not np.all(np.isfinite(info0)):
        info0 = np.zeros((m, m))
    dist = float(np.median([v.distance_mm for v in fit.views]))
    out = {}
    azimuths = [(90.0 * (n - 1) + 45.0 * ((n - 1) // 4)) % 360.0 for n in range(1, MAX_MORE_VIEWS + 1)]
    # the 8 azimuths repeat: each one's information computed once (square-on, the azimuth turns nothing)
    seen = _views_information(fit.camera, plate, dist, [(t, a) for _, t in VIEW_KINDS
                                                        for a in (sorted(set(azimuths)) if t else [0.0])],
                              fit.s2, ni, shape, fit.shape if shape is not None else None)
    for label, tilt in VIEW_KINDS:
        adds = []
        for azimuth in azimuths:  # the views up to the first that does not see the plate
            add = seen[tilt, azimuth if tilt else 0.0]
            if add is None:
                break
            adds.append(add)
        infos = info0 + np.cumsum(adds, axis=0) if adds else []

        def met(k, infos=infos):  # the stop rule met with the first k + 1 further views
            try:  # the intrinsics' block of the inverse: a solve for its ni columns, not a whole inverse
                cov = np.linalg.solve(infos[k], np.eye(m)[:, :ni])[:ni]
            except np.linalg.LinAlgError:
                return False
            return bool(np.all(np.isfinite(cov)) and np.all(np.diag(cov) > 0)
                        and stop_met(sigmas_of(cov), fit.camera.aspect))

        # each view adds positive semi-definite information, so the sigmas only fall: bisection for the fewest
        lo, hi = 0, len(adds)
        while lo < hi:
            mid = (lo + hi) // 2
            lo, hi = (lo, mid) if met(mid) else (mid + 1, hi)
        out[label] = lo + 1 if lo < len(adds) else None
    return {"distance_mm": dist, "views_needed": out}
