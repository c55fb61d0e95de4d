/* selfview._csil: the compiled IRLS and vote of the model-based fingertip measurement (selfview.silhouette).
 *
 * The Python function ``silhouette._solve_py`` is the reference: this computes the same iterations (the
 * homogeneous model lines l = A x B of the edges, each sample's candidate nearest its line, Tukey's weights
 * over 1.4826 MAD floored, the scaled Gauss-Newton step with the 1e-6 ridge, the camera motion applied on
 * the left, the same stopping rule), in double precision; sums are taken in another order than numpy's, so
 * results agree with the reference to rounding, not bit for bit (the tests compare them at a tolerance
 * with a physical meaning).
 *
 *   vote(off, nrm, g, tol, votes)
 *     the vote of silhouette._coarse_shift (its numpy code the reference): votes (G * G,) int64 [iy * G + ix]
 *     the samples (off (S, C) candidates, NaN: none; nrm (S, 2)) with a candidate within tol of
 *     nrm . (g[ix], g[iy]); the same comparisons, n . d summed without the matrix product's rounding.
 *   solve(q, pos, a_G, b_G, H, f, floor, iters, start_floor, H_out, w, r, pick, JtWJ) -> (code, sigma)
 *     q (S, C, 2) float64 candidates (undistorted sensor coordinates, NaN: none); pos (S,) int64 the
 *     row of each sample's edge in a_G, b_G (E, 3) float64 (the edges' ends in G); H (4, 4) float64 the
 *     start; f the focal length; start_floor < 0 for none. Outputs (written): H_out (4, 4), w (S,),
 *     r (S,), pick (S,) int64, JtWJ (6, 6). code 0: done; 1: fewer than 12 samples with a candidate
 *     (w is zero, as the reference returns); 2: a singular system (the caller runs the reference).
 *
 * Every buffer is checked (type, dimensions, shape) and every index (pos) before it is used: bad
 * arguments raise TypeError or ValueError naming the argument. Only the CPython C API (the buffer protocol).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define API_VERSION 1
#define MAXBUF 16

enum { T_F64 = 1, T_I64 = 2 };

typedef struct {
    Py_buffer v[MAXBUF];
    int n;
} BufSet;

static void bufs_release(BufSet *s)
{
    for (int i = 0; i < s->n; i++)
        PyBuffer_Release(&s->v[i]);
    s->n = 0;
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
    if ((f[0] == 'q' || f[0] == 'l' || f[0] == 'n') && b->itemsize == 8)
        return T_I64;
    return 0;
}

/* The buffer of argument ``name``: C-contiguous, of type ``kind``, ``ndim`` dimensions of the given
 * shape (-1: any). NULL with an exception set. */
static Py_buffer *get_buf(BufSet *s, PyObject *o, const char *name, int kind, int writable, int ndim,
                          const Py_ssize_t *shape)
{
    if (s->n >= MAXBUF) {
        PyErr_SetString(PyExc_RuntimeError, "_csil: too many buffers");
        return NULL;
    }
    Py_buffer *b = &s->v[s->n];
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    const char *tn = kind == T_F64 ? "float64" : "int64";
    if (PyObject_GetBuffer(o, b, flags) < 0) {
        PyErr_Clear();
        PyErr_Format(PyExc_TypeError, "%s: expected a C-contiguous%s %s array, got %.100s", name,
                     writable ? ", writable" : "", tn, Py_TYPE(o)->tp_name);
        return NULL;
    }
    s->n++;
    if (buf_kind(b) != kind) {
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
            goto fail;                                                                                   \
    } while (0)

static int cmp_double(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

/* np.median of n finite values (the buffer is reordered) */
static double median(double *v, Py_ssize_t n)
{
    qsort(v, (size_t)n, sizeof(double), cmp_double);
    if (n % 2)
        return v[n / 2];
    return 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

/* geometry.R_from_rotvec */
static void rotvec_R(const double *v, double R[9])
{
    double th = sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
    double K[9] = {0, -v[2], v[1], v[2], 0, -v[0], -v[1], v[0], 0};
    if (th < 1e-12) {
        for (int i = 0; i < 9; i++)
            R[i] = K[i] + (i % 4 == 0 ? 1.0 : 0.0);
        return;
    }
    for (int i = 0; i < 9; i++)
        K[i] /= th;
    double s = sin(th), c = 1.0 - cos(th);
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            double kk = 0.0;
            for (int m = 0; m < 3; m++)
                kk += K[3 * i + m] * K[3 * m + j];
            R[3 * i + j] = (i == j ? 1.0 : 0.0) + s * K[3 * i + j] + c * kk;
        }
}

/* A x = b (6 x 6) by Gaussian elimination with partial pivoting; 0 if singular */
static int solve6(double A[36], double b[6], double x[6])
{
    for (int k = 0; k < 6; k++) {
        int p = k;
        for (int i = k + 1; i < 6; i++)
            if (fabs(A[6 * i + k]) > fabs(A[6 * p + k]))
                p = i;
        if (A[6 * p + k] == 0.0 || !isfinite(A[6 * p + k]))
            return 0;
        if (p != k) {
            for (int j = 0; j < 6; j++) {
                double t = A[6 * k + j];
                A[6 * k + j] = A[6 * p + j];
                A[6 * p + j] = t;
            }
            double t = b[k];
            b[k] = b[p];
            b[p] = t;
        }
        for (int i = k + 1; i < 6; i++) {
            double m = A[6 * i + k] / A[6 * k + k];
            for (int j = k; j < 6; j++)
                A[6 * i + j] -= m * A[6 * k + j];
            b[i] -= m * b[k];
        }
    }
    for (int i = 5; i >= 0; i--) {
        double s = b[i];
        for (int j = i + 1; j < 6; j++)
            s -= A[6 * i + j] * x[j];
        x[i] = s / A[6 * i + i];
    }
    for (int i = 0; i < 6; i++)
        if (!isfinite(x[i]))
            return 0;
    return 1;
}

static PyObject *py_solve(PyObject *self, PyObject *args)
{
    PyObject *o_q, *o_pos, *o_a, *o_b, *o_H, *o_Ho, *o_w, *o_r, *o_pick, *o_J;
    double f, floor_, start_floor;
    Py_ssize_t iters;
    BufSet bs = {.n = 0};
    Py_buffer *b_q, *b_pos, *b_a, *b_b, *b_H, *b_Ho, *b_w, *b_r, *b_pick, *b_J;
    double *work = NULL;
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
    if (C < 1 || E < 1) {
        PyErr_SetString(PyExc_ValueError, "q, a_G: expected at least one candidate column and one edge");
        goto fail;
    }
    if (!(f > 0.0) || !isfinite(f) || !(floor_ > 0.0) || iters < 0 || iters > 1000) {
        PyErr_SetString(PyExc_ValueError, "f, floor, iters: expected f > 0, floor > 0, 0 <= iters <= 1000");
        goto fail;
    }
    const double *q = b_q->buf, *aG = b_a->buf, *bG = b_b->buf;
    const int64_t *pos = b_pos->buf;
    for (Py_ssize_t s = 0; s < S; s++)
        if (pos[s] < 0 || pos[s] >= E) {
            PyErr_Format(PyExc_ValueError, "pos: sample %zd names edge %lld, expected 0..%zd", s, (long long)pos[s],
                         E - 1);
            goto fail;
        }
    double *Ho = b_Ho->buf, *w = b_w->buf, *r = b_r->buf, *JtWJ = b_J->buf;
    int64_t *pick = b_pick->buf;
    work = PyMem_Malloc(sizeof(double) * (size_t)(S + 13 * E + 1));
    if (!work) {
        PyErr_NoMemory();
        goto fail;
    }
    double *absr = work, *M = work + S, *Dn = M + 3 * E, *K = Dn + 3 * E;  /* V (E, 7): the r term of each edge's row */
    double H[16];
    memcpy(H, b_H->buf, sizeof H);
    for (int i = 0; i < 36; i++)
        JtWJ[i] = 0.0;
    for (Py_ssize_t s = 0; s < S; s++) {
        w[s] = 0.0;
        r[s] = NAN;
        pick[s] = 0;
    }
    double sigma = floor_;
    int code = 0;
    for (Py_ssize_t it = 0; it < iters; it++) {
        /* the model lines */
        for (Py_ssize_t e = 0; e < E; e++) {
            double A[3], B[3];
            for (int i = 0; i < 3; i++) {
                A[i] = H[4 * i] * aG[3 * e] + H[4 * i + 1] * aG[3 * e + 1] + H[4 * i + 2] * aG[3 * e + 2] + H[4 * i + 3];
                B[i] = H[4 * i] * bG[3 * e] + H[4 * i + 1] * bG[3 * e + 1] + H[4 * i + 2] * bG[3 * e + 2] + H[4 * i + 3];
            }
            double l0 = A[1] * B[2] - A[2] * B[1], l1 = A[2] * B[0] - A[0] * B[2], l2 = A[0] * B[1] - A[1] * B[0];
            double N = hypot(l0, l1);
            double *m = M + 3 * e, *d = Dn + 3 * e, *V = K + 7 * e;
            m[0] = l0 / N;
            m[1] = l1 / N;
            m[2] = l2 / N;
            for (int i = 0; i < 3; i++)
                d[i] = (B[i] - A[i]) / N;
            V[0] = m[1] * m[2];
            V[1] = -m[0] * m[2];
            V[2] = 0.0;
            V[3] = m[1] * d[2];
            V[4] = -m[0] * d[2];
            V[5] = m[0] * d[1] - m[1] * d[0];
        }
        /* each sample's candidate nearest its line */
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
            for (Py_ssize_t s = 0; s < S; s++)
                w[s] = 0.0;
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
            const double *qq = q + 2 * (s * C + pick[s]);
            const double x = qq[0], y = qq[1];
            const double *m = M + 3 * pos[s], *d = Dn + 3 * pos[s], *V = K + 7 * pos[s];
            /* (l x q, (B - A) x q) / |l_12| + r V, q = (x, y, f) */
            double J[6];
            J[0] = m[1] * f - m[2] * y;
            J[1] = m[2] * x - m[0] * f;
            J[2] = m[0] * y - m[1] * x;
            J[3] = d[1] * f - d[2] * y;
            J[4] = d[2] * x - d[0] * f;
            J[5] = d[0] * y - d[1] * x;
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
        double dd[6], As[36], gs[6], x[6];
        for (int i = 0; i < 6; i++)
            dd[i] = sqrt(fmax(A[7 * i], 1e-12));
        for (int i = 0; i < 6; i++) {
            for (int j = 0; j < 6; j++)
                As[6 * i + j] = A[6 * i + j] / (dd[i] * dd[j]) + (i == j ? 1e-6 : 0.0);
            gs[i] = g[i] / dd[i];
        }
        if (!solve6(As, gs, x)) {
            code = 2;
            break;
        }
        double dxi[6], Rm[9], Hn[16];
        for (int i = 0; i < 6; i++)
            dxi[i] = -x[i] / dd[i];
        rotvec_R(dxi, Rm);
        for (int i = 0; i < 3; i++) {
            for (int j = 0; j < 4; j++)
                Hn[4 * i + j] = Rm[3 * i] * H[j] + Rm[3 * i + 1] * H[4 + j] + Rm[3 * i + 2] * H[8 + j] +
                                (j == 3 ? dxi[3 + i] : 0.0);
        }
        Hn[12] = Hn[13] = Hn[14] = 0.0;
        Hn[15] = 1.0;
        memcpy(H, Hn, sizeof H);
        double mr = fmax(fabs(dxi[0]), fmax(fabs(dxi[1]), fabs(dxi[2])));
        double mt = fmax(fabs(dxi[3]), fmax(fabs(dxi[4]), fabs(dxi[5])));
        if (fl <= floor_ && mr < 1e-7 && mt < 1e-5)
            break;
    }
    memcpy(Ho, H, sizeof H);
    PyMem_Free(work);
    bufs_release(&bs);
    return Py_BuildValue("(id)", code, sigma);
fail:
    PyMem_Free(work);
    bufs_release(&bs);
    return NULL;
}

/* The vote of silhouette._coarse_shift: votes[iy * G + ix] = how many samples have a candidate within tol
 * of n . (g[ix], g[iy]) (candidates NaN: none). */
static PyObject *py_vote(PyObject *self, PyObject *args)
{
    PyObject *o_off, *o_n, *o_g, *o_v;
    double tol;
    BufSet bs = {.n = 0};
    Py_buffer *b_off, *b_n, *b_g, *b_v;
    double *cand = NULL;
    if (!PyArg_ParseTuple(args, "OOOdO:vote", &o_off, &o_n, &o_g, &tol, &o_v))
        return NULL;
    GET(b_off, o_off, "off", T_F64, 0, 2, -1, -1);
    const Py_ssize_t S = b_off->shape[0], C = b_off->shape[1];
    GET(b_n, o_n, "nrm", T_F64, 0, 2, S, 2);
    GET(b_g, o_g, "g", T_F64, 0, 1, -1);
    const Py_ssize_t G = b_g->shape[0];
    GET(b_v, o_v, "votes", T_I64, 1, 1, G * G);
    if (!(tol >= 0.0) || G < 1 || G > 4096) {
        PyErr_SetString(PyExc_ValueError, "tol, g: expected tol >= 0 and 1..4096 grid values");
        goto fail;
    }
    const double *off = b_off->buf, *nrm = b_n->buf, *g = b_g->buf;
    int64_t *votes = b_v->buf;
    cand = PyMem_Malloc(sizeof(double) * (size_t)(C > 0 ? C : 1));
    if (!cand) {
        PyErr_NoMemory();
        goto fail;
    }
    for (Py_ssize_t i = 0; i < G * G; i++)
        votes[i] = 0;
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
    PyMem_Free(cand);
    bufs_release(&bs);
    Py_RETURN_NONE;
fail:
    PyMem_Free(cand);
    bufs_release(&bs);
    return NULL;
}

static PyMethodDef methods[] = {
    {"solve", py_solve, METH_VARARGS,
     "solve(q, pos, a_G, b_G, H, f, floor, iters, start_floor, H_out, w, r, pick, JtWJ) -> (code, sigma): "
     "the IRLS of silhouette._solve (code 0 done, 1 too few samples, 2 singular: run the reference)."},
    {"vote", py_vote, METH_VARARGS,
     "vote(off, nrm, g, tol, votes): the vote of silhouette._coarse_shift over the grid g x g."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef moddef = {
    PyModuleDef_HEAD_INIT, "_csil",
    "The model-based fingertip measurement's IRLS (see selfview/silhouette.py, the reference).",
    -1, methods, NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__csil(void)
{
    PyObject *m = PyModule_Create(&moddef);
    if (!m)
        return NULL;
    if (PyModule_AddIntConstant(m, "API", API_VERSION) < 0) {
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
