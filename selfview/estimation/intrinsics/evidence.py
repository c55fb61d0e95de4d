"""Evidence for a richer model without refits: the held-out check (each view left out in turn, to first order) as a
one-sided sign test over the views, and a chi-square test of parameters against 0."""

from __future__ import annotations

import math

import numpy as np

from selfview.estimation.intrinsics.fit import JointFit, leave_views_out


def sign_test_p(better: int, worse: int) -> float:
    """One-sided p-value of the sign test: P(``better`` or more successes in ``better + worse`` fair tosses)."""
    n = better + worse
    return sum(math.comb(n, k) for k in range(better, n + 1)) / 2.0**n if n else 1.0


def chi2_3_sf(x: float) -> float:
    """P(X > x) of a chi-square with 3 degrees of freedom."""
    x = max(float(x), 0.0)
    return math.erfc(math.sqrt(x / 2)) + math.sqrt(2 * x / math.pi) * math.exp(-x / 2)


def heldout_test(simple: JointFit, rich: JointFit) -> dict:
    """Does ``rich`` predict each view left out (by name) better than ``simple``? ``p`` the sign test's p-value (no
    model of the errors' distribution; one odd view weighs as one). {views, better, p, rms_simple_px, rms_rich_px}."""
    hs, hr = leave_views_out(simple)[1], leave_views_out(rich)[1]
    ns, nr = [v.name for v in simple.views], [v.name for v in rich.views]
    common = [nm for nm in nr if nm in ns]
    a = np.array([hs[ns.index(nm)] for nm in common])
    b = np.array([hr[nr.index(nm)] for nm in common])
    better, worse = int(np.sum(b < a)), int(np.sum(b > a))
    return {"views": len(common), "better": better, "p": sign_test_p(better, worse),
            "rms_simple_px": float(np.sqrt(a.mean())), "rms_rich_px": float(np.sqrt(b.mean()))}
