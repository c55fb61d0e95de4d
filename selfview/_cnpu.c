/* selfview._cnpu: the hot paths of the on-line solves: the paper's differential update (NP-U,
 * ``online.differential_update``) and the Gauss-Newton of NP-I and NP-R (``online._gauss_newton``).
 *
 * One function, np_u(), computes for the common case what the Python code of selfview/online.py
 * computes, in the same order of floating-point operations: eq. 4 (``_undistort``), eq. 15
 * (``_camera_points``), the rows of eq. 17 divided by z (``_eq17``), the normal system, its Cholesky
 * inverse as OpenCV's ``cv2.invert(N, flags=cv2.DECOMP_CHOLESKY)`` computes it (``hal::Cholesky``, the
 * identity as right-hand side) with the trace bound of ``_checked_inverse``, the least-squares solution
 * x = N^-1 A^T b, ``C'_H_G = Delta* C_H_G`` (eq. 13), eq. 16 and the distorted-pixel residuals by the
 * Newton inversion of ``_pixel_residuals``, and delta and d of eq. 14 (``_estimate``).
 *
 * It hands every other case back (returns None) to the Python code, which raises the errors: input
 * that is not C-contiguous float64 of the expected shapes, camera parameters that are not Python
 * numbers, non-finite numbers anywhere (input, intermediate or result), fewer than 3 points, a point
 * behind the camera before or after the update, a non-positive diagonal of the normal matrix, a
 * Cholesky pivot below DBL_EPSILON, a trace bound that does not settle the conditioning, a Newton
 * inversion that does not converge. Where the Python code uses numpy's BLAS (the normal matrix, the
 * products N^-1 (A^T b) and Delta* C_H_G) the sums here run in index order, and where it uses
 * math.hypot this uses the C library's hypot: the results may differ from the Python code's in the
 * last bits (the solution by up to the rounding of the normal equations, which both commit).
 *
 * A second function, np_i(), is the Gauss-Newton on SE(3) of NP-I and of NP-R's refinement
 * (``online._gauss_newton``), step for step: the linearisation (``_linearise``), the damping rule, the
 * Cholesky solve of cv2.solve(..., DECOMP_CHOLESKY), the stopping rule (``_largest_move``), the
 * update (``_perturbed``), the conditioning bound at the first and the last linearisation, the
 * residuals, and the motion from the prior as cv2.Rodrigues gives it. The start's nearest rotation
 * and cv2.Rodrigues's are computed by the polar iteration rather than an SVD (the same matrix to the
 * rounding). It hands back the same kinds of case, and also no convergence, a singular step, a prior
 * whose last row is not (0, 0, 0, 1) or that reflects, and a motion near a half turn.
 *
 * CPython C API only (no numpy headers): the arrays are read through the buffer protocol.
 */

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <float.h>
#include <math.h>
#include <string.h>

/* IEEE semantics as in Python: no contraction of a * b + c into a fused multiply-add (GCC contracts by
 * default outside the ISO C modes, on targets that have one). */
#if defined(__clang__)
#pragma STDC FP_CONTRACT OFF
#elif defined(__GNUC__)
#pragma GCC optimize("fp-contract=off")
#elif defined(_MSC_VER)
#pragma fp_contract(off)
#endif

/* The points a call may take: far beyond any use, small enough that no size below overflows. */
#define MAX_POINTS ((Py_ssize_t)1 << 20)
/* Points whose scratch (7 doubles each) lives on the stack. */
#define STACK_POINTS 16

static PyObject *str_f, *str_kappa, *str_cx, *str_cy, *str_aspect;

/* --- arguments ---------------------------------------------------------------------------------- */

/* One camera parameter as a double: 1; 0 if it is not a float or an int, is not finite, or reading
 * it raised an Exception (the Python code decides, and raises that where it reads it); -1 with an
 * exception set for a BaseException that is no Exception (KeyboardInterrupt, SystemExit). */
static int
camera_value(PyObject *camera, PyObject *name, double *out)
{
    PyObject *v = PyObject_GetAttr(camera, name);
    if (v == NULL) {
        if (PyErr_ExceptionMatches(PyExc_Exception)) {
            PyErr_Clear();
            return 0;
        }
        return -1;
    }
    int ok = 0;
    if (PyFloat_Check(v)) {
        *out = PyFloat_AS_DOUBLE(v);
        ok = 1;
    }
    else if (PyLong_CheckExact(v)) {
        *out = PyLong_AsDouble(v);
        if (*out == -1.0 && PyErr_Occurred()) {
            if (!PyErr_ExceptionMatches(PyExc_OverflowError)) {
                Py_DECREF(v);
                return -1;
            }
            PyErr_Clear();
        }
        else {
            ok = 1;
        }
    }
    Py_DECREF(v);
    return ok && isfinite(*out);
}

/* Whether the exception set is an exporter's refusal of the buffer asked for (no buffer protocol:
 * TypeError; not C-contiguous, not writable: numpy raises ValueError, others BufferError). */
static int
buffer_refused(void)
{
    return PyErr_ExceptionMatches(PyExc_BufferError) || PyErr_ExceptionMatches(PyExc_TypeError) ||
           PyErr_ExceptionMatches(PyExc_ValueError);
}

/* An input array: a C-contiguous buffer of doubles (format "d") of shape (rows, cols), rows < 0 for
 * any. 1: view holds it; 0: not such a buffer (view released, nothing set); -1: an exception. */
static int
get_input(PyObject *obj, Py_buffer *view, Py_ssize_t rows, Py_ssize_t cols)
{
    if (PyObject_GetBuffer(obj, view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) {
        if (buffer_refused()) {
            PyErr_Clear();
            return 0;
        }
        return -1;
    }
    if (view->ndim != 2 || view->shape == NULL || view->itemsize != (Py_ssize_t)sizeof(double) ||
        view->format == NULL || strcmp(view->format, "d") != 0 || (rows >= 0 && view->shape[0] != rows) ||
        view->shape[1] != cols || view->shape[0] < 0 || view->shape[0] > MAX_POINTS ||
        view->len != view->shape[0] * cols * (Py_ssize_t)sizeof(double)) {
        PyBuffer_Release(view);
        return 0;
    }
    return 1;
}

/* An output array: a writable C-contiguous buffer of `size` doubles (format "d"). 0: view holds it;
 * -1: an exception (TypeError, ValueError: the caller's mistake, not a case for the Python code). */
static int
get_output(PyObject *obj, Py_buffer *view, Py_ssize_t size, const char *what)
{
    if (PyObject_GetBuffer(obj, view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_WRITABLE) < 0) {
        if (buffer_refused()) {
            PyErr_Clear();
            PyErr_Format(PyExc_TypeError, "np_u: %s must be a writable C-contiguous float64 array, got %.200s",
                         what, Py_TYPE(obj)->tp_name);
        }
        return -1;
    }
    if (view->itemsize != (Py_ssize_t)sizeof(double) || view->format == NULL || strcmp(view->format, "d") != 0) {
        PyBuffer_Release(view);
        PyErr_Format(PyExc_TypeError, "np_u: %s must be a float64 array", what);
        return -1;
    }
    if (view->len != size * (Py_ssize_t)sizeof(double)) {
        PyBuffer_Release(view);
        PyErr_Format(PyExc_ValueError, "np_u: %s must hold %zd numbers, got %zd", what, size,
                     view->len / (Py_ssize_t)sizeof(double));
        return -1;
    }
    return 0;
}

/* --- the numerics -------------------------------------------------------------------------------- */

static int
all_finite(const double *v, Py_ssize_t n)
{
    for (Py_ssize_t i = 0; i < n; i++) {
        if (!isfinite(v[i])) {
            return 0;
        }
    }
    return 1;
}

/* OpenCV's hal::Cholesky (CholImpl) of the 6x6 A with the right-hand side B (6 x m, row-major),
 * solved in place, i.e. cv2.solve(A, B, flags=cv2.DECOMP_CHOLESKY): 1, or 0 where it reports failure. */
static int
cholesky_solve6(const double A[36], double *B, int m)
{
    double L[36];
    double s;
    int i, j, k;
    memcpy(L, A, sizeof L);
    for (i = 0; i < 6; i++) {
        for (j = 0; j < i; j++) {
            s = L[i * 6 + j];
            for (k = 0; k < j; k++) {
                s -= L[i * 6 + k] * L[j * 6 + k];
            }
            L[i * 6 + j] = s * L[j * 6 + j];
        }
        s = L[i * 6 + i];
        for (k = 0; k < i; k++) {
            double t = L[i * 6 + k];
            s -= t * t;
        }
        if (s < DBL_EPSILON) {
            return 0;
        }
        L[i * 6 + i] = 1. / sqrt(s);
    }
    for (i = 0; i < 6; i++) { /* L y = b */
        for (j = 0; j < m; j++) {
            s = B[i * m + j];
            for (k = 0; k < i; k++) {
                s -= L[i * 6 + k] * B[k * m + j];
            }
            B[i * m + j] = s * L[i * 6 + i];
        }
    }
    for (i = 5; i >= 0; i--) { /* L^T x = y */
        for (j = 0; j < m; j++) {
            s = B[i * m + j];
            for (k = 5; k > i; k--) {
                s -= L[k * 6 + i] * B[k * m + j];
            }
            B[i * m + j] = s * L[i * 6 + i];
        }
    }
    return 1;
}

/* cv2.invert(A, flags=cv2.DECOMP_CHOLESKY) of the 6x6 A (CholImpl with the identity as right-hand
 * side): B = A^-1 and 1, or 0 where it reports failure. */
static int
cholesky_inverse6(const double A[36], double B[36])
{
    for (int i = 0; i < 36; i++) {
        B[i] = (i % 7 == 0) ? 1.0 : 0.0;
    }
    return cholesky_solve6(A, B, 6);
}

/* sum(map(mul, diag(N), diag(N^-1))) as Python's built-in sum adds floats: in order from the first
 * term, compensated (Neumaier) from Python 3.12 on. */
static double
trace_product(const double N[36], const double Ninv[36])
{
    double total = N[0] * Ninv[0];
#if PY_VERSION_HEX >= 0x030C0000
    double c = 0.0;
    for (int i = 1; i < 6; i++) {
        double x = N[i * 7] * Ninv[i * 7];
        double t = total + x;
        if (fabs(total) >= fabs(x)) {
            c += (total - t) + x;
        }
        else {
            c += (x - t) + total;
        }
        total = t;
    }
    if (c != 0.0 && isfinite(c)) {
        total += c;
    }
#else
    for (int i = 1; i < 6; i++) {
        total += N[i * 7] * Ninv[i * 7];
    }
#endif
    return total;
}

/* One point of _pixel_residuals: the observed distorted sensor point obs = (X^, Y^, ...) minus the
 * distorted image of the predicted undistorted point (X, Y), in pixels: out = (du, dv). Inverts eq. 4
 * by three Newton steps from the observed radius; 0 where they do not reach it (the Python code then
 * falls back to the closed form of selfview.camera.distort). */
static int
pixel_residual(double k, double a, const double *obs, double X, double Y, double out[2])
{
    const double k3 = 3.0 * k;
    double Xh = obs[0], Yh = obs[1];
    double R = hypot(X, Y);
    double r = hypot(Xh, Yh);
    for (int step = 0; step < 3; step++) {
        double slope = k3 * r * r + 1.0;
        if (slope <= 0.0) {
            break;
        }
        r -= (k * r * r * r + r - R) / slope;
    }
    if (!(k3 * r * r + 1.0 > 0.0 && fabs(k * r * r * r + r - R) <= 1e-9 * (1.0 + R))) {
        return 0;
    }
    double s = R > 0.0 ? r / R : 1.0;
    double Xp = X * s, Yp = Y * s;
    out[0] = (Xh - Xp) / a;
    out[1] = Yh - Yp;
    return 1;
}

/* The solve, on validated buffers: H0 (16), P (3n), uv (2n), cam (f, kappa, cx, cy, aspect), n >= 3.
 * work: 7n doubles of scratch; Ab (14n): [A | b] of eq. 17; res (2n): the residuals (du, dv).
 * Out: H (16), x (6), scalars (rms, delta_deg, d_mm). 1: done; 0: a case for the Python code. */
static int
solve(const double *H0, const double *P, const double *uv, Py_ssize_t n, const double cam[5],
      double max_condition, double *work, double *Ab, double *res, double H[16], double x[6], double scalars[3])
{
    const double f = cam[0], k = cam[1], cx = cam[2], cy = cam[3], a = cam[4];
    double *obs = work;          /* (X^, Y^, X, Y) per point */
    double *pc = work + 4 * n;   /* (x, y, z) in the camera per point */
    Py_ssize_t i, row;
    int p, q;

    /* _prepare: finite input */
    if (!all_finite(H0, 16) || !all_finite(P, 3 * n) || !all_finite(uv, 2 * n)) {
        return 0;
    }
    /* _undistort (eq. 4) */
    for (i = 0; i < n; i++) {
        double u = uv[2 * i], v = uv[2 * i + 1];
        double Xh = a * (u - cx), Yh = v - cy;
        double s = 1.0 + k * (Xh * Xh + Yh * Yh);
        obs[4 * i] = Xh;
        obs[4 * i + 1] = Yh;
        obs[4 * i + 2] = Xh * s;
        obs[4 * i + 3] = Yh * s;
    }
    /* _camera_points (eq. 15) */
    {
        const double r11 = H0[0], r12 = H0[1], r13 = H0[2], t1 = H0[3];
        const double r21 = H0[4], r22 = H0[5], r23 = H0[6], t2 = H0[7];
        const double r31 = H0[8], r32 = H0[9], r33 = H0[10], t3 = H0[11];
        for (i = 0; i < n; i++) {
            double gx = P[3 * i], gy = P[3 * i + 1], gz = P[3 * i + 2];
            double z = r31 * gx + r32 * gy + r33 * gz + t3;
            if (!(z > 0.0)) {
                return 0;
            }
            pc[3 * i] = r11 * gx + r12 * gy + r13 * gz + t1;
            pc[3 * i + 1] = r21 * gx + r22 * gy + r23 * gz + t2;
            pc[3 * i + 2] = z;
        }
    }
    /* _eq17: two rows per point, divided by z */
    for (i = 0; i < n; i++) {
        double px = pc[3 * i], py = pc[3 * i + 1], z = pc[3 * i + 2];
        double X = obs[4 * i + 2], Y = obs[4 * i + 3];
        double iz = 1.0 / z;
        double *r1 = Ab + 14 * i, *r2 = r1 + 7;
        r1[0] = -X * py * iz;
        r1[1] = (f * z + X * px) * iz;
        r1[2] = -f * py * iz;
        r1[3] = f * iz;
        r1[4] = 0.0;
        r1[5] = -X * iz;
        r1[6] = (-f * px + X * z) * iz;
        r2[0] = (-f * z - Y * py) * iz;
        r2[1] = Y * px * iz;
        r2[2] = f * px * iz;
        r2[3] = 0.0;
        r2[4] = f * iz;
        r2[5] = -Y * iz;
        r2[6] = (-f * py + Y * z) * iz;
    }
    if (!all_finite(Ab, 14 * n)) {
        return 0;
    }
    /* the normal system N = A^T A, A^T b */
    double N[36], Atb[6], Ninv[36];
    for (p = 0; p < 6; p++) {
        for (q = p; q < 7; q++) {
            double s = 0.0;
            for (row = 0; row < 2 * n; row++) {
                s += Ab[7 * row + p] * Ab[7 * row + q];
            }
            if (q < 6) {
                N[6 * p + q] = N[6 * q + p] = s;
            }
            else {
                Atb[p] = s;
            }
        }
    }
    if (!all_finite(N, 36) || !all_finite(Atb, 6)) {
        return 0;
    }
    /* _checked_inverse: positive diagonal, Cholesky, the trace bound settles the conditioning */
    for (p = 0; p < 6; p++) {
        if (!(N[7 * p] > 0.0)) {
            return 0;
        }
    }
    if (!cholesky_inverse6(N, Ninv) || !all_finite(Ninv, 36)) {
        return 0;
    }
    {
        double bound = 6.0 * trace_product(N, Ninv);
        if (!(0.0 < bound && bound <= max_condition / 100.0)) {
            return 0;
        }
    }
    /* x = N^-1 (A^T b) */
    for (p = 0; p < 6; p++) {
        double s = 0.0;
        for (q = 0; q < 6; q++) {
            s += Ninv[6 * p + q] * Atb[q];
        }
        x[p] = s;
    }
    if (!all_finite(x, 6)) {
        return 0;
    }
    const double dx = x[0], dy = x[1], dz = x[2], tx = x[3], ty = x[4], tz = x[5];
    /* eq. 13: H = Delta* H0 */
    {
        const double D[16] = {1.0, -dz, dy, tx, dz, 1.0, -dx, ty, -dy, dx, 1.0, tz, 0.0, 0.0, 0.0, 1.0};
        for (p = 0; p < 4; p++) {
            for (q = 0; q < 4; q++) {
                double s = 0.0;
                for (int m = 0; m < 4; m++) {
                    s += D[4 * p + m] * H0[4 * m + q];
                }
                H[4 * p + q] = s;
            }
        }
        if (!all_finite(H, 16)) {
            return 0;
        }
    }
    /* eq. 16 and _pixel_residuals */
    {
        double sum_sq = 0.0;
        for (i = 0; i < n; i++) {
            double px = pc[3 * i], py = pc[3 * i + 1], pz = pc[3 * i + 2];
            double xn = px - dz * py + dy * pz + tx;
            double yn = dz * px + py - dx * pz + ty;
            double zn = -dy * px + dx * py + pz + tz;
            if (!(zn > 0.0)) {
                return 0;
            }
            if (!pixel_residual(k, a, obs + 4 * i, f * xn / zn, f * yn / zn, res + 2 * i)) {
                return 0; /* the Python code falls back to selfview.camera.distort */
            }
            sum_sq += res[2 * i] * res[2 * i] + res[2 * i + 1] * res[2 * i + 1];
        }
        if (!all_finite(res, 2 * n)) {
            return 0;
        }
        scalars[0] = sqrt(sum_sq / (double)n);
    }
    /* eq. 14, as _estimate: math.degrees(math.sqrt(m0 ** 2 + m1 ** 2 + m2 ** 2)), float ** 2 by pow */
    scalars[1] = sqrt(pow(fabs(dx), 2.0) + pow(fabs(dy), 2.0) + pow(fabs(dz), 2.0)) * (180.0 / 3.14159265358979323846);
    scalars[2] = sqrt(pow(fabs(tx), 2.0) + pow(fabs(ty), 2.0) + pow(fabs(tz), 2.0));
    return all_finite(scalars, 3);
}

/* --- NP-I: Gauss-Newton on SE(3) (online._gauss_newton) --------------------------------------------- */

/* _checked_inverse for the common case: a positive diagonal, a Cholesky inverse, and the trace bound
 * settles the conditioning (cond <= 6 trace(Ns^-1) <= max_condition / 100). 0: a case for Python. */
static int
conditioning_settled(const double N[36], double max_condition)
{
    double Ninv[36];
    for (int p = 0; p < 6; p++) {
        if (!(N[7 * p] > 0.0)) {
            return 0;
        }
    }
    if (!cholesky_inverse6(N, Ninv) || !all_finite(Ninv, 36)) {
        return 0;
    }
    double bound = 6.0 * trace_product(N, Ninv);
    return 0.0 < bound && bound <= max_condition / 100.0;
}

/* The orthogonal polar factor of the 3x3 A (row-major) by Newton's iteration Q <- (Q + Q^-T) / 2,
 * which converges quadratically to U V^T of A's SVD: what cv2.SVDecomp gives online._orthonormal and
 * cv2.Rodrigues computes first, to the rounding. 1 and Q; 0 if A is singular or reflects (det <= 0),
 * or the iteration does not settle in 30 steps (a case for the Python code). */
static int
polar3(const double A[9], double Q[9])
{
    memcpy(Q, A, 9 * sizeof(double));
    for (int it = 0; it < 30; it++) {
        const double a = Q[0], b = Q[1], c = Q[2], d = Q[3], e = Q[4], f = Q[5], g = Q[6], h = Q[7], i = Q[8];
        /* cofactors: Q^-T = cof(Q) / det(Q) */
        const double C[9] = {e * i - f * h, f * g - d * i, d * h - e * g, c * h - b * i, a * i - c * g,
                             b * g - a * h, b * f - c * e, c * d - a * f, a * e - b * d};
        const double det = a * C[0] + b * C[1] + c * C[2];
        if (!(det > 0.0) || !isfinite(det)) {
            return 0;
        }
        double change = 0.0;
        for (int k = 0; k < 9; k++) {
            double q = 0.5 * (Q[k] + C[k] / det);
            double dq = fabs(q - Q[k]);
            if (dq > change) {
                change = dq;
            }
            Q[k] = q;
        }
        if (!isfinite(change)) {
            return 0;
        }
        if (change <= 4.0 * DBL_EPSILON) {
            return 1;
        }
    }
    return 0;
}

/* cv2.Rodrigues of a 3x3 matrix M (row-major): its nearest rotation R (polar3), then OpenCV's formula
 * (theta = acos((tr R - 1) / 2), the axis from the skew part; zero below s = 1e-5, as OpenCV). 1 and
 * the rotation vector w [rad]; 0 for a rotation within about 1e-5 rad of a half turn (OpenCV's special
 * case there) or one that polar3 does not settle: a case for the Python code. */
static int
rodrigues_vector(const double M[9], double w[3])
{
    double R[9];
    if (!polar3(M, R)) {
        return 0;
    }
    double rx = R[7] - R[5], ry = R[2] - R[6], rz = R[3] - R[1];
    double s = sqrt((rx * rx + ry * ry + rz * rz) * 0.25);
    double c = (R[0] + R[4] + R[8] - 1) * 0.5;
    c = c > 1. ? 1. : c < -1. ? -1. : c;
    double theta = acos(c);
    if (s < 1e-5) {
        if (!(c > 0)) {
            return 0;
        }
        w[0] = w[1] = w[2] = 0.0;
        return 1;
    }
    double vth = 1 / (2 * s);
    vth *= theta;
    w[0] = rx * vth;
    w[1] = ry * vth;
    w[2] = rz * vth;
    return 1;
}

/* _linearise at the pose RT (3 rows of 4): the camera points pts (3n) and [J | r] (2n x 7). 0 for a
 * point behind the camera. */
static int
linearise(const double RT[12], const double *P, const double *obs, Py_ssize_t n, double f, double *pts, double *Jr)
{
    const double r11 = RT[0], r12 = RT[1], r13 = RT[2], t1 = RT[3];
    const double r21 = RT[4], r22 = RT[5], r23 = RT[6], t2 = RT[7];
    const double r31 = RT[8], r32 = RT[9], r33 = RT[10], t3 = RT[11];
    for (Py_ssize_t i = 0; i < n; i++) {
        double gx = P[3 * i], gy = P[3 * i + 1], gz = P[3 * i + 2];
        double X = obs[4 * i + 2], Y = obs[4 * i + 3];
        double x = r11 * gx + r12 * gy + r13 * gz + t1;
        double y = r21 * gx + r22 * gy + r23 * gz + t2;
        double z = r31 * gx + r32 * gy + r33 * gz + t3;
        if (!(z > 0.0)) {
            return 0;
        }
        double iz = 1.0 / z;
        double fa = f * x * iz, fc = f * y * iz, fiz = f * iz;
        double *j1 = Jr + 14 * i, *j2 = j1 + 7;
        j1[0] = -fa * y * iz;
        j1[1] = f + fa * x * iz;
        j1[2] = -fc;
        j1[3] = fiz;
        j1[4] = 0.0;
        j1[5] = -fa * iz;
        j1[6] = X - fa;
        j2[0] = -f - fc * y * iz;
        j2[1] = fc * x * iz;
        j2[2] = fa;
        j2[3] = 0.0;
        j2[4] = fiz;
        j2[5] = -fc * iz;
        j2[6] = Y - fc;
        pts[3 * i] = x;
        pts[3 * i + 1] = y;
        pts[3 * i + 2] = z;
    }
    return all_finite(Jr, 14 * n);
}

/* _perturbed: RT <- Rot(omega) RT, then v added to its translation column (omega, v = step[0:3], [3:6]). */
static void
perturb(double RT[12], const double step[6])
{
    const double w1 = step[0], w2 = step[1], w3 = step[2];
    double R[9];
    double th = sqrt(w1 * w1 + w2 * w2 + w3 * w3);
    if (th < DBL_EPSILON) {
        const double I[9] = {1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0};
        memcpy(R, I, sizeof R);
    }
    else {
        double c = cos(th), s = sin(th);
        double c1 = 1.0 - c, x = w1 / th, y = w2 / th, z = w3 / th;
        R[0] = c + c1 * (x * x);
        R[1] = c1 * (x * y) - s * z;
        R[2] = c1 * (x * z) + s * y;
        R[3] = c1 * (x * y) + s * z;
        R[4] = c + c1 * (y * y);
        R[5] = c1 * (y * z) - s * x;
        R[6] = c1 * (x * z) - s * y;
        R[7] = c1 * (y * z) + s * x;
        R[8] = c + c1 * (z * z);
    }
    double out[12];
    for (int row = 0; row < 3; row++) {
        const double a = R[3 * row], b = R[3 * row + 1], c = R[3 * row + 2];
        for (int col = 0; col < 4; col++) {
            out[4 * row + col] = a * RT[col] + b * RT[4 + col] + c * RT[8 + col];
        }
        out[4 * row + 3] += step[3 + row];
    }
    memcpy(RT, out, sizeof out);
}

/* The Gauss-Newton of online._gauss_newton on validated buffers: H0 (16, the prior; its last row
 * (0, 0, 0, 1)), Hs (16, the start: an orthonormal rotation), P (3n), uv (2n), cam, n >= 3.
 * work: 38n doubles of scratch. Out: H (16), motion (6), blob: the normal matrix N = J^T J (36) of
 * the last accepted linearisation, the distorted-pixel residuals (2n), the linearised residuals r
 * after the last step (2n); scalars (rms, delta_deg, d_mm), *iterations. 1: done; 0: a case for the
 * Python code. */
static int
gauss_newton(const double *H0, const double *Hs, const double *P, const double *uv, Py_ssize_t n,
             const double cam[5], double max_condition, double tol, long max_iter, double *work, double H[16],
             double motion[6], double *blob, double scalars[3], long *iterations)
{
    const double f = cam[0], k = cam[1], cx = cam[2], cy = cam[3], a = cam[4];
    double *obs = work;                                   /* (X^, Y^, X, Y) per point */
    double *pts[2] = {work + 4 * n, work + 7 * n};        /* the camera points of two linearisations */
    double *Jr[2] = {work + 10 * n, work + 24 * n};       /* their [J | r] */
    double RT[12], best_RT[12], M[49], best_M[49], step[6] = {0.0};
    double best_cost = 0.0, lam = 0.0, moved = INFINITY;
    int best = -1; /* which linearisation is the best so far (-1: none yet) */
    long it;
    Py_ssize_t i, row;

    if (!all_finite(H0, 16) || !all_finite(Hs, 16) || !all_finite(P, 3 * n) || !all_finite(uv, 2 * n)) {
        return 0;
    }
    for (i = 0; i < n; i++) { /* _undistort (eq. 4) */
        double Xh = a * (uv[2 * i] - cx), Yh = uv[2 * i + 1] - cy;
        double s = 1.0 + k * (Xh * Xh + Yh * Yh);
        obs[4 * i] = Xh;
        obs[4 * i + 1] = Yh;
        obs[4 * i + 2] = Xh * s;
        obs[4 * i + 3] = Yh * s;
    }
    memcpy(RT, Hs, sizeof RT);
    for (it = 1; it <= max_iter; it++) {
        const int cur = best < 0 ? 0 : 1 - best;
        if (!linearise(RT, P, obs, n, f, pts[cur], Jr[cur])) {
            return 0;
        }
        for (int p = 0; p < 7; p++) { /* M = [J | r]^T [J | r] */
            for (int q = p; q < 7; q++) {
                double s = 0.0;
                for (row = 0; row < 2 * n; row++) {
                    s += Jr[cur][7 * row + p] * Jr[cur][7 * row + q];
                }
                M[7 * p + q] = M[7 * q + p] = s;
            }
        }
        if (!all_finite(M, 49)) {
            return 0;
        }
        const double cost = M[48];
        if (best >= 0 && cost > best_cost * (1.0 + 1e-12) + 1e-30) {
            lam = fmax(10.0 * lam, 1e-6); /* the step raised the cost: back to the best, damped */
        }
        else {
            if (best < 0) {
                double N0[36];
                for (int p = 0; p < 6; p++) {
                    memcpy(N0 + 6 * p, M + 7 * p, 6 * sizeof(double));
                }
                if (!conditioning_settled(N0, max_condition)) {
                    return 0;
                }
            }
            lam = lam > 1e-9 ? 0.1 * lam : 0.0;
            best = cur;
            best_cost = cost;
            memcpy(best_RT, RT, sizeof RT);
            memcpy(best_M, M, sizeof M);
        }
        double N[36];
        for (int p = 0; p < 6; p++) {
            for (int q = 0; q < 6; q++) {
                N[6 * p + q] = best_M[7 * p + q];
            }
            if (lam != 0.0) {
                N[7 * p] = best_M[8 * p] + lam * best_M[8 * p];
            }
            step[p] = best_M[7 * p + 6];
        }
        if (!cholesky_solve6(N, step, 1) || !all_finite(step, 6)) {
            return 0;
        }
        /* _largest_move over the best linearisation's points */
        {
            const double w1 = step[0], w2 = step[1], w3 = step[2], v1 = step[3], v2 = step[4], v3 = step[5];
            double largest = 0.0;
            for (i = 0; i < n; i++) {
                const double x = pts[best][3 * i], y = pts[best][3 * i + 1], z = pts[best][3 * i + 2];
                double dx = w2 * z - w3 * y + v1, dy = w3 * x - w1 * z + v2, dz = w1 * y - w2 * x + v3;
                double d2 = dx * dx + dy * dy + dz * dz;
                if (d2 > largest) {
                    largest = d2;
                }
            }
            moved = sqrt(largest);
        }
        memcpy(RT, best_RT, sizeof RT);
        perturb(RT, step);
        if (!all_finite(RT, 12)) {
            return 0;
        }
        if (moved < tol) {
            break;
        }
    }
    if (it > max_iter) {
        return 0; /* no convergence: the Python code raises */
    }
    *iterations = it;
    double *N = blob, *res = blob + 36, *rlin = blob + 36 + 2 * n;
    for (int p = 0; p < 6; p++) {
        for (int q = 0; q < 6; q++) {
            N[6 * p + q] = best_M[7 * p + q];
        }
    }
    if (!conditioning_settled(N, max_condition)) {
        return 0;
    }
    memcpy(H, RT, sizeof RT);
    H[12] = H[13] = H[14] = 0.0;
    H[15] = 1.0;
    /* the residuals after the last (sub-tolerance) step, by the best linearisation, reprojected */
    {
        double sum_sq = 0.0;
        for (i = 0; i < n; i++) {
            double r2[2];
            for (int c = 0; c < 2; c++) {
                const double *j = Jr[best] + 7 * (2 * i + c);
                double s = 0.0;
                for (int p = 0; p < 6; p++) {
                    s += j[p] * step[p];
                }
                r2[c] = j[6] - s;
            }
            if (!pixel_residual(k, a, obs + 4 * i, obs[4 * i + 2] - r2[0], obs[4 * i + 3] - r2[1], res + 2 * i)) {
                return 0;
            }
            rlin[2 * i] = r2[0];
            rlin[2 * i + 1] = r2[1];
            sum_sq += res[2 * i] * res[2 * i] + res[2 * i + 1] * res[2 * i + 1];
        }
        if (!all_finite(res, 2 * n)) {
            return 0;
        }
        scalars[0] = sqrt(sum_sq / (double)n);
    }
    /* motion: the rotation vector and translation of C_H_C = H H0^-1 (H0 affine: [A | t]) */
    {
        const double a11 = H0[0], a12 = H0[1], a13 = H0[2], a21 = H0[4], a22 = H0[5], a23 = H0[6];
        const double a31 = H0[8], a32 = H0[9], a33 = H0[10];
        const double C[9] = {a22 * a33 - a23 * a32, a13 * a32 - a12 * a33, a12 * a23 - a13 * a22,
                             a23 * a31 - a21 * a33, a11 * a33 - a13 * a31, a13 * a21 - a11 * a23,
                             a21 * a32 - a22 * a31, a12 * a31 - a11 * a32, a11 * a22 - a12 * a21};
        const double det = a11 * C[0] + a12 * C[3] + a13 * C[6];
        if (!(fabs(det) > 1e-12) || !isfinite(det)) {
            return 0;
        }
        double Ai[12], Mrot[9]; /* H0^-1 = [A^-1 | -A^-1 t] */
        for (int p = 0; p < 3; p++) {
            for (int q = 0; q < 3; q++) {
                Ai[4 * p + q] = C[3 * p + q] / det;
            }
            Ai[4 * p + 3] = -(Ai[4 * p] * H0[3] + Ai[4 * p + 1] * H0[7] + Ai[4 * p + 2] * H0[11]);
        }
        for (int p = 0; p < 3; p++) {
            for (int q = 0; q < 4; q++) {
                double s = H[4 * p] * Ai[q] + H[4 * p + 1] * Ai[4 + q] + H[4 * p + 2] * Ai[8 + q];
                if (q < 3) {
                    Mrot[3 * p + q] = s;
                }
                else {
                    motion[3 + p] = s + H[4 * p + 3];
                }
            }
        }
        if (!all_finite(Mrot, 9) || !rodrigues_vector(Mrot, motion) || !all_finite(motion, 6)) {
            return 0;
        }
    }
    /* eq. 14, as _estimate computes it (float ** 2 by pow) */
    scalars[1] = sqrt(pow(fabs(motion[0]), 2.0) + pow(fabs(motion[1]), 2.0) + pow(fabs(motion[2]), 2.0)) *
                 (180.0 / 3.14159265358979323846);
    scalars[2] = sqrt(pow(fabs(motion[3]), 2.0) + pow(fabs(motion[4]), 2.0) + pow(fabs(motion[5]), 2.0));
    return all_finite(scalars, 3) && all_finite(rlin, 2 * n);
}

/* --- the module ------------------------------------------------------------------------------------ */

PyDoc_STRVAR(np_u_doc,
"np_u(C_H_G, p_G, uv, camera, max_condition, H_out, x_out)\n"
"--\n"
"\n"
"NP-U (selfview.online.differential_update) for the common case.\n"
"\n"
"C_H_G (4, 4), p_G (N, 3), uv (N, 2): C-contiguous float64 arrays; camera: an object with the number\n"
"attributes f, kappa, cx, cy, aspect; max_condition: online.MAX_CONDITION; H_out (4, 4), x_out (6,):\n"
"writable C-contiguous float64 arrays, filled with C'_H_G and the motion on success.\n"
"\n"
"Returns (rms_px, delta_deg, d_mm, blob), blob the bytes of 16 N float64: [A | b] of eq. 17 (2N, 7)\n"
"then the residuals (N, 2) [px]; or None for any case the Python code is to handle (input of another\n"
"kind or shape, non-finite numbers, N < 3, a point behind the camera, a system whose conditioning the\n"
"trace bound does not settle, a residual the Newton inversion does not reach). Raises TypeError or\n"
"ValueError for wrong arguments otherwise (their number, max_condition, the output arrays).");

static PyObject *
np_u(PyObject *Py_UNUSED(module), PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer hv = {0}, pv = {0}, uvv = {0}, hov = {0}, xov = {0};
    double stack_work[7 * STACK_POINTS];
    double *work = NULL;
    PyObject *blob = NULL, *result = NULL;
    double cam[5], max_condition, H[16], x[6], scalars[3];
    Py_ssize_t n;
    int r;

    if (nargs != 7) {
        PyErr_Format(PyExc_TypeError, "np_u expected 7 arguments, got %zd", nargs);
        return NULL;
    }
    if (!PyFloat_Check(args[4]) && !PyLong_Check(args[4])) {
        PyErr_Format(PyExc_TypeError, "np_u: max_condition must be a number, got %.200s", Py_TYPE(args[4])->tp_name);
        return NULL;
    }
    max_condition = PyFloat_AsDouble(args[4]);
    if (max_condition == -1.0 && PyErr_Occurred()) {
        return NULL;
    }
    /* the camera first: reading its attributes may run Python code, none runs while buffers are held */
    {
        PyObject *names[5] = {str_f, str_kappa, str_cx, str_cy, str_aspect};
        for (int i = 0; i < 5; i++) {
            r = camera_value(args[3], names[i], &cam[i]);
            if (r <= 0) {
                if (r < 0) {
                    return NULL;
                }
                Py_RETURN_NONE;
            }
        }
    }
    if (get_output(args[5], &hov, 16, "H_out") < 0 || get_output(args[6], &xov, 6, "x_out") < 0) {
        goto error;
    }
    if ((r = get_input(args[0], &hv, 4, 4)) <= 0 || (r = get_input(args[1], &pv, -1, 3)) <= 0) {
        goto fallback_or_error;
    }
    n = pv.shape[0];
    if ((r = get_input(args[2], &uvv, n, 2)) <= 0) {
        goto fallback_or_error;
    }
    if (n < 3) {
        goto fallback;
    }
    blob = PyBytes_FromStringAndSize(NULL, 16 * n * (Py_ssize_t)sizeof(double));
    if (blob == NULL) {
        goto error;
    }
    if (n <= STACK_POINTS) {
        work = stack_work;
    }
    else if ((work = PyMem_Malloc(7 * (size_t)n * sizeof(double))) == NULL) {
        PyErr_NoMemory();
        goto error;
    }
    {
        double *Ab = (double *)PyBytes_AS_STRING(blob);
        if (!solve((const double *)hv.buf, (const double *)pv.buf, (const double *)uvv.buf, n, cam, max_condition,
                   work, Ab, Ab + 14 * n, H, x, scalars)) {
            goto fallback;
        }
    }
    memcpy(hov.buf, H, sizeof H);
    memcpy(xov.buf, x, sizeof x);
    if ((result = PyTuple_New(4)) == NULL) {
        goto error;
    }
    for (int i = 0; i < 3; i++) {
        PyObject *v = PyFloat_FromDouble(scalars[i]);
        if (v == NULL) {
            Py_CLEAR(result);
            goto error;
        }
        PyTuple_SET_ITEM(result, i, v);
    }
    PyTuple_SET_ITEM(result, 3, blob); /* steals it */
    blob = NULL;
    goto done;

fallback_or_error:
    if (r < 0) {
        goto error;
    }
fallback:
    result = Py_None;
    Py_INCREF(result);
    goto done;
error:
    result = NULL;
done:
    Py_XDECREF(blob);
    if (work != NULL && work != stack_work) {
        PyMem_Free(work);
    }
    PyBuffer_Release(&uvv);
    PyBuffer_Release(&pv);
    PyBuffer_Release(&hv);
    PyBuffer_Release(&xov);
    PyBuffer_Release(&hov);
    return result;
}

PyDoc_STRVAR(np_i_doc,
"np_i(C_H_G, H_start, p_G, uv, camera, max_condition, tol, max_iter, H_out, motion_out)\n"
"--\n"
"\n"
"The Gauss-Newton of NP-I and of NP-R's refinement (selfview.online._gauss_newton) for the common case.\n"
"\n"
"C_H_G (4, 4) the prior, H_start (4, 4) the start or None (then the prior, its rotation made\n"
"orthonormal), p_G (N, 3), uv (N, 2): C-contiguous float64 arrays; camera: an object with the number\n"
"attributes f, kappa, cx, cy, aspect; max_condition: online.MAX_CONDITION; tol [mm] a number, max_iter\n"
"an int; H_out (4, 4), motion_out (6,): writable C-contiguous float64 arrays, filled on success.\n"
"\n"
"Returns (rms_px, delta_deg, d_mm, iterations, blob), blob the bytes of 36 + 4 N float64: the normal\n"
"matrix J^T J (6, 6) of the last accepted linearisation, the residuals (N, 2) [px], the linearised\n"
"residuals (2N,) after the last step; or None for any case the Python code is to handle (input of\n"
"another kind or shape, a prior whose last row is not (0, 0, 0, 1), non-finite numbers, N < 3, a point\n"
"behind the camera, a system whose conditioning the trace bound does not settle, a singular step, no\n"
"convergence, a motion near a half turn). Raises TypeError or ValueError for wrong arguments otherwise.");

static PyObject *
np_i(PyObject *Py_UNUSED(module), PyObject *const *args, Py_ssize_t nargs)
{
    Py_buffer hv = {0}, sv = {0}, pv = {0}, uvv = {0}, hov = {0}, mov = {0};
    double stack_work[38 * STACK_POINTS];
    double *work = NULL;
    PyObject *blob = NULL, *result = NULL;
    double cam[5], max_condition, tol, H[16], Hs[16], motion[6], scalars[3];
    long max_iter, iterations = 0;
    Py_ssize_t n;
    int r, overflow = 0;

    if (nargs != 10) {
        PyErr_Format(PyExc_TypeError, "np_i expected 10 arguments, got %zd", nargs);
        return NULL;
    }
    if (!PyFloat_Check(args[5]) && !PyLong_Check(args[5])) {
        PyErr_Format(PyExc_TypeError, "np_i: max_condition must be a number, got %.200s", Py_TYPE(args[5])->tp_name);
        return NULL;
    }
    max_condition = PyFloat_AsDouble(args[5]);
    if (max_condition == -1.0 && PyErr_Occurred()) {
        return NULL;
    }
    /* tol and max_iter as the Python code takes them; anything else is its case */
    if (PyFloat_Check(args[6])) {
        tol = PyFloat_AS_DOUBLE(args[6]);
    }
    else if (PyLong_CheckExact(args[6])) {
        tol = PyLong_AsDouble(args[6]);
        if (tol == -1.0 && PyErr_Occurred()) {
            if (!PyErr_ExceptionMatches(PyExc_OverflowError)) {
                return NULL;
            }
            PyErr_Clear();
            Py_RETURN_NONE;
        }
    }
    else {
        Py_RETURN_NONE;
    }
    if (!PyLong_CheckExact(args[7])) {
        Py_RETURN_NONE;
    }
    max_iter = PyLong_AsLongAndOverflow(args[7], &overflow);
    if (max_iter == -1 && PyErr_Occurred()) {
        return NULL;
    }
    if (overflow || max_iter < 1 || max_iter > 1000000) {
        Py_RETURN_NONE;
    }
    {
        PyObject *names[5] = {str_f, str_kappa, str_cx, str_cy, str_aspect};
        for (int i = 0; i < 5; i++) {
            r = camera_value(args[4], names[i], &cam[i]);
            if (r <= 0) {
                if (r < 0) {
                    return NULL;
                }
                Py_RETURN_NONE;
            }
        }
    }
    if (get_output(args[8], &hov, 16, "H_out") < 0 || get_output(args[9], &mov, 6, "motion_out") < 0) {
        goto error;
    }
    if ((r = get_input(args[0], &hv, 4, 4)) <= 0) {
        goto fallback_or_error;
    }
    if (args[1] != Py_None && (r = get_input(args[1], &sv, 4, 4)) <= 0) {
        goto fallback_or_error;
    }
    if ((r = get_input(args[2], &pv, -1, 3)) <= 0) {
        goto fallback_or_error;
    }
    n = pv.shape[0];
    if ((r = get_input(args[3], &uvv, n, 2)) <= 0) {
        goto fallback_or_error;
    }
    if (n < 3) {
        goto fallback;
    }
    {
        const double *H0 = (const double *)hv.buf;
        if (H0[12] != 0.0 || H0[13] != 0.0 || H0[14] != 0.0 || H0[15] != 1.0) {
            goto fallback;
        }
        if (args[1] != Py_None) {
            memcpy(Hs, sv.buf, sizeof Hs);
        }
        else { /* online._orthonormal(C_H_G) */
            const double A[9] = {H0[0], H0[1], H0[2], H0[4], H0[5], H0[6], H0[8], H0[9], H0[10]};
            double Q[9];
            if (!all_finite(A, 9) || !polar3(A, Q)) {
                goto fallback;
            }
            for (int p = 0; p < 3; p++) {
                memcpy(Hs + 4 * p, Q + 3 * p, 3 * sizeof(double));
                Hs[4 * p + 3] = H0[4 * p + 3];
            }
            Hs[12] = Hs[13] = Hs[14] = 0.0;
            Hs[15] = 1.0;
        }
    }
    blob = PyBytes_FromStringAndSize(NULL, (36 + 4 * n) * (Py_ssize_t)sizeof(double));
    if (blob == NULL) {
        goto error;
    }
    if (n <= STACK_POINTS) {
        work = stack_work;
    }
    else if ((work = PyMem_Malloc(38 * (size_t)n * sizeof(double))) == NULL) {
        PyErr_NoMemory();
        goto error;
    }
    if (!gauss_newton((const double *)hv.buf, Hs, (const double *)pv.buf, (const double *)uvv.buf, n, cam,
                      max_condition, tol, max_iter, work, H, motion, (double *)PyBytes_AS_STRING(blob), scalars,
                      &iterations)) {
        goto fallback;
    }
    memcpy(hov.buf, H, sizeof H);
    memcpy(mov.buf, motion, sizeof motion);
    result = Py_BuildValue("(dddlN)", scalars[0], scalars[1], scalars[2], iterations, blob);
    blob = NULL; /* N: the tuple owns it, or Py_BuildValue released it */
    goto done;

fallback_or_error:
    if (r < 0) {
        goto error;
    }
fallback:
    result = Py_None;
    Py_INCREF(result);
    goto done;
error:
    result = NULL;
done:
    Py_XDECREF(blob);
    if (work != NULL && work != stack_work) {
        PyMem_Free(work);
    }
    PyBuffer_Release(&uvv);
    PyBuffer_Release(&pv);
    PyBuffer_Release(&sv);
    PyBuffer_Release(&hv);
    PyBuffer_Release(&mov);
    PyBuffer_Release(&hov);
    return result;
}

static PyMethodDef cnpu_methods[] = {
    {"np_u", (PyCFunction)(void (*)(void))np_u, METH_FASTCALL, np_u_doc},
    {"np_i", (PyCFunction)(void (*)(void))np_i, METH_FASTCALL, np_i_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef cnpu_module = {
    PyModuleDef_HEAD_INIT,
    "selfview._cnpu",
    "The on-line solves of selfview.online for the common case: the differential update (NP-U) and the\n"
    "Gauss-Newton of NP-I and NP-R; see selfview/_native.py.",
    -1,
    cnpu_methods,
    NULL,
    NULL,
    NULL,
    NULL,
};

PyMODINIT_FUNC
PyInit__cnpu(void)
{
    if (str_f == NULL) {
        if ((str_f = PyUnicode_InternFromString("f")) == NULL ||
            (str_kappa = PyUnicode_InternFromString("kappa")) == NULL ||
            (str_cx = PyUnicode_InternFromString("cx")) == NULL ||
            (str_cy = PyUnicode_InternFromString("cy")) == NULL ||
            (str_aspect = PyUnicode_InternFromString("aspect")) == NULL) {
            Py_CLEAR(str_f);
            Py_CLEAR(str_kappa);
            Py_CLEAR(str_cx);
            Py_CLEAR(str_cy);
            return NULL;
        }
    }
    return PyModule_Create(&cnpu_module);
}
