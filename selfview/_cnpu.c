/* selfview._cnpu: the hot path of the paper's differential update (NP-U, ``online.differential_update``).
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

/* OpenCV's hal::Cholesky (CholImpl) of the 6x6 A with the identity as right-hand side, i.e.
 * cv2.invert(A, flags=cv2.DECOMP_CHOLESKY): B = A^-1 and 1, or 0 where it reports failure. */
static int
cholesky_inverse6(const double A[36], double B[36])
{
    double L[36];
    double s;
    int i, j, k;
    memcpy(L, A, sizeof L);
    for (i = 0; i < 36; i++) {
        B[i] = (i % 7 == 0) ? 1.0 : 0.0;
    }
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
        for (j = 0; j < 6; j++) {
            s = B[i * 6 + j];
            for (k = 0; k < i; k++) {
                s -= L[i * 6 + k] * B[k * 6 + j];
            }
            B[i * 6 + j] = s * L[i * 6 + i];
        }
    }
    for (i = 5; i >= 0; i--) { /* L^T x = y */
        for (j = 0; j < 6; j++) {
            s = B[i * 6 + j];
            for (k = 5; k > i; k--) {
                s -= L[k * 6 + i] * B[k * 6 + j];
            }
            B[i * 6 + j] = s * L[i * 6 + i];
        }
    }
    return 1;
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
        const double k3 = 3.0 * k;
        double sum_sq = 0.0;
        for (i = 0; i < n; i++) {
            double px = pc[3 * i], py = pc[3 * i + 1], pz = pc[3 * i + 2];
            double xn = px - dz * py + dy * pz + tx;
            double yn = dz * px + py - dx * pz + ty;
            double zn = -dy * px + dx * py + pz + tz;
            if (!(zn > 0.0)) {
                return 0;
            }
            double X = f * xn / zn, Y = f * yn / zn;
            double Xh = obs[4 * i], Yh = obs[4 * i + 1];
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
                return 0; /* the Python code falls back to selfview.camera.distort */
            }
            double s = R > 0.0 ? r / R : 1.0;
            double Xp = X * s, Yp = Y * s;
            double du = (Xh - Xp) / a, dv = Yh - Yp;
            res[2 * i] = du;
            res[2 * i + 1] = dv;
            sum_sq += du * du + dv * dv;
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

static PyMethodDef cnpu_methods[] = {
    {"np_u", (PyCFunction)(void (*)(void))np_u, METH_FASTCALL, np_u_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef cnpu_module = {
    PyModuleDef_HEAD_INIT,
    "selfview._cnpu",
    "The differential update (NP-U) of selfview.online for the common case; see selfview/_native.py.",
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
