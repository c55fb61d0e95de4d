/* selfview.measurement._csil: the compiled steps of the silhouette fit, each computing what its numpy reference in
 * silhouette.py computes, to the tests' tolerances: sample (_sample_py), candidates (_candidates_np, then
 * camera.undistort_pixels), vote (_votes_py), solve (_solve_py). Pixels are read as cv2.remap reads them; equal scores
 * rank by position. A point the Python code refuses makes sample return -1, a singular system solve return code 2: the
 * caller then runs the reference. Bad arguments raise TypeError or ValueError naming them. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define API_VERSION 2
#define MAXBUF 16

enum { T_F64 = 1, T_I64 = 2, T_F32 = 3, T_U8 = 4 };

typedef struct {
    Py_buffer v[MAXBUF];
    int n;
    void *work; /* the call's scratch memory */
} BufSet;

static void bufs_release(BufSet *s)
{
    for (int i = 0; i < s->n; i++)
        PyBuffer_Release(&s->v[i]);
    s->n = 0;
    PyMem_Free(s->work);
}

static int buf_kind(const Py_buffer *b)
{
    const char *f = b->format ? b->format : "B";
    if (*f == '@' || *f == '=')
        f++;
    if (f[0] == '\0' || f[1] != '\0')
        return 0;
    if (f[0] == 'd' && b->itemsize == 8)
        return T_F64;
    if (f[0] == 'f' && b->itemsize == 4)
        return T_F32;
    if (f[0] == 'B' && b->itemsize == 1)
        return T_U8;
    if ((f[0] == 'q' || f[0] == 'l' || f[0] == 'n') && b->itemsize == 8)
        return T_I64;
    return 0;
}

/* argument name's buffer: C-contiguous, of type kind, ndim dimensions of the given shape (-1: any); NULL: raised */
static Py_buffer *get_buf(BufSet *s, PyObject *o, const char *name, int kind, int writable, int ndim,
                          const Py_ssize_t *shape)
{
    if (s->n >= MAXBUF) {
        PyErr_SetString(PyExc_RuntimeError, "_csil: too many buffers");
        return NULL;
    }
    Py_buffer *b = &s->v[s->n];
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    const char *tn = kind == T_F64 ? "float64" : kind == T_F32 ? "float32" : kind == T_U8 ? "uint8" : "int64";
    if (PyObject_GetBuffer(o, b, flags) < 0) {
        PyErr_Clear();
        PyErr_Format(PyExc_TypeError, "%s: expected a C-contiguous%s %s array, got %.100s", name,
                     writable ? ", writable" : "", tn, Py_TYPE(o)->tp_name);
        return NULL;
    }
    s->n++;
    if (buf_kind(b) != kind && !(kind == T_F32 && buf_kind(b) == T_U8)) { /* a picture: float32 or uint8 */
        PyErr_Format(PyExc_TypeError, "%s: expected a %s array, got elements of format '%s'", name, tn,
                     b->format ? b->format : "B");
        return NULL;
    }
    if (b->ndim != ndim) {
        PyErr_Format(PyExc_ValueError, "%s: expected a %d-D array, got %d-D", name, ndim, b->ndim);
        return NULL;
    }
    for (int i = 0; i < ndim; i++) {
        if (shape[i] >= 0 && b->shape[i] != shape[i]) {
            PyErr_Format(PyExc_ValueError, "%s: dimension %d is %zd, expected %zd", name, i, b->shape[i], shape[i]);
            return NULL;
        }
    }
    return b;
}

#define GET(var, obj, name, kind, wr, nd, ...)                                                           \
    do {                                                                                                 \
        const Py_ssize_t shp_[] = {__VA_ARGS__};                                                         \
        var = get_buf(&bs, obj, name, kind, wr, nd, shp_);                                               \
        if (!var)                                                                                        \
            goto out;                                                                                   \
    } while (0)

/* the call's scratch memory (freed with its buffers) */
#define ALLOC(var, bytes)                                                                                \
    do {                                                                                                 \
        var = bs.work = PyMem_Malloc(bytes);                                                             \
        if (!var) {                                                                                      \
            PyErr_NoMemory();                                                                            \
            goto out;                                                                                    \
        }                                                                                                \
    } while (0)

#define REQUIRE(ok, exc, ...)                                                                            \
    do {                                                                                                 \
        if (!(ok)) {                                                                                     \
            PyErr_Format(exc, __VA_ARGS__);                                                              \
            goto out;                                                                                    \
        }                                                                                                \
    } while (0)

/* whether every index v[0..n) is in 0..hi-1; else ValueError "name: <item> i names <what> v, expected ..." */
static int indices_ok(const int64_t *v, Py_ssize_t n, Py_ssize_t hi, const char *name, const char *item,
                      const char *what)
{
    for (Py_ssize_t i = 0; i < n; i++)
        if (v[i] < 0 || v[i] >= hi) {
            if (hi == 2)
                PyErr_Format(PyExc_ValueError, "%s: %s %zd names %s %lld, expected 0 or 1", name, item, i, what,
                             (long long)v[i]);
            else
                PyErr_Format(PyExc_ValueError, "%s: %s %zd names %s %lld, expected 0..%zd", name, item, i, what,
                             (long long)v[i], hi - 1);
            return 0;
        }
    return 1;
}

static void cross3(const double a[3], const double b[3], double out[3])
{
    out[0] = a[1] * b[2] - a[2] * b[1];
    out[1] = a[2] * b[0] - a[0] * b[2];
    out[2] = a[0] * b[1] - a[1] * b[0];
}

/* the k-th smallest of v[0..n) (Hoare's selection; v is reordered: v[k] holds it, v[0..k) the ones not above it) */
static double select_kth(double *v, Py_ssize_t n, Py_ssize_t k)
{
    Py_ssize_t lo = 0, hi = n - 1;
    while (lo < hi) {
        const double pivot = v[lo + (hi - lo) / 2];
        Py_ssize_t i = lo, j = hi;
        while (i <= j) {
            while (v[i] < pivot)
                i++;
            while (v[j] > pivot)
                j--;
            if (i <= j) {
                const double t = v[i];
                v[i] = v[j];
                v[j] = t;
                i++;
                j--;
            }
        }
        if (k <= j)
            hi = j;
        else if (k >= i)
            lo = i;
        else
            break;
    }
    return v[k];
}

/* np.median of n finite values (the buffer is reordered): the middle one, or the mean of the two middle ones */
static double median(double *v, Py_ssize_t n)
{
    const double upper = select_kth(v, n, n / 2);
    if (n % 2)
        return upper;
    double lower = v[0];
    for (Py_ssize_t i = 1; i < n / 2; i++)
        lower = v[i] > lower ? v[i] : lower;
    return 0.5 * (lower + upper);
}

/* geometry.R_from_rotvecs of one vector: I + sin(th) K + (1 - cos(th)) K^2, K = [v / th]x (I + [v]x near 0) */
static void rotvec_R(const double *v, double R[9])
{
    const double th = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]), n = th < 1e-12 ? 1.0 : th;
    const double s = th < 1e-12 ? 1.0 : sin(th), c = th < 1e-12 ? 0.0 : 1.0 - cos(th);
    const double K[9] = {0, -v[2] / n, v[1] / n, v[2] / n, 0, -v[0] / n, -v[1] / n, v[0] / n, 0};
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            double kk = 0.0;
            for (int m = 0; m < 3; m++)
                kk += K[3 * i + m] * K[3 * m + j];
            R[3 * i + j] = (i == j ? 1.0 : 0.0) + s * K[3 * i + j] + c * kk;
        }
}

/* the rigid transform H (4, 4, row-major) applied to p */
static void apply_H(const double *H, const double p[3], double out[3])
{
    for (int i = 0; i < 3; i++)
        out[i] = H[4 * i] * p[0] + H[4 * i + 1] * p[1] + H[4 * i + 2] * p[2] + H[4 * i + 3];
}

/* the camera's position in the frame H maps to the camera's: -R^T t */
static void cam_origin(const double *H, double o[3])
{
    for (int i = 0; i < 3; i++)
        o[i] = -(H[i] * H[3] + H[4 + i] * H[7] + H[8 + i] * H[11]);
}

/* A x = b (6 x 6) by Gaussian elimination with partial pivoting on Ab = [A | b] (6, 7); 0 if singular */
static int solve6(double Ab[42], double x[6])
{
    for (int k = 0; k < 6; k++) {
        int p = k;
        for (int i = k + 1; i < 6; i++)
            if (fabs(Ab[7 * i + k]) > fabs(Ab[7 * p + k]))
                p = i;
        if (Ab[7 * p + k] == 0.0 || !isfinite(Ab[7 * p + k]))
            return 0;
        if (p != k)
            for (int j = 0; j < 7; j++) {
                const double t = Ab[7 * k + j];
                Ab[7 * k + j] = Ab[7 * p + j];
                Ab[7 * p + j] = t;
            }
        for (int i = k + 1; i < 6; i++) {
            const double m = Ab[7 * i + k] / Ab[7 * k + k];
            for (int j = k; j < 7; j++)
                Ab[7 * i + j] -= m * Ab[7 * k + j];
        }
    }
    for (int i = 5; i >= 0; i--) {
        double s = Ab[7 * i + 6];
        for (int j = i + 1; j < 6; j++)
            s -= Ab[7 * i + j] * x[j];
        x[i] = s / Ab[7 * i + i];
        if (!isfinite(x[i]))
            return 0;
    }
    return 1;
}

/* solve(q, pos, a_G, b_G, H, f, floor, iters, start_floor, H_out, w, r, pick, JtWJ) -> (code, sigma): q (S, C, 2)
 * candidates (undistorted sensor coordinates, NaN: none), pos (S,) each sample's edge in a_G, b_G (E, 3) [mm, G], H
 * the start C_H_G, f [px], start_floor < 0: none. code 0 done, 1 under 12 samples with a candidate (w 0), 2 singular */
static PyObject *py_solve(PyObject *Py_UNUSED(self), PyObject *args)
{
    PyObject *o_q, *o_pos, *o_a, *o_b, *o_H, *o_Ho, *o_w, *o_r, *o_pick, *o_J;
    double f, floor_, start_floor;
    Py_ssize_t iters;
    BufSet bs = {.n = 0};
    PyObject *ret = NULL;
    Py_buffer *b_q, *b_pos, *b_a, *b_b, *b_H, *b_Ho, *b_w, *b_r, *b_pick, *b_J;
    if (!PyArg_ParseTuple(args, "OOOOOddndOOOOO:solve", &o_q, &o_pos, &o_a, &o_b, &o_H, &f, &floor_, &iters,
                          &start_floor, &o_Ho, &o_w, &o_r, &o_pick, &o_J))
        return NULL;
    GET(b_q, o_q, "q", T_F64, 0, 3, -1, -1, 2);
    const Py_ssize_t S = b_q->shape[0], C = b_q->shape[1];
    GET(b_pos, o_pos, "pos", T_I64, 0, 1, S);
    GET(b_a, o_a, "a_G", T_F64, 0, 2, -1, 3);
    const Py_ssize_t E = b_a->shape[0];
    GET(b_b, o_b, "b_G", T_F64, 0, 2, E, 3);
    GET(b_H, o_H, "H", T_F64, 0, 2, 4, 4);
    GET(b_Ho, o_Ho, "H_out", T_F64, 1, 2, 4, 4);
    GET(b_w, o_w, "w", T_F64, 1, 1, S);
    GET(b_r, o_r, "r", T_F64, 1, 1, S);
    GET(b_pick, o_pick, "pick", T_I64, 1, 1, S);
    GET(b_J, o_J, "JtWJ", T_F64, 1, 2, 6, 6);
    REQUIRE(C >= 1 && E >= 1, PyExc_ValueError, "q, a_G: expected at least one candidate column and one edge");
    REQUIRE(f > 0.0 && isfinite(f) && floor_ > 0.0 && iters >= 0 && iters <= 1000, PyExc_ValueError,
            "f, floor, iters: expected f > 0, floor > 0, 0 <= iters <= 1000");
    const double *q = b_q->buf, *aG = b_a->buf, *bG = b_b->buf;
    const int64_t *pos = b_pos->buf;
    if (!indices_ok(pos, S, E, "pos", "sample", "edge"))
        goto out;
    double *Ho = b_Ho->buf, *w = b_w->buf, *r = b_r->buf, *JtWJ = b_J->buf;
    int64_t *pick = b_pick->buf;
    double *work;
    ALLOC(work, sizeof(double) * (size_t)(S + 13 * E + 1));
    double *absr = work, *M = work + S, *Dn = M + 3 * E, *K = Dn + 3 * E;  /* V (E, 7): the r term of each edge's row */
    double H[16];
    memcpy(H, b_H->buf, sizeof H);
    memset(JtWJ, 0, 36 * sizeof(double));
    for (Py_ssize_t s = 0; s < S; s++) {
        w[s] = 0.0;
        r[s] = NAN;
        pick[s] = 0;
    }
    double sigma = floor_;
    int code = 0;
    for (Py_ssize_t it = 0; it < iters; it++) {
        for (Py_ssize_t e = 0; e < E; e++) {
            double A[3], B[3];
            apply_H(H, aG + 3 * e, A);
            apply_H(H, bG + 3 * e, B);
            double l[3];
            cross3(A, B, l);
            const double N = hypot(l[0], l[1]);
            double *m = M + 3 * e, *d = Dn + 3 * e, *V = K + 7 * e;
            for (int i = 0; i < 3; i++) {
                m[i] = l[i] / N;
                d[i] = (B[i] - A[i]) / N;
            }
            V[0] = m[1] * m[2];
            V[1] = -m[0] * m[2];
            V[2] = 0.0;
            V[3] = m[1] * d[2];
            V[4] = -m[0] * d[2];
            V[5] = m[0] * d[1] - m[1] * d[0];
        }
        Py_ssize_t nh = 0;
        for (Py_ssize_t s = 0; s < S; s++) {
            const double *m = M + 3 * pos[s];
            double best = INFINITY;
            Py_ssize_t bk = 0;
            for (Py_ssize_t c = 0; c < C; c++) {
                const double *qq = q + 2 * (s * C + c);
                double rc = qq[0] * m[0] + qq[1] * m[1] + f * m[2];
                if (!isfinite(rc))
                    rc = INFINITY;
                if (fabs(rc) < fabs(best)) {
                    best = rc;
                    bk = c;
                }
            }
            pick[s] = bk;
            r[s] = best;
            if (isfinite(best))
                absr[nh++] = fabs(best);
        }
        if (nh < 12) {
            memset(w, 0, (size_t)S * sizeof(double));
            code = 1;
            break;
        }
        double mad = median(absr, nh);
        double fl = start_floor < 0 ? floor_ : fmax(floor_, start_floor * pow(0.5, (double)it));
        sigma = fmax(1.4826 * mad, fl);
        double cw = 4.685 * sigma;
        double A[36] = {0}, g[6] = {0};
        for (Py_ssize_t s = 0; s < S; s++) {
            if (!isfinite(r[s])) {
                w[s] = 0.0;
                continue;
            }
            double u = r[s] / cw;
            w[s] = fabs(u) < 1 ? (1 - u * u) * (1 - u * u) : 0.0;
            if (w[s] == 0.0)
                continue;
            const double *qq = q + 2 * (s * C + pick[s]), qv[3] = {qq[0], qq[1], f};
            const double *m = M + 3 * pos[s], *d = Dn + 3 * pos[s], *V = K + 7 * pos[s];
            /* (l x q, (B - A) x q) / |l_12| + r V, q = (x, y, f) */
            double J[6];
            cross3(m, qv, J);
            cross3(d, qv, J + 3);
            for (int i = 0; i < 6; i++)
                J[i] += r[s] * V[i];
            for (int i = 0; i < 6; i++) {
                double wi = w[s] * J[i];
                for (int j = i; j < 6; j++)
                    A[6 * i + j] += wi * J[j];
                g[i] += wi * r[s];
            }
        }
        for (int i = 0; i < 6; i++)
            for (int j = 0; j < i; j++)
                A[6 * i + j] = A[6 * j + i];
        memcpy(JtWJ, A, sizeof A);
        /* the normal equations scaled to a unit diagonal, a 1e-6 ridge */
        double dd[6], Ab[42], x[6];
        for (int i = 0; i < 6; i++)
            dd[i] = sqrt(fmax(A[7 * i], 1e-12));
        for (int i = 0; i < 6; i++) {
            for (int j = 0; j < 6; j++)
                Ab[7 * i + j] = A[6 * i + j] / (dd[i] * dd[j]) + (i == j ? 1e-6 : 0.0);
            Ab[7 * i + 6] = g[i] / dd[i];
        }
        if (!solve6(Ab, x)) {
            code = 2;
            break;
        }
        double dxi[6], Rm[9], Hn[16] = {[15] = 1.0};
        for (int i = 0; i < 6; i++)
            dxi[i] = -x[i] / dd[i];
        rotvec_R(dxi, Rm);
        for (int i = 0; i < 3; i++)
            for (int j = 0; j < 4; j++)
                Hn[4 * i + j] = Rm[3 * i] * H[j] + Rm[3 * i + 1] * H[4 + j] + Rm[3 * i + 2] * H[8 + j] +
                                (j == 3 ? dxi[3 + i] : 0.0);
        memcpy(H, Hn, sizeof H);
        double mr = fmax(fabs(dxi[0]), fmax(fabs(dxi[1]), fabs(dxi[2])));
        double mt = fmax(fabs(dxi[3]), fmax(fabs(dxi[4]), fabs(dxi[5])));
        if (fl <= floor_ && mr < 1e-7 && mt < 1e-5)
            break;
    }
    memcpy(Ho, H, sizeof H);
    ret = Py_BuildValue("(id)", code, sigma);
out:
    bufs_release(&bs);
    return ret;
}

/* vote(off, nrm, g, tol, votes): votes[iy * G + ix] the samples (off (S, C), NaN: none; nrm (S, 2)) with a candidate
 * within tol of nrm . (g[ix], g[iy]) */
static PyObject *py_vote(PyObject *Py_UNUSED(self), PyObject *args)
{
    PyObject *o_off, *o_n, *o_g, *o_v;
    double tol;
    BufSet bs = {.n = 0};
    PyObject *ret = NULL;
    Py_buffer *b_off, *b_n, *b_g, *b_v;
    if (!PyArg_ParseTuple(args, "OOOdO:vote", &o_off, &o_n, &o_g, &tol, &o_v))
        return NULL;
    GET(b_off, o_off, "off", T_F64, 0, 2, -1, -1);
    const Py_ssize_t S = b_off->shape[0], C = b_off->shape[1];
    GET(b_n, o_n, "nrm", T_F64, 0, 2, S, 2);
    GET(b_g, o_g, "g", T_F64, 0, 1, -1);
    const Py_ssize_t G = b_g->shape[0];
    GET(b_v, o_v, "votes", T_I64, 1, 1, G * G);
    REQUIRE(tol >= 0.0 && G >= 1 && G <= 4096, PyExc_ValueError, "tol, g: expected tol >= 0 and 1..4096 grid values");
    const double *off = b_off->buf, *nrm = b_n->buf, *g = b_g->buf;
    int64_t *votes = b_v->buf;
    double *cand;
    ALLOC(cand, sizeof(double) * (size_t)(C > 0 ? C : 1));
    memset(votes, 0, (size_t)(G * G) * sizeof(int64_t));
    for (Py_ssize_t s = 0; s < S; s++) {
        Py_ssize_t k = 0;
        for (Py_ssize_t c = 0; c < C; c++)
            if (isfinite(off[s * C + c]))
                cand[k++] = off[s * C + c];
        if (!k)
            continue;
        const double nx = nrm[2 * s], ny = nrm[2 * s + 1];
        for (Py_ssize_t iy = 0; iy < G; iy++) {
            const double py = ny * g[iy];
            for (Py_ssize_t ix = 0; ix < G; ix++) {
                const double p = nx * g[ix] + py;
                for (Py_ssize_t c = 0; c < k; c++)
                    if (fabs(p - cand[c]) <= tol) {
                        votes[iy * G + ix]++;
                        break;
                    }
            }
        }
    }
    ret = Py_NewRef(Py_None);
out:
    bufs_release(&bs);
    return ret;
}

typedef struct {
    double f, kappa, cx, cy, aspect, width, height, skew, rmax;
} Cam;
_Static_assert(sizeof(Cam) == 9 * sizeof(double), "Cam: nine doubles, no padding (get_cam copies cam into it)");

/* cam (8,): f, kappa, cx, cy, aspect, width, height, skew of a camera.CameraModel; 0 with an exception set */
static int get_cam(const double *v, Cam *c)
{
    for (int i = 0; i < 8; i++)
        if (!isfinite(v[i])) {
            PyErr_SetString(PyExc_ValueError,
                            "cam: expected 8 finite numbers (f, kappa, cx, cy, aspect, width, height, skew)");
            return 0;
        }
    if (!(v[0] > 0) || !(v[4] > 0) || !(v[5] > 0) || !(v[6] > 0)) {
        PyErr_SetString(PyExc_ValueError, "cam: expected f, aspect, width and height > 0");
        return 0;
    }
    memcpy(c, v, 8 * sizeof(double)); /* the fields in cam's order */
    c->rmax = INFINITY;
    if (c->kappa < 0) {
        double r = sqrt(-1.0 / (3.0 * c->kappa));
        c->rmax = r + c->kappa * r * r * r;
    }
    return 1;
}

/* CameraModel.project of a camera-frame point (eqs. 3, 4, as there); 0 where it refuses (z <= 0, beyond the fold) */
static int project(const Cam *c, const double p[3], double uv[2])
{
    if (!(p[2] > 0))
        return 0;
    const double X = c->f * p[0] / p[2], Y = c->f * p[1] / p[2];
    const double R = sqrt(X * X + Y * Y), k = c->kappa;
    double r = R;
    if (k > 0) {
        const double pp = 1.0 / k, q = -R / k;
        const double disc = sqrt((q / 2) * (q / 2) + (pp / 3) * (pp / 3) * (pp / 3));
        r = cbrt(-q / 2 + disc) + cbrt(-q / 2 - disc);
    } else if (k < 0) {
        if (R > c->rmax * (1 + 1e-12))
            return 0;
        const double pp = 1.0 / k, m = 2.0 * sqrt(-pp / 3.0);
        double arg = 3.0 * (-R / k) / (pp * m);
        arg = arg < -1.0 ? -1.0 : arg > 1.0 ? 1.0 : arg;
        r = m * cos(acos(arg) / 3.0 - 2.0 * 3.14159265358979323846 / 3.0);
    }
    if (k != 0.0)
        for (int i = 0; i < 3; i++)
            r -= (k * r * r * r + r - R) / (3 * k * r * r + 1.0);
    const double s = R > 0 ? r / R : 1.0;
    uv[0] = X * s / c->aspect + c->cx + c->skew * (Y * s); /* the grabber's shear: u += skew (v - cy) */
    uv[1] = Y * s + c->cy;
    return isfinite(uv[0]) && isfinite(uv[1]);
}

/* camera.CameraModel.in_image of one pixel: margin px or more inside the picture's border */
static int in_image(const Cam *c, const double u[2], double margin)
{
    return u[0] >= -0.5 + margin && u[0] <= c->width - 0.5 - margin && u[1] >= -0.5 + margin &&
           u[1] <= c->height - 0.5 - margin;
}

/* silhouette._blocked for one ray o + t d: through the box (lo, hi) before t = 1 (0 / 0: no bound, as there) */
static int blocked(const double o[3], const double d[3], const double *lo, const double *hi)
{
    double tn = -INFINITY, tf = 1.0;
    for (int i = 0; i < 3; i++) {
        const double t1 = (lo[i] - o[i]) / d[i], t2 = (hi[i] - o[i]) / d[i];
        if (isnan(t1) || isnan(t2))
            continue;
        tn = fmax(tn, fmin(t1, t2));
        tf = fmin(tf, fmax(t1, t2));
    }
    return (tn < tf - 1e-6) && (tn > 1e-6) && (tf - tn > 1e-4);
}

#define MAX_PER_EDGE 400

/* sample(a_G, b_G, d_in, finger, box, H, cam, margin, step, p, edge, uv, nrm) -> S, or -1: points every step px along
 * edges a_G -> b_G (E, 3) [mm, G] over 1 mm in front of H (C_H_G), margin px in the picture, not behind the other
 * finger's box (2, 2, 3); normals into the first face (d_in (E, 3)); writes p (Smax >= 400 E, 3), edge, uv [px], nrm */
static PyObject *py_sample(PyObject *Py_UNUSED(self), PyObject *args)
{
    PyObject *o_a, *o_b, *o_d, *o_fin, *o_box, *o_H, *o_cam, *o_p, *o_e, *o_uv, *o_n;
    double margin, step;
    BufSet bs = {.n = 0};
    PyObject *ret = NULL;
    Py_buffer *b_a, *b_b, *b_d, *b_fin, *b_box, *b_H, *b_cam, *b_p, *b_e, *b_uv, *b_n;
    Py_ssize_t S = 0;
    if (!PyArg_ParseTuple(args, "OOOOOOOddOOOO:sample", &o_a, &o_b, &o_d, &o_fin, &o_box, &o_H, &o_cam, &margin, &step,
                          &o_p, &o_e, &o_uv, &o_n))
        return NULL;
    GET(b_a, o_a, "a_G", T_F64, 0, 2, -1, 3);
    const Py_ssize_t E = b_a->shape[0];
    GET(b_b, o_b, "b_G", T_F64, 0, 2, E, 3);
    GET(b_d, o_d, "d_in", T_F64, 0, 2, E, 3);
    GET(b_fin, o_fin, "finger", T_I64, 0, 1, E);
    GET(b_box, o_box, "box", T_F64, 0, 3, 2, 2, 3);
    GET(b_H, o_H, "H", T_F64, 0, 2, 4, 4);
    GET(b_cam, o_cam, "cam", T_F64, 0, 1, 8);
    GET(b_p, o_p, "p", T_F64, 1, 2, -1, 3);
    const Py_ssize_t Smax = b_p->shape[0];
    GET(b_e, o_e, "edge", T_I64, 1, 1, Smax);
    GET(b_uv, o_uv, "uv", T_F64, 1, 2, Smax, 2);
    GET(b_n, o_n, "nrm", T_F64, 1, 2, Smax, 2);
    REQUIRE(Smax >= E * MAX_PER_EDGE, PyExc_ValueError, "p: room for %zd samples, expected %d per edge (%zd)", Smax,
            MAX_PER_EDGE, E * MAX_PER_EDGE);
    REQUIRE(step > 0 && isfinite(step) && isfinite(margin), PyExc_ValueError,
            "step, margin: expected step > 0 and a finite margin");
    const int64_t *fin = b_fin->buf;
    Cam c;
    if (!indices_ok(fin, E, 2, "finger", "edge", "finger") || !get_cam(b_cam->buf, &c))
        goto out;
    const double *aG = b_a->buf, *bG = b_b->buf, *dG = b_d->buf, *box = b_box->buf, *H = b_H->buf;
    double *P = b_p->buf, *UV = b_uv->buf, *NR = b_n->buf;
    int64_t *EO = b_e->buf;
    double o[3]; /* the camera's position in G */
    cam_origin(H, o);
    double all[2 * MAX_PER_EDGE]; /* the pixels of an edge's samples */
    for (Py_ssize_t e = 0; e < E; e++) {
        const double *a = aG + 3 * e, *b = bG + 3 * e, *d = dG + 3 * e, *lo = box + 6 * (1 - fin[e]), *hi = lo + 3;
        double A[3], B[3], ua[2], ub[2], m[3], m2[3], C1[3], C2[3], u1[2], u2[2];
        apply_H(H, a, A);
        apply_H(H, b, B);
        if (!(A[2] > 1.0 && B[2] > 1.0))
            continue;
        if (!project(&c, A, ua) || !project(&c, B, ub))
            goto refuse;
        const double kf = sqrt((ub[0] - ua[0]) * (ub[0] - ua[0]) + (ub[1] - ua[1]) * (ub[1] - ua[1])) / step;
        const int n = (int)(kf < 2 ? 2 : kf > MAX_PER_EDGE ? MAX_PER_EDGE : kf);
        /* the edge's side: its first face's direction in the picture */
        for (int i = 0; i < 3; i++) {
            m[i] = 0.5 * (a[i] + b[i]);
            m2[i] = m[i] + 0.05 * d[i];
        }
        apply_H(H, m, C1);
        apply_H(H, m2, C2);
        if (!project(&c, C1, u1) || !project(&c, C2, u2))
            goto refuse;
        const double side[2] = {u2[0] - u1[0], u2[1] - u1[1]};
        for (int k = 0; k < n; k++) {
            const double t = ((double)k + 0.5) / n;
            double p[3], pc[3];
            for (int i = 0; i < 3; i++)
                p[i] = a[i] + t * (b[i] - a[i]);
            apply_H(H, p, pc);
            if (!project(&c, pc, all + 2 * k))
                goto refuse;
        }
        /* tangents from the neighbours on the edge; kept: in the picture, not behind the other finger */
        for (int k = 0; k < n; k++) {
            const double *u = all + 2 * k;
            if (!in_image(&c, u, margin))
                continue;
            const double t = ((double)k + 0.5) / n;
            double p[3], dp[3];
            for (int i = 0; i < 3; i++) {
                p[i] = a[i] + t * (b[i] - a[i]);
                dp[i] = p[i] - o[i];
            }
            if (blocked(o, dp, lo, hi))
                continue;
            const double *v = k + 1 < n ? u : u - 2; /* the sample and the next one, or the last two */
            double tx = v[2] - v[0], ty = v[3] - v[1];
            const double L = sqrt(tx * tx + ty * ty) + 1e-12;
            tx /= L;
            ty /= L;
            const double nx = -ty, ny = tx, sg = nx * side[0] + ny * side[1] < 0 ? -1.0 : 1.0;
            memcpy(P + 3 * S, p, sizeof p);
            EO[S] = e;
            UV[2 * S] = u[0];
            UV[2 * S + 1] = u[1];
            NR[2 * S] = sg * nx;
            NR[2 * S + 1] = sg * ny;
            S++;
        }
    }
    ret = PyLong_FromSsize_t(S);
    goto out;
refuse:
    ret = PyLong_FromLong(-1);
out:
    bufs_release(&bs);
    return ret;
}

/* cv2.remap's sample (INTER_LINEAR, BORDER_REPLICATE): the position rounded to 1/32 px, weights in single precision */
#define PIX(row, x) (img8 ? (float)img8[(row) + (x)] : img[(row) + (x)])
static inline float bilinear(const float *img, const uint8_t *img8, int H, int W, float x, float y)
{
    x = x < -1e6f ? -1e6f : x > 1e6f ? 1e6f : x;
    y = y < -1e6f ? -1e6f : y > 1e6f ? 1e6f : y;
    const long X = lrintf(x * 32.0f), Y = lrintf(y * 32.0f);
    const int fx = (int)(X & 31), fy = (int)(Y & 31);
    const long ix = (X - fx) / 32, iy = (Y - fy) / 32;
    const float ax = (1.f / 32) * fx, ay = (1.f / 32) * fy;
    const int x0 = ix < 0 ? 0 : ix >= W ? W - 1 : (int)ix, x1 = ix + 1 < 0 ? 0 : ix + 1 >= W ? W - 1 : (int)ix + 1;
    const int y0 = iy < 0 ? 0 : iy >= H ? H - 1 : (int)iy, y1 = iy + 1 < 0 ? 0 : iy + 1 >= H ? H - 1 : (int)iy + 1;
    const Py_ssize_t r0 = (Py_ssize_t)y0 * W, r1 = (Py_ssize_t)y1 * W;
    return PIX(r0, x0) * ((1.f - ay) * (1.f - ax)) + PIX(r0, x1) * ((1.f - ay) * ax) +
           PIX(r1, x0) * (ay * (1.f - ax)) + PIX(r1, x1) * (ay * ax);
}
#undef PIX

static inline int sgnf(float v) { return (v > 0) - (v < 0); }

/* candidates(img, uv, nrm, lev1, lev2, R, gates, cam, off, face, contrast, q): img (H, W) float32 or uint8; uv, nrm
 * (S, 2); lev1, lev2 (S,) the first and second face's levels (NaN: none); R [px]; gates: plateau [px], least contrast,
 * level tolerance and its floor [grey]. Writes (S, C) off [px along nrm], face, contrast (NaN: none), q (S, C, 2). */
static PyObject *py_candidates(PyObject *Py_UNUSED(self), PyObject *args)
{
    PyObject *o_img, *o_uv, *o_n, *o_l1, *o_l2, *o_g, *o_cam, *o_off, *o_face, *o_con, *o_q;
    double R;
    BufSet bs = {.n = 0};
    PyObject *ret = NULL;
    Py_buffer *b_img, *b_uv, *b_n, *b_l1, *b_l2, *b_g, *b_cam, *b_off, *b_face, *b_con, *b_q;
    if (!PyArg_ParseTuple(args, "OOOOOdOOOOOO:candidates", &o_img, &o_uv, &o_n, &o_l1, &o_l2, &R, &o_g, &o_cam,
                          &o_off, &o_face, &o_con, &o_q))
        return NULL;
    GET(b_img, o_img, "img", T_F32, 0, 2, -1, -1);
    GET(b_uv, o_uv, "uv", T_F64, 0, 2, -1, 2);
    const Py_ssize_t S = b_uv->shape[0];
    GET(b_n, o_n, "nrm", T_F64, 0, 2, S, 2);
    GET(b_l1, o_l1, "lev1", T_F64, 0, 1, S);
    GET(b_l2, o_l2, "lev2", T_F64, 0, 1, S);
    GET(b_g, o_g, "gates", T_F64, 0, 1, 4);
    GET(b_cam, o_cam, "cam", T_F64, 0, 1, 8);
    GET(b_off, o_off, "off", T_F64, 1, 2, S, -1);
    const Py_ssize_t C = b_off->shape[1];
    GET(b_face, o_face, "face", T_F64, 1, 2, S, C);
    GET(b_con, o_con, "contrast", T_F64, 1, 2, S, C);
    GET(b_q, o_q, "q", T_F64, 1, 3, S, C, 2);
    const int Hh = (int)b_img->shape[0], Ww = (int)b_img->shape[1];
    const double *gates = b_g->buf;
    const int P = (int)gates[0];
    REQUIRE(b_img->shape[0] >= 1 && b_img->shape[1] >= 1 && b_img->shape[0] <= 1 << 20 && b_img->shape[1] <= 1 << 20,
            PyExc_ValueError, "img: expected a picture of 1..2^20 rows and columns");
    REQUIRE(R >= 1.0 && R <= 1000.0 && C >= 1 && (double)P == gates[0] && P >= 2 && P <= 50, PyExc_ValueError,
            "R, off, gates: expected 1 <= R <= 1000, a candidate column, a plateau of 2..50 px");
    Cam c;
    if (!get_cam(b_cam->buf, &c))
        goto out;
    const double *uv = b_uv->buf, *nr = b_n->buf, *l1 = b_l1->buf, *l2 = b_l2->buf;
    for (Py_ssize_t s = 0; s < 2 * S; s++)
        REQUIRE(isfinite(uv[s]) && isfinite(nr[s]), PyExc_ValueError, "uv, nrm: sample %zd is not finite", s / 2);
    const float min_con = (float)gates[1];
    const double ltol = gates[2], ltol_grey = gates[3];
    const int Ri = (int)ceil(R), L = 2 * Ri + 2 * P + 3, M = L - 4;
    float *work;
    ALLOC(work, sizeof(float) * (size_t)(4 * L) + sizeof(double) * (size_t)M);
    /* profile at offsets -Ri-P-1..Ri+P+1, D at -Ri-P..Ri+P; per step m (D's m + 1) the mean levels 2..P px each side */
    float *prof = work, *D = work + L, *face = D + L, *other = face + L;
    double *score = (double *)(other + L);
    const int is8 = buf_kind(b_img) == T_U8;
    const float *img = is8 ? NULL : b_img->buf;
    const uint8_t *img8 = is8 ? b_img->buf : NULL;
    double *OFF = b_off->buf, *FACE = b_face->buf, *CON = b_con->buf, *Q = b_q->buf;
    for (Py_ssize_t s = 0; s < S; s++) {
        const double u = uv[2 * s], v = uv[2 * s + 1], nx = nr[2 * s], ny = nr[2 * s + 1];
        for (int i = 0; i < L; i++) {
            const double k = (double)(i - Ri - P - 1);
            prof[i] = bilinear(img, img8, Hh, Ww, (float)(u + k * nx), (float)(v + k * ny));
        }
        for (int j = 0; j < L - 2; j++)
            D[j] = 0.5f * (prof[j + 2] - prof[j]);
        const int has1 = isfinite(l1[s]), has2 = isfinite(l2[s]);
        for (int m = 0; m < M; m++) {
            score[m] = INFINITY;
            const float a0 = fabsf(D[m]), a1 = fabsf(D[m + 1]), a2 = fabsf(D[m + 2]);
            if (!(a1 >= a0 && a1 > a2) || abs(m - Ri - P + 1) > R)
                continue;
            float fc = 0.f, ot = 0.f;
            for (int k = 2; k <= P; k++) {
                const int i1 = m + 2 + k, i2 = m + 2 - k;
                fc += prof[i1 > L - 1 ? L - 1 : i1];
                ot += prof[i2 < 0 ? 0 : i2];
            }
            face[m] = fc / (float)(P - 1);
            other[m] = ot / (float)(P - 1);
            const float con = face[m] - other[m];
            /* contrast, polarity (the derivative's sign is the face side's minus the other's), the faces' levels */
            if (!(fabsf(con) >= min_con) || sgnf(D[m + 1]) != sgnf(con))
                continue;
            if (has1 && !(fabs((double)face[m] - l1[s]) <= fmax(ltol * l1[s], ltol_grey)))
                continue;
            if (has2 && !(fabs((double)other[m] - l2[s]) <= fmax(ltol * l2[s], ltol_grey)))
                continue;
            score[m] = has1 ? fabs((double)face[m] - l1[s]) : -(double)fabsf(con);
        }
        /* the C best scores (ties: the nearer the profile's start), each located by a parabola through |D| */
        for (Py_ssize_t cc = 0; cc < C; cc++) {
            double *o = OFF + s * C + cc, *fo = FACE + s * C + cc, *co = CON + s * C + cc, *qo = Q + 2 * (s * C + cc);
            int m = -1;
            for (int i = 0; i < M; i++)
                if (score[i] < INFINITY && (m < 0 || score[i] < score[m]))
                    m = i;
            if (m < 0) {
                *o = *fo = *co = qo[0] = qo[1] = NAN;
                continue;
            }
            score[m] = INFINITY;
            const float a0 = fabsf(D[m]), a1 = fabsf(D[m + 1]), a2 = fabsf(D[m + 2]);
            const float den = a0 - 2 * a1 + a2;
            float frac = fabsf(den) > 1e-9f ? 0.5f * (a0 - a2) / den : 0.0f;
            frac = frac < -0.5f ? -0.5f : frac > 0.5f ? 0.5f : frac;
            const float off = (float)(m - Ri - P + 1) + frac;
            *o = off;
            *fo = face[m];
            *co = face[m] - other[m];
            /* camera.CameraModel.undistort_pixels of the candidate's pixel */
            const double pu = u + (double)off * nx, pv = v + (double)off * ny;
            const double X = c.aspect * (pu - c.cx - c.skew * (pv - c.cy)), Y = pv - c.cy, r2 = X * X + Y * Y;
            qo[0] = X * (1.0 + c.kappa * r2);
            qo[1] = Y * (1.0 + c.kappa * r2);
        }
    }
    ret = Py_NewRef(Py_None);
out:
    bufs_release(&bs);
    return ret;
}

static PyMethodDef methods[] = {
    {"solve", py_solve, METH_VARARGS, "silhouette._solve_py's IRLS (see _csil.c)."},
    {"vote", py_vote, METH_VARARGS, "silhouette._votes_py's vote (see _csil.c)."},
    {"sample", py_sample, METH_VARARGS, "silhouette._sample_py (see _csil.c)."},
    {"candidates", py_candidates, METH_VARARGS, "silhouette._candidates_np and camera.undistort_pixels (see _csil.c)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef moddef = {
    PyModuleDef_HEAD_INIT, "_csil",
    "The model-based fingertip measurement's IRLS (see selfview/measurement/silhouette.py, the reference).",
    -1, methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__csil(void)
{
    PyObject *m = PyModule_Create(&moddef);
    if (m && PyModule_AddIntConstant(m, "API", API_VERSION) < 0)
        Py_CLEAR(m);
    return m;
}
