"""Levenberg-Marquardt least squares on numpy: minimises ``sum(fun(x)**2)``, x (P,), residuals (M,), M >= P, in Moré's
(1978) trust-region form of MINPACK's ``lmder``/``lmdif`` (Willson's Tsai code): it stops where ``lmdif`` stops."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from selfview.errors import CalibrationError

__all__ = ["LMResult", "covariance", "levenberg_marquardt", "numeric_jacobian", "wald_chi2"]

Residuals = Callable[[np.ndarray], np.ndarray]
Jacobian = Callable[[np.ndarray], np.ndarray]

_EPS = np.finfo(float).eps
_DWARF = np.finfo(float).tiny
#: Smallest singular value, relative to the largest, that the normal equations resolve.
_NORMAL_FLOOR = 1e-7


@dataclass(frozen=True)
class LMResult:
    """Outcome of ``levenberg_marquardt``: ``x`` (P,); ``residuals`` (M,), ``jacobian`` (M, P) at x; ``cost`` sum of
    squares; ``iterations``, ``nfev`` Jacobian, residual calls; ``converged`` (False: out of budget); ``message``."""

    x: np.ndarray
    residuals: np.ndarray
    jacobian: np.ndarray
    cost: float
    iterations: int
    nfev: int
    converged: bool
    message: str

    def covariance(self, sigma2: float | None = None, *, normal: bool = False) -> np.ndarray:
        """(P, P) covariance of ``x`` (``covariance``), by default with residual variance ``cost / (M - P)``."""
        m, p = self.jacobian.shape
        return covariance(self.jacobian, self.cost / max(m - p, 1) if sigma2 is None else sigma2, normal=normal)


def _r_factor(A) -> np.ndarray:
    """R of A = Q R: a tall matrix's SVD is its R's, far cheaper than an SVD of thousands of rows."""
    return np.linalg.qr(A, mode="r")


def _normal_matrix(J, d, normal) -> np.ndarray:
    """``D^-1 J^T J D^-1``, column scales ``d``; a callable ``normal(J)`` gives the problem's own (sparse) J^T J."""
    if callable(normal):
        return np.asarray(normal(J), dtype=float) / np.outer(d, d)
    Js = J / d
    return Js.T @ Js


def covariance(J, sigma2: float, *, normal=False) -> np.ndarray:
    """(P, P) covariance ``sigma2 (J^T J)^-1``, ``J`` (M, P), by the SVD of the scaled J (inverting J^T J squares its
    condition) or J^T J if ``normal`` (as ``levenberg_marquardt``); all inf if a direction is undetermined."""
    J = np.asarray(J, dtype=float)
    m, p = J.shape
    cn = np.linalg.norm(J, axis=0)
    cn = np.where(cn > 0, cn, 1.0)
    if normal:
        A = _normal_matrix(J, cn, normal)
        w = np.linalg.eigvalsh(A)
        if not (np.all(np.isfinite(w)) and w[0] > _NORMAL_FLOOR**2 * w[-1]):
            return np.full((p, p), np.inf)
        return sigma2 * np.linalg.inv(A) / np.outer(cn, cn)
    _, s, Vt = np.linalg.svd(_r_factor(J / cn), full_matrices=False)
    if not (np.all(np.isfinite(s)) and s[-1] > _EPS * max(m, p) * s[0]):
        return np.full((p, p), np.inf)
    return sigma2 * ((Vt.T / (s * s)) @ Vt) / np.outer(cn, cn)


def wald_chi2(value, cov) -> float:
    """value^T cov^-1 value: the chi-square of ``value`` against 0 (inf when ``cov`` is singular)."""
    value = np.asarray(value, float)
    try:
        return float(value @ np.linalg.solve(np.asarray(cov, float), value))
    except np.linalg.LinAlgError:
        return math.inf


def numeric_jacobian(fun: Residuals, x, *, r0=None, method: str = "central", scale=None,
                     rel_step: float | None = None) -> np.ndarray:
    """(M, P) Jacobian of ``fun`` at ``x`` (P,): ``central`` differences (relative step eps^(1/3)) or ``forward``
    (sqrt(eps), MINPACK's ``fdjac2``; ``r0`` = fun(x) saves a call); step j ``rel_step * |x_j|``, or ``* scale_j``
    (default 1) where x_j = 0. ValueError for an unknown method, CalibrationError for non-finite residuals."""
    x = np.asarray(x, dtype=float).ravel()
    p = x.size
    if method not in ("central", "forward"):
        raise ValueError(f"numeric_jacobian: method must be 'central' or 'forward', got {method!r}")
    sc = np.ones(p) if scale is None else np.broadcast_to(np.abs(np.asarray(scale, dtype=float)), (p,))
    if rel_step is None:
        rel_step = _EPS ** (1.0 / 3.0) if method == "central" else np.sqrt(_EPS)
    h = rel_step * np.where(x != 0, np.abs(x), sc)

    def moved(j: int, step: float) -> np.ndarray:
        xj = x.copy()
        xj[j] += step
        return np.asarray(fun(xj), dtype=float).ravel()

    if method == "forward":
        f0 = np.asarray(fun(x) if r0 is None else r0, dtype=float).ravel()
        J = np.column_stack([(moved(j, h[j]) - f0) / h[j] for j in range(p)])
    else:
        J = np.column_stack([(moved(j, h[j]) - moved(j, -h[j])) / (2.0 * h[j]) for j in range(p)])
    if not np.all(np.isfinite(J)):
        raise CalibrationError("numeric Jacobian: the residual function is not finite near the current parameters")
    return J


class _ScaledSVD:
    """``J D^-1 = U S V^T`` and ``c = U^T r``, so each damping trial of Moré's iteration costs O(P): ``z(par)`` the
    scaled step D x in basis V minimising ``||J x - r||^2 + par ||D x||^2``, ``step(zv)`` x (P,), ``gradient_norm()``
    ||(J D^-1)^T r||, ``jnorm(zv)`` ||J x||, ``newton_norm2(zv, par)`` ||y||^2 of y = S_par^-T D^2 x / ||D x||."""

    def __init__(self, J, r, d):
        p = J.shape[1]
        R = _r_factor(np.column_stack([J / d, r]))  # J D^-1 = Q R[:, :P], R[:, P] = Q^T r
        U, s, Vt = np.linalg.svd(R[:p, :p])
        self.c = U.T @ R[:p, p]
        self.s, self.Vt, self.d = s, Vt, d
        # MINPACK tests R's diagonal for an exact zero; a relative floor does it here
        self.rank_ok = s > _EPS * max(J.shape) * (s[0] if s.size else 0.0)
        self.full_rank = bool(np.all(self.rank_ok))

    def gradient_norm(self):
        return float(np.linalg.norm(self.s * self.c))

    def jnorm(self, zv):
        return float(np.linalg.norm(self.s * zv))

    def z(self, par):
        s = self.s
        if par == 0:
            return np.where(self.rank_ok, self.c / np.where(self.rank_ok, s, 1.0), 0.0)
        return s * self.c / (s * s + par)

    def newton_norm2(self, zv, par):
        s2 = self.s * self.s + par
        return float(np.sum(zv * zv / np.where(s2 > 0, s2, np.inf))) / float(zv @ zv)

    def step(self, zv):
        return (self.Vt.T @ zv) / self.d


class _ScaledNormal:
    """``_ScaledSVD``'s quantities from ``A = D^-1 J^T J D^-1`` (V = I), cheaper for thousands of residuals;
    ``LinAlgError`` if A is not positive definite to ``_NORMAL_FLOOR`` (the caller then takes the SVD)."""

    def __init__(self, J, r, d, normal=True):
        self.A, self.g, self.d = _normal_matrix(J, d, normal), (J.T @ r) / d, d
        L = np.linalg.cholesky(self.A)
        if not np.min(np.diag(L)) ** 2 > _NORMAL_FLOOR**2 * np.max(np.diag(self.A)):
            raise np.linalg.LinAlgError("normal equations: not positive definite")
        self.full_rank = True

    def _solve(self, par, b):
        # two solves per damping cost far less than an inverse
        return np.linalg.solve(self.A + par * np.eye(len(self.A)), b)

    def z(self, par):
        return self._solve(par, self.g)

    def newton_norm2(self, zv, par):
        return float(zv @ self._solve(par, zv)) / float(zv @ zv)

    def step(self, zv):
        return zv / self.d

    def gradient_norm(self):
        return float(np.linalg.norm(self.g))

    def jnorm(self, zv):
        return float(np.sqrt(max(zv @ self.A @ zv, 0.0)))


def _factor(J, r, d, normal):
    """The factorisation of an iteration: the normal equations' when asked and positive definite, else the SVD."""
    try:
        return _ScaledNormal(J, r, d, normal) if normal else _ScaledSVD(J, r, d)
    except np.linalg.LinAlgError:
        return _ScaledSVD(J, r, d)


def _lm_parameter(svd, delta, par):
    """(damping, scaled step in basis V) with ||D x|| within 10 % of ``delta``: MINPACK's ``lmpar``."""
    zv = svd.z(0.0)
    dxnorm = float(np.linalg.norm(zv))
    fp = dxnorm - delta
    if fp <= 0.1 * delta:
        return 0.0, zv
    parl = fp / delta / svd.newton_norm2(zv, 0.0) if svd.full_rank else 0.0
    gnorm = svd.gradient_norm()
    paru = gnorm / delta
    if paru == 0:
        paru = _DWARF / min(delta, 0.1)
    par = min(max(par, parl), paru)
    if par == 0:
        par = gnorm / dxnorm
    for it in range(1, 11):
        if par == 0:
            par = max(_DWARF, 1e-3 * paru)
        zv = svd.z(par)
        dxnorm = float(np.linalg.norm(zv))
        prev, fp = fp, dxnorm - delta
        if abs(fp) <= 0.1 * delta or (parl == 0 and fp <= prev and prev < 0) or it == 10:
            break
        parc = fp / delta / svd.newton_norm2(zv, par)
        if fp > 0:
            parl = max(parl, par)
        elif fp < 0:
            paru = min(paru, par)
        par = max(parl, par + parc)
    return par, zv


def _start(fun: Residuals, x0) -> tuple[np.ndarray, np.ndarray]:
    """(x (P,), residuals (M,) at x) checked: P > 0, M >= P, the residuals finite."""
    x = np.array(x0, dtype=float).ravel()
    if x.size == 0:
        raise ValueError("levenberg_marquardt: no parameters")
    r = np.asarray(fun(x), dtype=float).ravel()
    if r.size < x.size:
        raise ValueError(f"levenberg_marquardt: {r.size} residuals cannot determine {x.size} parameters")
    if not np.all(np.isfinite(r)):
        raise CalibrationError("least squares: the residuals are not finite at the start point")
    return x, r


def _jacobian_function(fun: Residuals, jac, m: int, n: int, scale):
    """(jacobian(x, r) -> checked (M, P), residual calls per use) for ``jac``: a callable, 'central' or 'forward'."""
    numeric = isinstance(jac, str)
    if numeric and jac not in ("central", "forward"):
        raise ValueError(f"levenberg_marquardt: jac must be a callable, 'central' or 'forward', got {jac!r}")

    def jacobian(xv, r):
        if numeric:
            J = numeric_jacobian(fun, xv, r0=r if jac == "forward" else None, method=jac, scale=scale)
        else:
            J = np.asarray(jac(xv), dtype=float)
        if J.shape != (m, n):
            raise ValueError(f"levenberg_marquardt: Jacobian of shape {J.shape}, expected {(m, n)}")
        return J

    return jacobian, ({"central": 2 * n, "forward": n}[jac] if numeric else 0)


def _stop_test(actred, prered, ratio, delta, xnorm, gnorm, ftol, xtol, out_of_budget: bool):
    """MINPACK's tests after a trial step, in its order: (converged, message or None for the budget's) or None."""
    small_f = abs(actred) <= ftol and prered <= ftol and ratio <= 2.0
    small_x = delta <= xtol * xnorm
    if small_f or small_x:
        return True, " and ".join(m for m, hit in (("relative cost reduction at most ftol", small_f),
                                                   ("relative step bound at most xtol", small_x)) if hit)
    if out_of_budget:
        return False, None
    if (abs(actred) <= _EPS and prered <= _EPS and ratio <= 2.0) or delta <= _EPS * xnorm or gnorm <= _EPS:
        return True, "no further reduction possible at machine precision"
    return None


def _new_bound(ratio, actred, dirder, fnorm, fnorm1, delta, pnorm, par):
    """MINPACK's update of the step bound and the damping from the ratio of actual to predicted reduction."""
    if ratio <= 0.25:
        temp = 0.5 if actred >= 0 else 0.5 * dirder / (dirder + 0.5 * actred)
        if 0.1 * fnorm1 >= fnorm or temp < 0.1:
            temp = 0.1
        return temp * min(delta, pnorm / 0.1), par / temp
    if par == 0 or ratio >= 0.75:
        return pnorm / 0.5, 0.5 * par
    return delta, par


def levenberg_marquardt(fun: Residuals, x0, jac: Jacobian | str | None = None, *, ftol: float = 1e-12,
                        xtol: float = 1e-12, gtol: float = 0.0, max_nfev: int | None = None, factor: float = 100.0,
                        scale=None, normal=False) -> LMResult:
    """Minimise ``sum(fun(x)**2)`` from ``x0`` (P,); ``jac(x)`` the (M, P) Jacobian or None/'central'/'forward';
    first step bound ``factor * ||D x0||``; ``normal`` (True, or a function of J giving J^T J): factor J^T J, not J.
    A trial step with non-finite residuals (a point behind the camera) is rejected. ValueError for M < P or a
    Jacobian of the wrong shape, CalibrationError for non-finite residuals at ``x0``."""
    x, r = _start(fun, x0)
    m, n = r.size, x.size
    max_nfev = 200 * (n + 1) if max_nfev is None else int(max_nfev)
    jacobian, extra = _jacobian_function(fun, "central" if jac is None else jac, m, n, scale)
    nfev, iterations, par, fnorm = 1, 0, 0.0, float(np.linalg.norm(r))
    converged, message = False, f"gave up after {max_nfev} residual evaluations"
    done = False
    while not done:
        J = jacobian(x, r)
        nfev += extra
        J_at_x = True
        iterations += 1
        acnorm = np.linalg.norm(J, axis=0)
        if iterations == 1:
            d = np.where(acnorm > 0, acnorm, 1.0)
            xnorm = float(np.linalg.norm(d * x))
            delta = factor * xnorm if xnorm > 0 else factor
        nz = acnorm > 0  # MINPACK's gtol measure: the largest cosine between the residuals and a Jacobian column
        gnorm = 0.0 if fnorm <= 0 else float(np.max(np.abs((J.T @ r)[nz] / (fnorm * acnorm[nz])), initial=0.0))
        if gnorm <= gtol:
            converged, message = True, "residuals orthogonal to the Jacobian (gtol)"
            break
        d = np.maximum(d, acnorm)
        svd = _factor(J, r, d, normal)
        while True:
            par, zv = _lm_parameter(svd, delta, par)
            x_new = x - svd.step(zv)
            pnorm = float(np.linalg.norm(zv))
            if iterations == 1:
                delta = min(delta, pnorm)
            r_new = np.asarray(fun(x_new), dtype=float).ravel()
            nfev += 1
            fnorm1 = float(np.linalg.norm(r_new)) if np.all(np.isfinite(r_new)) else np.inf
            actred = 1.0 - (fnorm1 / fnorm) ** 2 if 0.1 * fnorm1 < fnorm else -1.0
            t1, t2 = svd.jnorm(zv) / fnorm, np.sqrt(par) * pnorm / fnorm
            prered, dirder = t1 * t1 + 2.0 * t2 * t2, -(t1 * t1 + t2 * t2)
            ratio = actred / prered if prered != 0 else 0.0
            delta, par = _new_bound(ratio, actred, dirder, fnorm, fnorm1, delta, pnorm, par)
            if ratio >= 1e-4:
                x, r, fnorm = x_new, r_new, fnorm1
                xnorm = float(np.linalg.norm(d * x))
                J_at_x = False
            stop = _stop_test(actred, prered, ratio, delta, xnorm, gnorm, ftol, xtol, nfev >= max_nfev)
            if stop is not None:
                converged, message, done = stop[0], stop[1] or message, True
                break
            if ratio >= 1e-4:
                break
    if not J_at_x:
        J = jacobian(x, r)
        nfev += extra
    return LMResult(x=x, residuals=r, jacobian=J, cost=fnorm * fnorm, iterations=iterations, nfev=nfev,
                    converged=converged, message=message)
