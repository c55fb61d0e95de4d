"""What the views say about a richer model: the held-out check (each view left out in turn, to first order,
``fit.leave_views_out``) as a one-sided paired t-test over the views, and the chi-square test of parameters
against 0 with the pixel noise estimated. Both without refits."""

from __future__ import annotations

import math

import numpy as np

from selfview.estimation.intrinsics.fit import JointFit, leave_views_out


def student_t_sf(t: float, dof: int) -> float:
    """P(T > t) of Student's t with ``dof`` degrees of freedom (by quadrature: T = sqrt(dof) tan(u), whose
    density in u is proportional to cos(u)^(dof - 1))."""
    if dof < 1:
        raise ValueError(f"student_t_sf: expected dof >= 1, got {dof}")
    u = np.linspace(math.atan(t / math.sqrt(dof)), math.pi / 2, 4001)
    c = math.exp(math.lgamma((dof + 1) / 2) - math.lgamma(dof / 2)) / math.sqrt(math.pi)
    y = np.cos(u) ** (dof - 1)
    return float(c * np.sum((y[1:] + y[:-1]) / 2 * np.diff(u)))


def chi2_3_sf(x: float) -> float:
    """P(X > x) of a chi-square with 3 degrees of freedom."""
    x = max(float(x), 0.0)
    return math.erfc(math.sqrt(x / 2)) + math.sqrt(2 * x / math.pi) * math.exp(-x / 2)


def wald_chi2(value, cov) -> float:
    """value^T cov^-1 value: the chi-square of ``value`` against 0 (inf when ``cov`` is singular)."""
    value = np.asarray(value, float)
    try:
        return float(value @ np.linalg.solve(np.asarray(cov, float), value))
    except np.linalg.LinAlgError:
        return math.inf


def heldout_test(simple: JointFit, rich: JointFit) -> dict:
    """Does ``rich`` predict the views left out better than ``simple``? Per view common to both (by name):
    the mean square of its residuals predicted from the other views (its pose refitted to it), simple minus
    rich; their mean over its standard error is t, with one fewer degrees of freedom than views; ``p`` the
    one-sided p-value (small: the rich model predicts better). {views, t, p, rms_simple_px, rms_rich_px}."""
    hs, hr = leave_views_out(simple)[1], leave_views_out(rich)[1]
    ns, nr = [v.name for v in simple.views], [v.name for v in rich.views]
    common = [nm for nm in nr if nm in ns]
    a = np.array([hs[ns.index(nm)] for nm in common])
    b = np.array([hr[nr.index(nm)] for nm in common])
    d = a - b
    V = len(d)
    out = {"views": V, "rms_simple_px": float(np.sqrt(a.mean())), "rms_rich_px": float(np.sqrt(b.mean()))}
    sd = float(d.std(ddof=1)) if V > 1 else 0.0
    if V < 3 or not sd > 0:
        return {**out, "t": 0.0, "p": 1.0}
    t = float(d.mean() / (sd / math.sqrt(V)))
    return {**out, "t": t, "p": student_t_sf(t, V - 1)}
