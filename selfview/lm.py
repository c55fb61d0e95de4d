"""A small Levenberg-Marquardt least-squares solver on numpy.

Minimises ``sum(fun(x)**2)`` over ``x`` (P,) for a residual function returning (M,) with M >= P, using
an analytic Jacobian when one is given and central differences otherwise. Marquardt's scaling (the
largest column norms of the Jacobian seen so far, as MINPACK's ``lmdif`` does) makes the damping
invariant to the parameters' units, so f [px], kappa [px^-2] and translations [mm] can share one
vector. One SVD per Jacobian serves every damping trial of that iteration.

A residual function may return non-finite values for a parameter vector it cannot evaluate (a point
behind the camera, beyond the lens's fold): such a trial step is rejected like one that raises the cost.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from selfview.errors import CalibrationError

__all__ = ["LMResult", "levenberg_marquardt", "numeric_jacobian"]

Residuals = Callable[[np.ndarray], np.ndarray]
Jacobian = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class LMResult:
    """Outcome of ``levenberg_marquardt``.

    ``x`` (P,) solution; ``residuals`` (M,) and ``jacobian`` (M, P) at ``x``; ``cost`` the sum of
    squared residuals; ``iterations`` Jacobian evaluations; ``nfev`` residual evaluations;
    ``converged`` whether a tolerance was met (False: ``max_iter`` ran out); ``message`` which one.
    """

    x: np.ndarray
    residuals: np.ndarray
    jacobian: np.ndarray
    cost: float
    iterations: int
    nfev: int
    converged: bool
    message: str

    def covariance(self, sigma2: float | None = None) -> np.ndarray:
        """(P, P) covariance of ``x``: ``sigma2 (J^T J)^-1``, by default with the residual variance
        ``cost / (M - P)``. A pseudo-inverse keeps it finite when a parameter is undetermined."""
        J = self.jacobian
        m, p = J.shape
        if sigma2 is None:
            sigma2 = self.cost / max(m - p, 1)
        return sigma2 * np.linalg.pinv(J.T @ J)


def numeric_jacobian(fun: Residuals, x, r0=None, scale=None, rel_step: float | None = None) -> np.ndarray:
    """(M, P) Jacobian of ``fun`` at ``x`` (P,) by central differences.

    Each step is ``rel_step * max(|x_j|, scale_j)`` (``scale`` (P,) the typical size of each parameter,
    default 1; ``rel_step`` default eps^(1/3)). ``r0`` is accepted for symmetry with forward schemes
    and only fixes M. Raises ``CalibrationError`` if a residual is not finite.
    """
    x = np.asarray(x, dtype=float)
    p = x.size
    sc = np.ones(p) if scale is None else np.broadcast_to(np.asarray(scale, dtype=float), (p,))
    h_rel = np.finfo(float).eps ** (1.0 / 3.0) if rel_step is None else float(rel_step)
    h = h_rel * np.maximum(np.abs(x), np.abs(sc))
    m = np.asarray(fun(x) if r0 is None else r0).size
    J = np.empty((m, p))
    for j in range(p):
        xp = x.copy()
        xm = x.copy()
        xp[j] += h[j]
        xm[j] -= h[j]
        J[:, j] = (np.asarray(fun(xp), dtype=float) - np.asarray(fun(xm), dtype=float)) / (xp[j] - xm[j])
    if not np.all(np.isfinite(J)):
        raise CalibrationError("numeric Jacobian: the residual function is not finite near the current parameters")
    return J


def levenberg_marquardt(
    fun: Residuals,
    x0,
    jac: Jacobian | None = None,
    *,
    max_iter: int = 100,
    ftol: float = 1e-14,
    xtol: float = 1e-12,
    gtol: float = 1e-14,
    lambda0: float = 1e-3,
    scale=None,
) -> LMResult:
    """Minimise ``sum(fun(x)**2)`` from ``x0`` (P,) by Levenberg-Marquardt.

    ``jac(x)`` returns the (M, P) Jacobian of the residuals; without it, central differences
    (``scale`` (P,): typical parameter sizes for the difference steps). Stops when the relative cost
    reduction of an accepted step is below ``ftol``, the scaled step is below ``xtol`` relative to
    the scaled parameters, the scaled gradient's cosine with the residual is below ``gtol``, no step
    can reduce the cost any more (a minimum to machine precision), or after ``max_iter`` Jacobians
    (``converged`` False). Raises ``ValueError`` for M < P or a bad shape and ``CalibrationError`` when
    the residuals are not finite at ``x0``.
    """
    x = np.array(x0, dtype=float).ravel()
    p = x.size
    if p == 0:
        raise ValueError("levenberg_marquardt: no parameters")
    r = np.asarray(fun(x), dtype=float).ravel()
    nfev = 1
    if r.size < p:
        raise ValueError(f"levenberg_marquardt: {r.size} residuals cannot determine {p} parameters")
    if not np.all(np.isfinite(r)):
        raise CalibrationError("least squares: the residuals are not finite at the start point")
    cost = float(r @ r)

    def jacobian(xv, rv):
        if jac is None:
            return numeric_jacobian(fun, xv, rv, scale)
        J = np.asarray(jac(xv), dtype=float)
        if J.shape != (r.size, p):
            raise ValueError(f"levenberg_marquardt: Jacobian of shape {J.shape}, expected {(r.size, p)}")
        return J

    D = np.zeros(p)
    lam = float(lambda0)
    nu = 2.0
    converged, message = False, f"no convergence in {max_iter} iterations"
    J = jacobian(x, r)
    it = 1
    while True:
        # Marquardt scaling: never shrink, so the trust region cannot collapse on a vanishing column.
        cn = np.linalg.norm(J, axis=0)
        D = np.maximum(D, np.where(cn > 0, cn, 1.0))
        Js = J / D
        g = Js.T @ r
        if cost == 0.0 or np.max(np.abs(g)) <= gtol * np.sqrt(cost) * np.max(np.linalg.norm(Js, axis=0)):
            converged, message = True, "gradient orthogonal to the residuals (gtol)"
            break
        U, s, Vt = np.linalg.svd(Js, full_matrices=False)
        Utr = U.T @ r
        accepted = False
        while not accepted:
            # Damped step in scaled units: (Js^T Js + lam I) dz = -Js^T r, through the SVD of Js.
            dz = -(Vt.T @ (s / (s * s + lam) * Utr))
            step = dz / D
            x_new = x + step
            r_new = np.asarray(fun(x_new), dtype=float).ravel()
            nfev += 1
            cost_new = float(r_new @ r_new) if np.all(np.isfinite(r_new)) else np.inf
            # Predicted reduction of the linear model, the gain ratio rho decides the damping.
            Jdz = Js @ dz
            predicted = -(2.0 * float(Jdz @ r) + float(Jdz @ Jdz))
            if cost_new < cost:
                rho = (cost - cost_new) / predicted if predicted > 0 else 0.0
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
                accepted = True
                small_f = (cost - cost_new) <= ftol * cost
                small_x = np.linalg.norm(dz) <= xtol * (np.linalg.norm(D * x) + xtol)
                x, r, cost = x_new, r_new, cost_new
                if small_f or small_x:
                    converged = True
                    message = "relative cost reduction below ftol" if small_f else "relative step below xtol"
            else:
                lam *= nu
                nu *= 2.0
                if lam > 1e16 or np.linalg.norm(dz) <= np.finfo(float).eps * (np.linalg.norm(D * x) + 1e-300):
                    converged, message = True, "no step reduces the cost further (minimum to machine precision)"
                    break
        if converged or it >= max_iter:
            if accepted:
                J = jacobian(x, r)
            break
        J = jacobian(x, r)
        it += 1
    return LMResult(
        x=x, residuals=r, jacobian=J, cost=cost, iterations=it, nfev=nfev, converged=converged, message=message
    )
