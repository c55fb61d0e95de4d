/* selfview._ctrack: the compiled kernels of the fingertip tracker's per-frame step
 * (selfview.tracking.FingertipTracker._track), and a few of the full search's (selfview.fingertips).
 *
 * The Python code in selfview/tracking.py is the reference: each kernel computes what a chain of numpy
 * calls there computes, in the same order of operations and the same precision (float32 where numpy
 * computes in float32), so that the tracked corners come out bit-identical on IEEE hardware. The
 * comments say which Python function each part follows (numpy's pairwise summation where numpy sums
 * that way, the C library's atan2/sin/cos for numpy's). What stays in Python: OpenCV's remap of the
 * coarse profiles, numpy's log of the peak fits (numpy's float32 log is not the C library's), the
 * camera model, the checks with their messages and the corners.
 *
 * Kernels (all arrays C-contiguous numpy arrays or other buffers; outputs preallocated by the caller):
 *   coarse_maps(pts, pd, sub, R, W, H, mx, my)                 the maps of _profiles_coarse
 *   coarse(prof1, sub, pts, eid, h, levels, crease, sr1, phase, W, H, R, lim, P, min_contrast,
 *          keep_fraction, ph)                                  -> None | (edge, n_ok, n_sub)
 *   fine(img, pts, pd, ph, eid, h, levels, crease, g, R, half, P, min_contrast, cand, est, logarg) -> G
 *   profiles(img, pts, pd, phase, R, out)                      _profiles (the sampling of fine, for the tests)
 *   finish(cand, est, lg, pts, pd, ph, eid, textured, cross, eid_out, Am, Bm)  -> K
 *   lines(q, gid, n_prev, c_prev, n, c, w)                     _robust_lines
 *   line_stats(q, gid, w, n, c, Am, Bm, n_in, levels, s_mean, s_ss, r_ss, s_in, ei)  -> Kin
 *   group_median(values, gid, n, out)                          _Groups.median
 * and three of the full search's (selfview.fingertips.find_fingertips, its Python code the reference):
 *   clear(st, others, pdir, R, margin, ok)                     the profiles clear of other edges (_edge_steps)
 *   search_profiles(img, st, pdir, ph, R, out)                 _edge_steps's bilinear profiles
 *   template_sums(Gn, q, n, out)                               _template_score's sums of one edge
 *
 * Every buffer is checked (type, number of dimensions, shape, lengths consistent with the others) and
 * every index into a buffer is checked before it is used: bad arguments raise TypeError or ValueError
 * naming the argument, never a read outside a buffer. Only the CPython C API (the buffer protocol), no
 * numpy headers. No contraction of a * b + c into a fused multiply-add (numpy rounds each operation).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#if defined(__clang__)
#pragma STDC FP_CONTRACT OFF
#elif defined(__GNUC__)
#pragma GCC optimize("fp-contract=off")
#endif

#define API_VERSION 2

/* sizes given as arguments (profile half-lengths, windows) beyond this are refused: no overflow */
#define MAX_SIZE ((Py_ssize_t)1 << 20)

/* ------------------------------------------------------------------------------------------------ */
/* buffers                                                                                          */

enum { T_F64 = 1, T_F32 = 2, T_U8 = 4, T_I64 = 8, T_BOOL = 16 };

#define MAXBUF 24

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

static int host_little(void)
{
    const uint16_t one = 1;
    return *(const unsigned char *)&one == 1;
}

/* The element type of a buffer (one of T_*), 0 for anything else. */
static int buf_kind(const Py_buffer *b)
{
    const char *f = b->format ? b->format : "B";
    if (*f == '@' || *f == '=')
        f++;
    else if (*f == '<' || *f == '>' || *f == '!') {
        if ((*f == '<') != host_little())
            return 0;
        f++;
    }
    if (f[0] == '\0' || f[1] != '\0')
        return 0;
    switch (f[0]) {
    case 'd': return b->itemsize == 8 ? T_F64 : 0;
    case 'f': return b->itemsize == 4 ? T_F32 : 0;
    case 'B': return b->itemsize == 1 ? T_U8 : 0;
    case '?': return b->itemsize == 1 ? T_BOOL : 0;
    case 'q': case 'l': case 'n': return b->itemsize == 8 ? T_I64 : 0;
    default: return 0;
    }
}

static const char *kinds_text(int kinds)
{
    switch (kinds) {
    case T_F64: return "float64";
    case T_F32: return "float32";
    case T_U8: return "uint8";
    case T_I64: return "int64";
    case T_BOOL: return "bool";
    case T_U8 | T_F32 | T_F64: return "uint8, float32 or float64";
    case T_F32 | T_F64: return "float32 or float64";
    default: return "another type";
    }
}

static void shape_text(char *out, size_t size, int ndim, const Py_ssize_t *shape)
{
    size_t k = 0;
    k += (size_t)PyOS_snprintf(out + k, size - k, "(");
    for (int i = 0; i < ndim && k < size; i++) {
        if (shape[i] < 0)
            k += (size_t)PyOS_snprintf(out + k, size - k, "%s", i ? ", any" : "any");
        else
            k += (size_t)PyOS_snprintf(out + k, size - k, i ? ", %zd" : "%zd", shape[i]);
    }
    if (k < size)
        PyOS_snprintf(out + k, size - k, ndim == 1 ? ",)" : ")");
}

/* The buffer of argument ``name``: C-contiguous, of one of the types ``kinds``, with ``ndim``
 * dimensions and the given shape (-1: any; ``at_least``: the first dimension may be larger, for
 * outputs with room for all rows). Kept in ``s`` for release; NULL with an exception set. */
static Py_buffer *get_buf(BufSet *s, PyObject *o, const char *name, int kinds, int writable, int ndim,
                          const Py_ssize_t *shape, int at_least)
{
    if (s->n >= MAXBUF) {
        PyErr_SetString(PyExc_RuntimeError, "_ctrack: too many buffers");
        return NULL;
    }
    Py_buffer *b = &s->v[s->n];
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(o, b, flags) < 0) {
        int is_buffer = PyObject_CheckBuffer(o);
        PyErr_Clear();
        if (!is_buffer)
            PyErr_Format(PyExc_TypeError, "%s: expected a %s array, got %.100s", name, kinds_text(kinds),
                         Py_TYPE(o)->tp_name);
        else
            PyErr_Format(PyExc_TypeError, "%s: expected a C-contiguous%s %s array", name,
                         writable ? ", writable" : "", kinds_text(kinds));
        return NULL;
    }
    s->n++;
    int k = buf_kind(b);
    if (!(k & kinds)) {
        PyErr_Format(PyExc_TypeError, "%s: expected a %s array, got elements of format '%s' (%zd bytes)", name,
                     kinds_text(kinds), b->format ? b->format : "B", b->itemsize);
        return NULL;
    }
    int bad = b->ndim != ndim;
    for (int i = 0; !bad && i < ndim; i++) {
        if (shape[i] < 0)
            continue;
        if ((i == 0 && at_least) ? b->shape[0] < shape[0] : b->shape[i] != shape[i])
            bad = 1;
    }
    if (bad) {
        char want[128], got[128];
        shape_text(want, sizeof want, ndim, shape);
        shape_text(got, sizeof got, b->ndim, b->shape ? b->shape : shape);
        if (b->ndim != ndim)
            PyErr_Format(PyExc_ValueError, "%s: expected a %d-D array of shape %s, got %d-D", name, ndim, want,
                         b->ndim);
        else
            PyErr_Format(PyExc_ValueError, "%s: expected shape %s%s, got %s", name, want,
                         at_least ? " (first dimension at least)" : "", got);
        return NULL;
    }
    return b;
}

#define GET(var, obj, name, kinds, wr, nd, ...)                                                          \
    do {                                                                                                 \
        const Py_ssize_t shp_[] = {__VA_ARGS__};                                                         \
        var = get_buf(&bs, obj, name, kinds, wr, nd, shp_, 0);                                           \
        if (!var)                                                                                        \
            goto fail;                                                                                   \
    } while (0)

#define GET_ROOM(var, obj, name, kinds, nd, ...)                                                         \
    do {                                                                                                 \
        const Py_ssize_t shp_[] = {__VA_ARGS__};                                                         \
        var = get_buf(&bs, obj, name, kinds, 1, nd, shp_, 1);                                            \
        if (!var)                                                                                        \
            goto fail;                                                                                   \
    } while (0)

/* ------------------------------------------------------------------------------------------------ */
/* numpy's scalar semantics                                                                         */

/* np.maximum(a, b) for floats: NaN in either propagates */
static inline double np_max(double a, double b) { return (a >= b || a != a) ? a : b; }

/* np.clip(x, lo, hi) for floats (numpy's _NPY_CLIP: min(max(x, lo), hi), NaN propagates) */
static inline double np_clip(double x, double lo, double hi)
{
    double t = (x != x) ? x : (x > lo ? x : lo);
    return (t != t) ? t : (t < hi ? t : hi);
}

/* np.sign for floats */
static inline double np_sign(double x) { return x > 0 ? 1.0 : x < 0 ? -1.0 : x == 0 ? 0.0 : x; }

/* The result of a float32 operation when ``f32`` (its operands float32 values held in doubles: one
 * rounding of the exact double result to float32 is the float32 operation's result, since double has
 * more than 2 * 24 + 2 bits), else the double. */
static inline double rnd(double x, int f32) { return f32 ? (double)(float)x : x; }

/* One element of buffer ``b`` (its kind ``k``) as a double. */
static inline double elem(const void *p, int k, Py_ssize_t i)
{
    switch (k) {
    case T_U8: return (double)((const unsigned char *)p)[i];
    case T_F32: return (double)((const float *)p)[i];
    default: return ((const double *)p)[i];
    }
}

static inline void store(void *p, int k, Py_ssize_t i, double v)
{
    if (k == T_F32)
        ((float *)p)[i] = (float)v;
    else
        ((double *)p)[i] = v;
}

static int cmp_double(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

/* The k-th smallest of a[0..n-1] (a reordered: a[i] <= a[k] for i < k, a[i] >= a[k] for i > k);
 * Wirth's selection. No NaN in a. */
static double select_kth(double *a, Py_ssize_t n, Py_ssize_t k)
{
    Py_ssize_t l = 0, m = n - 1;
    while (l < m) {
        double x = a[k];
        Py_ssize_t i = l, j = m;
        do {
            while (a[i] < x)
                i++;
            while (x < a[j])
                j--;
            if (i <= j) {
                double t = a[i];
                a[i] = a[j];
                a[j] = t;
                i++;
                j--;
            }
        } while (i <= j);
        if (j < k)
            l = i;
        if (k < i)
            m = j;
    }
    return a[k];
}

/* tracking._Groups.median: the median of ``values`` (K,) in each of the groups 0..n-1 given by
 * ``gid`` (K,), sorted (each group's values consecutive, ``starts`` (n + 1,) their bounds), NaN for an
 * empty group. Computed as the Python computes it: every value shifted by gid * span (span: the
 * values' whole spread + 1), the two middle values of each group averaged and the shift taken off
 * again. The groups' shifted values do not mix, so each group's are selected on their own; same
 * result as the global sort. Non-finite values: NaN for every group. ``scratch``: K doubles. */
static void trick_median(const double *values, const Py_ssize_t *starts, Py_ssize_t n, double *out, double *scratch)
{
    Py_ssize_t K = starts[n];
    if (K == 0) {
        for (Py_ssize_t g = 0; g < n; g++)
            out[g] = NAN;
        return;
    }
    double vmax = values[0], vmin = values[0];
    int nan = 0;
    for (Py_ssize_t j = 0; j < K; j++) {
        double v = values[j];
        if (v != v)
            nan = 1;
        if (v > vmax)
            vmax = v;
        if (v < vmin)
            vmin = v;
    }
    double span = (vmax - vmin) + 1.0;
    if (nan || !isfinite(span)) {
        for (Py_ssize_t g = 0; g < n; g++)
            out[g] = NAN;
        return;
    }
    for (Py_ssize_t g = 0; g < n; g++) {
        Py_ssize_t a = starts[g], cnt = starts[g + 1] - a;
        if (cnt == 0) {
            out[g] = NAN;
            continue;
        }
        double shift = (double)g * span;
        for (Py_ssize_t j = 0; j < cnt; j++)
            scratch[j] = values[a + j] + shift;
        Py_ssize_t lo = (cnt - 1) / 2, hi = cnt / 2;
        double vlo, vhi;
        if (cnt <= 24) {
            qsort(scratch, (size_t)cnt, sizeof(double), cmp_double);
            vlo = scratch[lo];
            vhi = scratch[hi];
        } else {
            vlo = select_kth(scratch, cnt, lo);
            vhi = vlo;
            if (hi != lo) {
                vhi = scratch[hi];
                for (Py_ssize_t j = hi + 1; j < cnt; j++)
                    if (scratch[j] < vhi)
                        vhi = scratch[j];
            }
        }
        out[g] = 0.5 * (vlo + vhi) - shift;
    }
}

/* The bounds starts (n + 1,) of the groups gid (K,): -1 with ValueError naming ``name`` when gid is
 * not sorted or not within 0..n-1 (or, with ``need_all``, a group is empty). */
static int group_bounds(const int64_t *gid, Py_ssize_t K, Py_ssize_t n, Py_ssize_t *starts, const char *name,
                        int need_all)
{
    int64_t prev = 0;
    Py_ssize_t g = 0;
    starts[0] = 0;
    for (Py_ssize_t j = 0; j < K; j++) {
        int64_t v = gid[j];
        if (v < 0 || v >= (int64_t)n) {
            PyErr_Format(PyExc_ValueError, "%s: group index %lld at position %zd is not within 0..%zd", name,
                         (long long)v, j, n - 1);
            return -1;
        }
        if (v < prev) {
            PyErr_Format(PyExc_ValueError, "%s: expected sorted group indices, %lld follows %lld at position %zd",
                         name, (long long)v, (long long)prev, j);
            return -1;
        }
        while (g < (Py_ssize_t)v)
            starts[++g] = j;
        prev = v;
    }
    while (g < n)
        starts[++g] = K;
    if (need_all)
        for (g = 0; g < n; g++)
            if (starts[g + 1] == starts[g]) {
                PyErr_Format(PyExc_ValueError, "%s: group %zd has no points", name, g);
                return -1;
            }
    return 0;
}

static int check_index(const int64_t *idx, Py_ssize_t n, Py_ssize_t lim, const char *name)
{
    for (Py_ssize_t i = 0; i < n; i++)
        if (idx[i] < 0 || idx[i] >= (int64_t)lim) {
            PyErr_Format(PyExc_ValueError, "%s: index %lld at position %zd is not within 0..%zd", name,
                         (long long)idx[i], i, lim - 1);
            return -1;
        }
    return 0;
}

static void *alloc(size_t n, size_t size)
{
    void *p = calloc(n ? n : 1, size);
    if (!p)
        PyErr_NoMemory();
    return p;
}

/* ------------------------------------------------------------------------------------------------ */
/* per-profile parameters (tracking._Rows: each row's edge parameters)                              */

typedef struct {
    Py_ssize_t h;
    double exp_hi, exp_lo, tol, contrast0, g_lo, g_hi;
} RowPar;

static void row_par(RowPar *p, Py_ssize_t e, const int64_t *h, const double *levels, const unsigned char *crease,
                    const double *g)
{
    double lo = levels[2 * e], hi = levels[2 * e + 1];
    p->h = (Py_ssize_t)h[e];
    p->exp_hi = hi;                                /* levels[eid, 1] */
    p->exp_lo = crease[e] ? lo : NAN;              /* np.where(crease, levels[:, 0], nan)[eid] */
    p->contrast0 = fabs(hi - lo);                  /* np.abs(levels[:, 1] - levels[:, 0])[eid] */
    p->tol = np_max(15.0, 0.3 * p->contrast0);     /* np.maximum(15.0, 0.3 * contrast0) */
    p->g_lo = g ? g[2 * e] : 0.0;
    p->g_hi = g ? g[2 * e + 1] : 0.0;
}

/* Whether profiles of 2R + 1 samples hold every sample the candidates (start, width) and, with
 * ``windows``, the step windows of an edge with half-width h read; else ValueError. */
static int check_reach(Py_ssize_t R, Py_ssize_t start, Py_ssize_t width, int64_t h64, Py_ssize_t P, int windows,
                       Py_ssize_t e)
{
    Py_ssize_t L = 2 * R + 1, c0 = start + R;
    if (h64 < 0 || h64 > (int64_t)R) {
        PyErr_Format(PyExc_ValueError, "h: profiles of 2R+1 = %zd samples are too short for edge %zd (h=%lld)", L, e,
                     (long long)h64);
        return -1;
    }
    Py_ssize_t h = (Py_ssize_t)h64;
    int ok = width >= 1 && c0 - h - P / 2 >= 0 && c0 + width - 1 + h + 1 + P / 2 <= L - 1;
    if (ok && windows) /* ws = at + R - h - P + 1 .. ws + 2 (h + P) over at in start..start + width - 1 */
        ok = start + R - h - P + 1 >= 0 && start + width - 1 + R - h - P + 1 + 2 * (h + P) <= L;
    if (!ok) {
        PyErr_Format(PyExc_ValueError,
                     "h: profiles of 2R+1 = %zd samples are too short for edge %zd (h=%zd, plateau %zd, steps %zd..%zd)",
                     L, e, h, P, start, start + width - 1);
        return -1;
    }
    return 0;
}

/* tracking._candidates for one profile ``pv`` (its 2R + 1 values; ``f32``: a float32 profile, whose
 * differences numpy rounds to float32): the strongest allowed step among the positions start ..
 * start + width - 1. Returns its column k; ``diff`` (width,) the differences, ``*ok`` whether it is
 * allowed (score >= 0). np.argmax: the first maximum, or the first NaN. */
static Py_ssize_t candidates(const double *pv, Py_ssize_t R, Py_ssize_t start, Py_ssize_t width, const RowPar *p,
                             Py_ssize_t P, int f32, double *diff, int *ok)
{
    Py_ssize_t c0 = start + R, k = 0;
    double best = 0.0;
    for (Py_ssize_t i = 0; i < width; i++) {
        double d = rnd(pv[c0 + i + 1] - pv[c0 + i], f32);
        diff[i] = d;
        double hi_side = pv[c0 + i + p->h + 1 + P / 2];
        double lo_side = pv[c0 + i - p->h - P / 2];
        int allowed = fabs(hi_side - p->exp_hi) <= p->tol;
        if (fabs(lo_side - p->exp_lo) > p->tol) /* NaN: no expectation */
            allowed = 0;
        double s = allowed ? fabs(d) : -1.0;
        if (i == 0) {
            best = s;
        } else if (best == best && (s > best || s != s)) {
            best = s;
            k = i;
        }
    }
    *ok = best >= 0.0;
    return k;
}

/* ------------------------------------------------------------------------------------------------ */
/* coarse_maps: the maps of tracking._profiles_coarse(img, pts_in[sub], pd[sub], R), with pts_in =  */
/* np.clip(pts, R + 1, edge_lim - R - 1.001) as _track clips them                                    */

static PyObject *py_coarse_maps(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o_pts, *o_pd, *o_sub, *o_mx, *o_my;
    Py_ssize_t R, W, H;
    BufSet bs = {.n = 0};
    Py_buffer *b_pts, *b_pd, *b_sub, *b_mx, *b_my;
    if (!PyArg_ParseTuple(args, "OOOnnnOO:coarse_maps", &o_pts, &o_pd, &o_sub, &R, &W, &H, &o_mx, &o_my))
        return NULL;
    if (R < 1 || W < 2 || H < 2 || R > MAX_SIZE) {
        PyErr_Format(PyExc_ValueError, "R, W, H: expected 1 <= R <= 2**20 and a picture of at least 2x2, got %zd, %zd, %zd",
                     R, W, H);
        return NULL;
    }
    GET(b_pts, o_pts, "pts", T_F64, 0, 2, -1, 2);
    Py_ssize_t M = b_pts->shape[0];
    GET(b_pd, o_pd, "pd", T_F64, 0, 2, M, 2);
    GET(b_sub, o_sub, "sub", T_I64, 0, 1, -1);
    Py_ssize_t m = b_sub->shape[0], L = 2 * R + 1;
    GET(b_mx, o_mx, "mx", T_F32, 1, 2, m, L);
    GET(b_my, o_my, "my", T_F32, 1, 2, m, L);
    const double *pts = b_pts->buf, *pd = b_pd->buf;
    const int64_t *sub = b_sub->buf;
    float *mx = b_mx->buf, *my = b_my->buf;
    if (check_index(sub, m, M, "sub") < 0)
        goto fail;
    double lo = (double)(R + 1);
    double hi_x = ((double)W - 1.0 - (double)R) - 1.001, hi_y = ((double)H - 1.0 - (double)R) - 1.001;
    for (Py_ssize_t i = 0; i < m; i++) {
        Py_ssize_t r = (Py_ssize_t)sub[i];
        /* pts_in[sub].astype(float32) + off * pd[sub].astype(float32), off = arange(-R, R + 1, float32) */
        float x = (float)np_clip(pts[2 * r], lo, hi_x), y = (float)np_clip(pts[2 * r + 1], lo, hi_y);
        float dx = (float)pd[2 * r], dy = (float)pd[2 * r + 1];
        for (Py_ssize_t j = 0; j < L; j++) {
            float off = (float)(j - R);
            float ox = off * dx, oy = off * dy;
            mx[i * L + j] = x + ox;
            my[i * L + j] = y + oy;
        }
    }
    bufs_release(&bs);
    Py_RETURN_NONE;
fail:
    bufs_release(&bs);
    return NULL;
}

/* ------------------------------------------------------------------------------------------------ */
/* coarse: step 2 of _track after the remap: on every profile of ``sub``, _candidates over -lim ..   */
/* lim - 1, the tests, the count per edge, the "shows a step in only" check, the median offset per   */
/* edge (_group_median of at + 0.5) and the phases of the second pass, ph = phase + offset[eid].     */

static PyObject *py_coarse(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o_prof, *o_sub, *o_pts, *o_eid, *o_h, *o_lev, *o_crease, *o_sr1, *o_phase, *o_ph;
    Py_ssize_t W, H, R, lim, P;
    double min_contrast, keep;
    BufSet bs = {.n = 0};
    Py_buffer *b_prof, *b_sub, *b_pts, *b_eid, *b_h, *b_lev, *b_crease, *b_sr1, *b_phase, *b_ph;
    double *pv = NULL, *diff = NULL, *vals = NULL, *scratch = NULL, *med = NULL;
    Py_ssize_t *n_ok = NULL, *n_sub = NULL, *starts = NULL;
    PyObject *result = NULL;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOnnnnnddO:coarse", &o_prof, &o_sub, &o_pts, &o_eid, &o_h, &o_lev,
                          &o_crease, &o_sr1, &o_phase, &W, &H, &R, &lim, &P, &min_contrast, &keep, &o_ph))
        return NULL;
    if (R < 1 || lim < 1 || P < 1 || W < 2 || H < 2 || R > MAX_SIZE || lim > MAX_SIZE || P > MAX_SIZE) {
        PyErr_Format(PyExc_ValueError, "R, lim, P, W, H: expected positive sizes (up to 2**20), got %zd, %zd, %zd, %zd, %zd", R,
                     lim, P, W, H);
        return NULL;
    }
    Py_ssize_t L = 2 * R + 1;
    GET(b_prof, o_prof, "prof1", T_U8 | T_F32 | T_F64, 0, 2, -1, L);
    Py_ssize_t m = b_prof->shape[0];
    GET(b_sub, o_sub, "sub", T_I64, 0, 1, m);
    GET(b_pts, o_pts, "pts", T_F64, 0, 2, -1, 2);
    Py_ssize_t M = b_pts->shape[0];
    GET(b_eid, o_eid, "eid", T_I64, 0, 1, M);
    GET(b_h, o_h, "h", T_I64, 0, 1, -1);
    Py_ssize_t E = b_h->shape[0];
    GET(b_lev, o_lev, "levels", T_F64, 0, 2, E, 2);
    GET(b_crease, o_crease, "crease", T_BOOL, 0, 1, E);
    GET(b_sr1, o_sr1, "sr1", T_F64, 0, 1, M);
    GET(b_phase, o_phase, "phase", T_F64, 0, 1, M);
    GET(b_ph, o_ph, "ph", T_F64, 1, 1, M);
    const int kp = buf_kind(b_prof);
    const void *prof = b_prof->buf;
    const int64_t *sub = b_sub->buf, *eid = b_eid->buf, *h = b_h->buf;
    const double *pts = b_pts->buf, *levels = b_lev->buf, *sr1 = b_sr1->buf, *phase = b_phase->buf;
    const unsigned char *crease = b_crease->buf;
    double *ph = b_ph->buf;
    if (check_index(sub, m, M, "sub") < 0)
        goto fail;
    for (Py_ssize_t i = 1; i < m; i++)
        if (sub[i] <= sub[i - 1]) {
            PyErr_Format(PyExc_ValueError, "sub: expected increasing row indices, %lld follows %lld",
                         (long long)sub[i], (long long)sub[i - 1]);
            goto fail;
        }
    if (!(starts = alloc((size_t)E + 1, sizeof(Py_ssize_t))))
        goto fail;
    if (group_bounds(eid, M, E, starts, "eid", 0) < 0)
        goto fail;
    for (Py_ssize_t e = 0; e < E; e++)
        if (check_reach(R, -lim, 2 * lim, h[e], P, 0, e) < 0)
            goto fail;
    if (!(pv = alloc((size_t)L, sizeof(double))) || !(diff = alloc((size_t)(2 * lim), sizeof(double))) ||
        !(vals = alloc((size_t)m, sizeof(double))) || !(scratch = alloc((size_t)m, sizeof(double))) ||
        !(med = alloc((size_t)E, sizeof(double))) || !(n_ok = alloc((size_t)E, sizeof(Py_ssize_t))) ||
        !(n_sub = alloc((size_t)E, sizeof(Py_ssize_t))))
        goto fail;
    const double lim_x = (double)W - 1.0, lim_y = (double)H - 1.0;
    /* the ok rows' values at + 0.5 come in the order of their edges (sub increasing, eid sorted): their
     * group bounds, counted as they come */
    Py_ssize_t nv = 0;
    for (Py_ssize_t i = 0; i < m; i++) {
        Py_ssize_t r = (Py_ssize_t)sub[i], e = (Py_ssize_t)eid[r];
        RowPar p;
        row_par(&p, e, h, levels, crease, NULL);
        double px = pts[2 * r], py = pts[2 * r + 1];
        /* inside = np.all((pts - R - 1 >= 0) & (pts + R + 1 < edge_lim), axis=1) */
        int inside = (px - (double)R) - 1.0 >= 0 && (py - (double)R) - 1.0 >= 0 && (px + (double)R) + 1.0 < lim_x &&
                     (py + (double)R) + 1.0 < lim_y;
        for (Py_ssize_t j = 0; j < L; j++) /* .astype(np.float32) */
            pv[j] = (double)(float)elem(prof, kp, i * L + j);
        int ok;
        Py_ssize_t k = candidates(pv, R, -lim, 2 * lim, &p, P, 1, diff, &ok);
        Py_ssize_t at = -lim + k;
        double peak = diff[k];
        /* ok &= (|at + 0.5| <= sr1[sub]) & (|peak| >= MIN_CONTRAST) & inside[sub] */
        ok = ok && fabs((double)at + 0.5) <= sr1[r] && fabs(peak) >= min_contrast && inside;
        n_sub[e] += inside;
        if (ok) {
            n_ok[e]++;
            vals[nv++] = (double)at + 0.5;
        }
    }
    /* located = n_sub >= 3; short = located & (n_ok < np.maximum(3, KEEP_FRACTION * n_sub)) */
    for (Py_ssize_t e = 0; e < E; e++)
        if (n_sub[e] >= 3 && (double)n_ok[e] < np_max(3.0, keep * (double)n_sub[e])) {
            result = Py_BuildValue("(nnn)", e, n_ok[e], n_sub[e]);
            goto done;
        }
    /* offset = np.where(located, _group_median(at[ok] + 0.5, e1[ok], E), 0.0) */
    starts[0] = 0;
    for (Py_ssize_t e = 0; e < E; e++)
        starts[e + 1] = starts[e] + n_ok[e];
    trick_median(vals, starts, E, med, scratch);
    for (Py_ssize_t e = 0; e < E; e++)
        if (n_sub[e] < 3)
            med[e] = 0.0;
    for (Py_ssize_t r = 0; r < M; r++)
        ph[r] = phase[r] + med[eid[r]];
    result = Py_None;
    Py_INCREF(result);
done:
fail:
    free(pv);
    free(diff);
    free(vals);
    free(scratch);
    free(med);
    free(n_ok);
    free(n_sub);
    free(starts);
    bufs_release(&bs);
    return result;
}

/* ------------------------------------------------------------------------------------------------ */
/* fine: step 3 of _track up to the logarithms: per profile, _profiles (the bilinear samples exactly */
/* as numpy computes them, single precision for uint8 and float32 pictures), the running sums (as    */
/* np.cumsum), _candidates, _steps and _step_estimates' area estimate, and every acceptance test of  */
/* _steps but the peak's. The rows that pass go to ``cand`` (row), ``est`` (e, Am, Bm, at, the peak's */
/* sample at + (kk - k)), ``logarg`` (the three arguments of the peak fit's log, in the profiles'    */
/* precision: float32, or float64 for a float64 picture). Returns their number G.                   */

typedef struct {
    int kind, f32;
    const void *p;
    Py_ssize_t W, H;
} Img;

/* _profiles for one row: 2R + 1 bilinear samples at (cx, cy) + (j + ph) (dx, dy), j = -R..R, as
 * numpy computes them: positions in float64, fx, fy cast to float32, v00 and v10 cast to float32 and
 * the interpolation in float32 for a uint8 or float32 picture (v01, v11 stay float64 for a float64 one,
 * and the sums with them). Returns -1, or the sample (at *bad_x, *bad_y) that would read outside the
 * picture (its four pixels must lie inside: 0 <= x < W - 1, 0 <= y < H - 1; NaN fails). */
#define SAMPLE_ROW(PIX, VT, LOAD_LO, LOAD_HI)                                                              \
    do {                                                                                                 \
        const PIX *a = im->p;                                                                            \
        for (Py_ssize_t j = 0; j < L; j++) {                                                             \
            double off = (double)(j - R) + ph; /* np.arange(-R, R + 1, dtype=float64) + phase */         \
            double ox = off * dx, oy = off * dy;                                                         \
            double x = cx + ox, y = cy + oy;                                                             \
            if (!(x >= 0.0 && y >= 0.0 && x < wlim && y < hlim)) {                                       \
                *bad_x = x;                                                                              \
                *bad_y = y;                                                                              \
                return j;                                                                                \
            }                                                                                            \
            /* np.floor: for 0 <= x < W - 1 the truncation (no libm call) */                             \
            const Py_ssize_t ix = (Py_ssize_t)x, iy = (Py_ssize_t)y;                                     \
            const VT fx = (VT)(float)(x - (double)ix), fy = (VT)(float)(y - (double)iy);                 \
            const Py_ssize_t i00 = iy * W + ix;                                                          \
            const VT v00 = LOAD_LO(a[i00]), v01 = LOAD_HI(a[i00 + 1]);                                   \
            const VT v10 = LOAD_LO(a[i00 + W]), v11 = LOAD_HI(a[i00 + W + 1]);                           \
            const VT top = v00 + (v01 - v00) * fx;                                                       \
            const VT bot = v10 + (v11 - v10) * fx;                                                       \
            pv[j] = (double)(top + (bot - top) * fy);                                                    \
        }                                                                                                \
    } while (0)

#define AS_FLOAT(v) ((float)(v))
#define AS_DOUBLE(v) ((double)(v))
#define VIA_FLOAT(v) ((double)(float)(v))

static Py_ssize_t sample_row(const Img *im, double cx, double cy, double dx, double dy, double ph, Py_ssize_t R,
                             double *pv, double *bad_x, double *bad_y)
{
    const Py_ssize_t W = im->W, L = 2 * R + 1;
    const double wlim = (double)(W - 1), hlim = (double)(im->H - 1);
    if (im->kind == T_U8)
        SAMPLE_ROW(unsigned char, float, AS_FLOAT, AS_FLOAT);
    else if (im->kind == T_F32)
        SAMPLE_ROW(float, float, AS_FLOAT, AS_FLOAT);
    else /* numpy: v00, v10 cast to float32, v01, v11 float64: the sums in float64 */
        SAMPLE_ROW(double, double, VIA_FLOAT, AS_DOUBLE);
    return -1;
}

/* np.ptp of pv[a..a + n - 1] in the profiles' precision (NaN propagates) */
static double ptp(const double *pv, Py_ssize_t a, Py_ssize_t n, int f32)
{
    double mx = pv[a], mn = pv[a];
    for (Py_ssize_t i = 1; i < n; i++) {
        double v = pv[a + i];
        if (v != v)
            return v;
        if (v > mx)
            mx = v;
        if (v < mn)
            mn = v;
    }
    if (mx != mx)
        return mx;
    return rnd(mx - mn, f32);
}

static PyObject *py_fine(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o_img, *o_pts, *o_pd, *o_ph, *o_eid, *o_h, *o_lev, *o_crease, *o_g, *o_cand, *o_est, *o_logarg;
    Py_ssize_t R, half, P;
    double min_contrast;
    BufSet bs = {.n = 0};
    Py_buffer *b_img, *b_pts, *b_pd, *b_ph, *b_eid, *b_h, *b_lev, *b_crease, *b_g, *b_cand, *b_est, *b_logarg;
    double *pv = NULL, *cs = NULL, *diff = NULL;
    PyObject *result = NULL;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOnnndOOO:fine", &o_img, &o_pts, &o_pd, &o_ph, &o_eid, &o_h, &o_lev,
                          &o_crease, &o_g, &R, &half, &P, &min_contrast, &o_cand, &o_est, &o_logarg))
        return NULL;
    if (R < 1 || half < 2 || P < 1 || R > MAX_SIZE || half > MAX_SIZE || P > MAX_SIZE) {
        PyErr_Format(PyExc_ValueError, "R, half, P: expected R >= 1, half >= 2, P >= 1 (up to 2**20), got %zd, %zd, %zd", R, half,
                     P);
        return NULL;
    }
    GET(b_img, o_img, "img", T_U8 | T_F32 | T_F64, 0, 2, -1, -1);
    if (b_img->shape[0] < 2 || b_img->shape[1] < 2) {
        PyErr_Format(PyExc_ValueError, "img: expected a picture of at least 2x2 pixels, got %zdx%zd", b_img->shape[1],
                     b_img->shape[0]);
        goto fail;
    }
    GET(b_pts, o_pts, "pts", T_F64, 0, 2, -1, 2);
    Py_ssize_t M = b_pts->shape[0];
    GET(b_pd, o_pd, "pd", T_F64, 0, 2, M, 2);
    GET(b_ph, o_ph, "ph", T_F64, 0, 1, M);
    GET(b_eid, o_eid, "eid", T_I64, 0, 1, M);
    GET(b_h, o_h, "h", T_I64, 0, 1, -1);
    Py_ssize_t E = b_h->shape[0];
    GET(b_lev, o_lev, "levels", T_F64, 0, 2, E, 2);
    GET(b_crease, o_crease, "crease", T_BOOL, 0, 1, E);
    GET(b_g, o_g, "g", T_F64, 0, 2, E, 2);
    Img im = {buf_kind(b_img), buf_kind(b_img) != T_F64, b_img->buf, b_img->shape[1], b_img->shape[0]};
    const int kp = im.f32 ? T_F32 : T_F64; /* the profiles' precision */
    GET_ROOM(b_cand, o_cand, "cand", T_I64, 1, M);
    GET_ROOM(b_est, o_est, "est", T_F64, 2, M, 5);
    GET_ROOM(b_logarg, o_logarg, "logarg", kp, 2, M, 3);
    const double *pts = b_pts->buf, *pd = b_pd->buf, *phs = b_ph->buf, *levels = b_lev->buf, *gg = b_g->buf;
    const int64_t *eid = b_eid->buf, *h = b_h->buf;
    const unsigned char *crease = b_crease->buf;
    int64_t *cand = b_cand->buf;
    double *est = b_est->buf;
    void *logarg = b_logarg->buf;
    const int f32 = im.f32;
    if (check_index(eid, M, E, "eid") < 0)
        goto fail;
    for (Py_ssize_t e = 0; e < E; e++)
        if (check_reach(R, -half, 2 * half, h[e], P, 1, e) < 0)
            goto fail;
    const Py_ssize_t L = 2 * R + 1, D = 2 * half;
    if (!(pv = alloc((size_t)L, sizeof(double))) || !(cs = alloc((size_t)L + 1, sizeof(double))) ||
        !(diff = alloc((size_t)D, sizeof(double))))
        goto fail;
    const double lim_x = (double)im.W - 1.0, lim_y = (double)im.H - 1.0;
    const double floor_peak = rnd(1e-3, f32); /* np.maximum(..., 1e-3) in the profiles' precision */
    Py_ssize_t G = 0;
    for (Py_ssize_t r = 0; r < M; r++) {
        Py_ssize_t e = (Py_ssize_t)eid[r];
        RowPar p;
        row_par(&p, e, h, levels, crease, gg);
        const Py_ssize_t hh = p.h;
        double px = pts[2 * r], py = pts[2 * r + 1], phr = phs[r];
        /* reach = R2 + |ph| + 1; inside = all((pts - reach >= 0) & (pts + reach < edge_lim));
         * the profile sampled at np.clip(pts, reach, edge_lim - reach - 0.001) */
        double reach = ((double)R + fabs(phr)) + 1.0;
        int inside = px - reach >= 0 && py - reach >= 0 && px + reach < lim_x && py + reach < lim_y;
        double cx = np_clip(px, reach, (lim_x - reach) - 0.001), cy = np_clip(py, reach, (lim_y - reach) - 0.001);
        double bx = 0, by = 0;
        Py_ssize_t bad = sample_row(&im, cx, cy, pd[2 * r], pd[2 * r + 1], phr, R, pv, &bx, &by);
        if (bad >= 0) {
            char where[96];
            PyOS_snprintf(where, sizeof where, "(%.3f, %.3f)", bx, by);
            PyErr_Format(PyExc_ValueError,
                         "pts, pd, ph: sample %zd of profile %zd lies at %s, outside the %zdx%zd picture", bad, r,
                         where, im.W, im.H);
            goto fail;
        }
        /* cs = np.cumsum(prof, axis=1, dtype=float64) after a 0 */
        cs[0] = 0.0;
        for (Py_ssize_t j = 0; j < L; j++)
            cs[j + 1] = cs[j] + pv[j];
        /* _steps: _candidates within half samples of the middle */
        int ok;
        Py_ssize_t k = candidates(pv, R, -half, D, &p, P, f32, diff, &ok);
        if (!ok || !inside)
            continue;
        Py_ssize_t at = -half + k;
        double peak = diff[k], sgn = np_sign(peak);
        Py_ssize_t ws = at + R - hh - P + 1;
        double Am = (cs[ws + P] - cs[ws]) / (double)P;
        double S = cs[ws + P + 2 * hh] - cs[ws + P];
        double Bm = (cs[ws + 2 * hh + 2 * P] - cs[ws + 2 * hh + P]) / (double)P;
        double x_lo = (double)(at - hh) + 0.5, x_hi = (double)(at + hh) + 0.5;
        double x_A = x_lo - (double)P / 2.0, x_B = x_hi + (double)P / 2.0;
        /* _step_estimates: the area estimate, three Newton steps */
        double e_ = (double)at + 0.5;
        for (int it = 0; it < 3; it++) {
            double Ae = Am - p.g_lo * (x_A - e_);
            double Be = Bm - p.g_hi * (x_B - e_);
            double u = e_ - x_lo, v = x_hi - e_;
            double F = Ae * u - p.g_lo * (u * u) / 2 + Be * v + p.g_hi * (v * v) / 2 - S;
            e_ = e_ - F / (Ae - Be);
        }
        /* the acceptance tests of _steps (all but the peak's) */
        double contrast = fabs(Bm - Am);
        double rough = np_max(ptp(pv, ws, P, f32), ptp(pv, ws + 2 * hh + P, P, f32));
        double slope_allow = (fabs(p.g_lo) + fabs(p.g_hi)) * (double)P;
        double whole = ptp(pv, ws, 2 * (hh + P), f32);
        int good = (Bm - Am) * sgn >= np_max(min_contrast, 0.35 * p.contrast0) && fabs(Bm - p.exp_hi) <= p.tol &&
                   !(fabs(Am - p.exp_lo) > p.tol) && rough <= 0.08 * contrast + 8 + slope_allow &&
                   whole <= 1.15 * contrast + 10 + slope_allow && fabs(e_ - ((double)at + 0.5)) < 1.5 &&
                   rnd(peak * sgn, f32) > 0;
        if (!good)
            continue;
        /* _step_estimates, the peak: kk = clip(k, 1, D - 2), np.maximum(diff[kk + i] * sgn, 1e-3) */
        Py_ssize_t kk = k < 1 ? 1 : k > D - 2 ? D - 2 : k;
        cand[G] = r;
        est[5 * G + 0] = e_;
        est[5 * G + 1] = Am;
        est[5 * G + 2] = Bm;
        est[5 * G + 3] = (double)at;
        est[5 * G + 4] = (double)(at + (kk - k));
        for (int i = 0; i < 3; i++)
            store(logarg, kp, 3 * G + i, np_max(rnd(diff[kk - 1 + i] * sgn, f32), floor_peak));
        G++;
    }
    result = PyLong_FromSsize_t(G);
fail:
    free(pv);
    free(cs);
    free(diff);
    bufs_release(&bs);
    return result;
}

/* profiles: tracking._profiles(img, pts, pd, phase, R) into ``out`` (M, 2R + 1): float32 for a uint8
 * or float32 picture, float64 for a float64 one. The positions are used as given (no clipping): one
 * whose samples would read outside the picture raises ValueError. */
static PyObject *py_profiles(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o_img, *o_pts, *o_pd, *o_ph, *o_out;
    Py_ssize_t R;
    BufSet bs = {.n = 0};
    Py_buffer *b_img, *b_pts, *b_pd, *b_ph, *b_out;
    double *pv = NULL;
    PyObject *result = NULL;
    if (!PyArg_ParseTuple(args, "OOOOnO:profiles", &o_img, &o_pts, &o_pd, &o_ph, &R, &o_out))
        return NULL;
    if (R < 0 || R > MAX_SIZE) {
        PyErr_Format(PyExc_ValueError, "R: expected 0 <= R <= 2**20, got %zd", R);
        return NULL;
    }
    GET(b_img, o_img, "img", T_U8 | T_F32 | T_F64, 0, 2, -1, -1);
    GET(b_pts, o_pts, "pts", T_F64, 0, 2, -1, 2);
    Py_ssize_t M = b_pts->shape[0], L = 2 * R + 1;
    GET(b_pd, o_pd, "pd", T_F64, 0, 2, M, 2);
    GET(b_ph, o_ph, "phase", T_F64, 0, 1, M);
    Img im = {buf_kind(b_img), buf_kind(b_img) != T_F64, b_img->buf, b_img->shape[1], b_img->shape[0]};
    const int kp = im.f32 ? T_F32 : T_F64;
    GET(b_out, o_out, "out", kp, 1, 2, M, L);
    const double *pts = b_pts->buf, *pd = b_pd->buf, *ph = b_ph->buf;
    if (!(pv = alloc((size_t)L, sizeof(double))))
        goto fail;
    for (Py_ssize_t r = 0; r < M; r++) {
        double bx = 0, by = 0;
        Py_ssize_t bad = sample_row(&im, pts[2 * r], pts[2 * r + 1], pd[2 * r], pd[2 * r + 1], ph[r], R, pv, &bx, &by);
        if (bad >= 0) {
            char where[96];
            PyOS_snprintf(where, sizeof where, "(%.3f, %.3f)", bx, by);
            PyErr_Format(PyExc_ValueError,
                         "pts, pd, phase: sample %zd of profile %zd lies at %s, outside the %zdx%zd picture", bad, r,
                         where, im.W, im.H);
            goto fail;
        }
        for (Py_ssize_t j = 0; j < L; j++)
            store(b_out->buf, kp, r * L + j, pv[j]);
    }
    result = Py_None;
    Py_INCREF(result);
fail:
    free(pv);
    bufs_release(&bs);
    return result;
}

/* ------------------------------------------------------------------------------------------------ */
/* finish: the rest of _step_estimates (the peak of the rise from lg = np.log(logarg)), its test and */
/* the accepted crossings of _steps: cross = pts + (e or e_peak, + ph) pd, with their edge and       */
/* levels. Returns their number K.                                                                  */

static PyObject *py_finish(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o_cand, *o_est, *o_lg, *o_pts, *o_pd, *o_ph, *o_eid, *o_tex, *o_cross, *o_eido, *o_Am, *o_Bm;
    BufSet bs = {.n = 0};
    Py_buffer *b_cand, *b_est, *b_lg, *b_pts, *b_pd, *b_ph, *b_eid, *b_tex, *b_cross, *b_eido, *b_Am, *b_Bm;
    PyObject *result = NULL;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOOO:finish", &o_cand, &o_est, &o_lg, &o_pts, &o_pd, &o_ph, &o_eid, &o_tex,
                          &o_cross, &o_eido, &o_Am, &o_Bm))
        return NULL;
    GET(b_cand, o_cand, "cand", T_I64, 0, 1, -1);
    Py_ssize_t G = b_cand->shape[0];
    GET(b_est, o_est, "est", T_F64, 0, 2, G, 5);
    GET(b_lg, o_lg, "lg", T_F32 | T_F64, 0, 2, G, 3);
    GET(b_pts, o_pts, "pts", T_F64, 0, 2, -1, 2);
    Py_ssize_t M = b_pts->shape[0];
    GET(b_pd, o_pd, "pd", T_F64, 0, 2, M, 2);
    GET(b_ph, o_ph, "ph", T_F64, 0, 1, M);
    GET(b_eid, o_eid, "eid", T_I64, 0, 1, M);
    GET(b_tex, o_tex, "textured", T_BOOL, 0, 1, -1);
    Py_ssize_t E = b_tex->shape[0];
    GET_ROOM(b_cross, o_cross, "cross", T_F64, 2, G, 2);
    GET_ROOM(b_eido, o_eido, "eid_out", T_I64, 1, G);
    GET_ROOM(b_Am, o_Am, "Am", T_F64, 1, G);
    GET_ROOM(b_Bm, o_Bm, "Bm", T_F64, 1, G);
    const int64_t *cand = b_cand->buf, *eid = b_eid->buf;
    const double *est = b_est->buf, *pts = b_pts->buf, *pd = b_pd->buf, *ph = b_ph->buf;
    const void *lg = b_lg->buf;
    const int klg = buf_kind(b_lg), f32 = klg == T_F32;
    const unsigned char *tex = b_tex->buf;
    double *cross = b_cross->buf, *Am = b_Am->buf, *Bm = b_Bm->buf;
    int64_t *eido = b_eido->buf;
    if (check_index(cand, G, M, "cand") < 0 || check_index(eid, M, E, "eid") < 0)
        goto fail;
    Py_ssize_t K = 0;
    for (Py_ssize_t g = 0; g < G; g++) {
        Py_ssize_t r = (Py_ssize_t)cand[g];
        const double *es = est + 5 * g;
        double lm = elem(lg, klg, 3 * g), l0 = elem(lg, klg, 3 * g + 1), lp = elem(lg, klg, 3 * g + 2);
        /* den = lm - 2 l0 + lp; e_peak = at + (kk - k) + 0.5 + where(den < 0, 0.5 (lm - lp) / den, nan) */
        double den = rnd(rnd(lm - rnd(2 * l0, f32), f32) + lp, f32);
        double frac = den < 0 ? rnd(rnd(0.5 * rnd(lm - lp, f32), f32) / den, f32) : NAN;
        double e_peak = (es[4] + 0.5) + frac;
        if (!(fabs(e_peak - (es[3] + 0.5)) < 1.0))
            continue;
        Py_ssize_t e = (Py_ssize_t)eid[r];
        /* along = where(textured, e_peak, e) + phase; cross = pts + along pd */
        double along = (tex[e] ? e_peak : es[0]) + ph[r];
        double ax = along * pd[2 * r], ay = along * pd[2 * r + 1];
        cross[2 * K] = pts[2 * r] + ax;
        cross[2 * K + 1] = pts[2 * r + 1] + ay;
        eido[K] = e;
        Am[K] = es[1];
        Bm[K] = es[2];
        K++;
    }
    result = PyLong_FromSsize_t(K);
fail:
    bufs_release(&bs);
    return result;
}

/* ------------------------------------------------------------------------------------------------ */
/* lines: tracking._robust_lines (with _tukey and _lines_tls)                                       */

/* _tukey: Tukey biweights w (K,) of residuals r with a scale per group: 1.4826 MAD, at least floor */
static void tukey(const double *r, const int64_t *gid, const Py_ssize_t *starts, Py_ssize_t K, Py_ssize_t E,
                  double floor_, double *w, double *absr, double *s, double *scratch)
{
    for (Py_ssize_t j = 0; j < K; j++)
        absr[j] = fabs(r[j]);
    trick_median(absr, starts, E, s, scratch);
    for (Py_ssize_t g = 0; g < E; g++)
        s[g] = np_max(1.4826 * s[g], floor_);
    for (Py_ssize_t j = 0; j < K; j++) {
        double u = r[j] / (4.685 * s[gid[j]]);
        double a = 1 - u * u;
        w[j] = fabs(u) < 1 ? a * a : 0.0;
    }
}

/* numpy's pairwise summation (DOUBLE_pairwise_sum, numpy/_core/src/umath/loops_utils.h.src) of n
 * doubles a[0], a[stride], ...: what np.add.reduce and the reduction inner loops of np.add.reduceat sum */
static double pairwise_sum(const double *a, Py_ssize_t n, Py_ssize_t stride)
{
    if (n < 8) {
        double res = 0.;
        for (Py_ssize_t i = 0; i < n; i++)
            res += a[i * stride];
        return res;
    } else if (n <= 128) {
        double r[8], res;
        Py_ssize_t i;
        for (int k = 0; k < 8; k++)
            r[k] = a[k * stride];
        for (i = 8; i < n - (n % 8); i += 8)
            for (int k = 0; k < 8; k++)
                r[k] += a[(i + k) * stride];
        res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
        for (; i < n; i++)
            res += a[i * stride];
        return res;
    } else {
        Py_ssize_t n2 = n / 2;
        n2 -= n2 % 8;
        return pairwise_sum(a, n2, stride) + pairwise_sum(a + n2 * stride, n - n2, stride);
    }
}

/* _lines_tls: a weighted total-least-squares line per group (every group present): normals (nx, ny),
 * turned like the previous ones, and c. The six weighted moments A (K, 6) of every point, summed per
 * group as np.add.reduceat(A, starts, axis=0) sums them: each column the group's first row plus the
 * pairwise sum of the others. */
static void lines_tls(const double *q, const double *w, const Py_ssize_t *starts, Py_ssize_t E, double *nx,
                      double *ny, double *c, double *A)
{
    for (Py_ssize_t j = 0; j < starts[E]; j++) {
        double x = q[2 * j], y = q[2 * j + 1], wj = w[j];
        double a1 = wj * x, a2 = wj * y;
        double *row = A + 6 * j;
        row[0] = wj;
        row[1] = a1;
        row[2] = a2;
        row[3] = a1 * x;
        row[4] = a2 * y;
        row[5] = a1 * y;
    }
    for (Py_ssize_t g = 0; g < E; g++) {
        Py_ssize_t a = starts[g], cnt = starts[g + 1] - a;
        double m[6];
        for (int i = 0; i < 6; i++)
            m[i] = A[6 * a + i] + (cnt > 1 ? pairwise_sum(A + 6 * (a + 1) + i, cnt - 1, 6) : 0.0);
        double sw = np_max(m[0], 1e-300), sx = m[1], sy = m[2], sxx = m[3], syy = m[4], sxy = m[5];
        double mx = sx / sw, my = sy / sw;
        double cxx = sxx - sx * mx, cyy = syy - sy * my, cxy = sxy - sx * my;
        /* direction of the largest spread: the C library's atan2, sin, cos, which numpy's float64 ones
         * are where numpy has no SIMD version of its own for the CPU (then they may differ by an ulp) */
        double ang = 0.5 * atan2(2 * cxy, cxx - cyy);
        double ax = -sin(ang), ay = cos(ang);
        if (ax * nx[g] + ay * ny[g] < 0) {
            ax = -ax;
            ay = -ay;
        }
        nx[g] = ax;
        ny[g] = ay;
        c[g] = ax * mx + ay * my;
    }
}

static PyObject *py_lines(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o_q, *o_gid, *o_np, *o_cp, *o_n, *o_c, *o_w;
    BufSet bs = {.n = 0};
    Py_buffer *b_q, *b_gid, *b_np, *b_cp, *b_n, *b_c, *b_w;
    Py_ssize_t *starts = NULL;
    double *r = NULL, *absr = NULL, *scratch = NULL, *s = NULL, *nx = NULL, *ny = NULL, *c = NULL, *med = NULL;
    double *A = NULL;
    PyObject *result = NULL;
    if (!PyArg_ParseTuple(args, "OOOOOOO:lines", &o_q, &o_gid, &o_np, &o_cp, &o_n, &o_c, &o_w))
        return NULL;
    GET(b_q, o_q, "q", T_F64, 0, 2, -1, 2);
    Py_ssize_t K = b_q->shape[0];
    GET(b_gid, o_gid, "gid", T_I64, 0, 1, K);
    GET(b_np, o_np, "n_prev", T_F64, 0, 2, -1, 2);
    Py_ssize_t E = b_np->shape[0];
    GET(b_cp, o_cp, "c_prev", T_F64, 0, 1, E);
    GET(b_n, o_n, "n", T_F64, 1, 2, E, 2);
    GET(b_c, o_c, "c", T_F64, 1, 1, E);
    GET(b_w, o_w, "w", T_F64, 1, 1, K);
    const double *q = b_q->buf, *n_prev = b_np->buf, *c_prev = b_cp->buf;
    const int64_t *gid = b_gid->buf;
    if (!(starts = alloc((size_t)E + 1, sizeof(Py_ssize_t))))
        goto fail;
    if (group_bounds(gid, K, E, starts, "gid", 1) < 0)
        goto fail;
    if (!(r = alloc((size_t)K, sizeof(double))) || !(absr = alloc((size_t)K, sizeof(double))) ||
        !(scratch = alloc((size_t)K, sizeof(double))) || !(s = alloc((size_t)E, sizeof(double))) ||
        !(nx = alloc((size_t)E, sizeof(double))) || !(ny = alloc((size_t)E, sizeof(double))) ||
        !(c = alloc((size_t)E, sizeof(double))) || !(med = alloc((size_t)E, sizeof(double))) ||
        !(A = alloc(6 * (size_t)K, sizeof(double))))
        goto fail;
    double *w = b_w->buf;
    /* r = sum(q * n_prev[gid], axis=1) - c_prev[gid]; w = _tukey(r - median(r)[gid], groups, 0.05) */
    for (Py_ssize_t j = 0; j < K; j++) {
        Py_ssize_t g = (Py_ssize_t)gid[j];
        r[j] = (q[2 * j] * n_prev[2 * g] + q[2 * j + 1] * n_prev[2 * g + 1]) - c_prev[g];
    }
    trick_median(r, starts, E, med, scratch);
    for (Py_ssize_t j = 0; j < K; j++)
        r[j] = r[j] - med[gid[j]];
    tukey(r, gid, starts, K, E, 0.05, w, absr, s, scratch);
    for (Py_ssize_t g = 0; g < E; g++) {
        nx[g] = n_prev[2 * g];
        ny[g] = n_prev[2 * g + 1];
    }
    for (int it = 0; it < 3; it++) {
        lines_tls(q, w, starts, E, nx, ny, c, A);
        for (Py_ssize_t j = 0; j < K; j++) {
            Py_ssize_t g = (Py_ssize_t)gid[j];
            r[j] = (q[2 * j] * nx[g] + q[2 * j + 1] * ny[g]) - c[g];
        }
        tukey(r, gid, starts, K, E, 0.05, w, absr, s, scratch);
    }
    double *n_out = b_n->buf, *c_out = b_c->buf;
    for (Py_ssize_t g = 0; g < E; g++) {
        n_out[2 * g] = nx[g];
        n_out[2 * g + 1] = ny[g];
        c_out[g] = c[g];
    }
    result = Py_None;
    Py_INCREF(result);
fail:
    free(starts);
    free(r);
    free(absr);
    free(scratch);
    free(s);
    free(nx);
    free(ny);
    free(c);
    free(med);
    free(A);
    bufs_release(&bs);
    return result;
}

/* ------------------------------------------------------------------------------------------------ */
/* line_stats: what _track computes from the lines' inliers (w > 0): their count per edge, the faces' */
/* levels (_group_median of Am and Bm), their position along the line s_in and its mean and spread,  */
/* the residuals' sum of squares. Returns the number of inliers Kin (ei, s_in hold them).           */

static PyObject *py_line_stats(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o_q, *o_gid, *o_w, *o_n, *o_c, *o_Am, *o_Bm, *o_nin, *o_lev, *o_smean, *o_sss, *o_rss, *o_sin, *o_ei;
    BufSet bs = {.n = 0};
    Py_buffer *b_q, *b_gid, *b_w, *b_n, *b_c, *b_Am, *b_Bm, *b_nin, *b_lev, *b_smean, *b_sss, *b_rss, *b_sin, *b_ei;
    Py_ssize_t *starts = NULL;
    double *vals = NULL, *scratch = NULL, *med = NULL;
    PyObject *result = NULL;
    if (!PyArg_ParseTuple(args, "OOOOOOOOOOOOOO:line_stats", &o_q, &o_gid, &o_w, &o_n, &o_c, &o_Am, &o_Bm, &o_nin,
                          &o_lev, &o_smean, &o_sss, &o_rss, &o_sin, &o_ei))
        return NULL;
    GET(b_q, o_q, "q", T_F64, 0, 2, -1, 2);
    Py_ssize_t K = b_q->shape[0];
    GET(b_gid, o_gid, "gid", T_I64, 0, 1, K);
    GET(b_w, o_w, "w", T_F64, 0, 1, K);
    GET(b_n, o_n, "n", T_F64, 0, 2, -1, 2);
    Py_ssize_t E = b_n->shape[0];
    GET(b_c, o_c, "c", T_F64, 0, 1, E);
    GET(b_Am, o_Am, "Am", T_F64, 0, 1, K);
    GET(b_Bm, o_Bm, "Bm", T_F64, 0, 1, K);
    GET(b_nin, o_nin, "n_in", T_I64, 1, 1, E);
    GET(b_lev, o_lev, "levels", T_F64, 1, 2, E, 2);
    GET(b_smean, o_smean, "s_mean", T_F64, 1, 1, E);
    GET(b_sss, o_sss, "s_ss", T_F64, 1, 1, E);
    GET(b_rss, o_rss, "r_ss", T_F64, 1, 1, E);
    GET_ROOM(b_sin, o_sin, "s_in", T_F64, 1, K);
    GET_ROOM(b_ei, o_ei, "ei", T_I64, 1, K);
    const double *q = b_q->buf, *w = b_w->buf, *n = b_n->buf, *c = b_c->buf, *Am = b_Am->buf, *Bm = b_Bm->buf;
    const int64_t *gid = b_gid->buf;
    int64_t *n_in = b_nin->buf, *ei = b_ei->buf;
    double *levels = b_lev->buf, *s_mean = b_smean->buf, *s_ss = b_sss->buf, *r_ss = b_rss->buf, *s_in = b_sin->buf;
    if (!(starts = alloc(2 * (size_t)E + 1, sizeof(Py_ssize_t))))
        goto fail;
    if (group_bounds(gid, K, E, starts, "gid", 0) < 0)
        goto fail;
    if (!(vals = alloc(2 * (size_t)K, sizeof(double))) || !(scratch = alloc(2 * (size_t)K, sizeof(double))) ||
        !(med = alloc(2 * (size_t)E, sizeof(double))))
        goto fail;
    for (Py_ssize_t g = 0; g < E; g++)
        n_in[g] = 0, s_mean[g] = 0.0, s_ss[g] = 0.0, r_ss[g] = 0.0;
    /* inl = w > 0; ei = gid[inl]; n_in = bincount(ei); s_in = sum(qi * t2[ei], axis=1), t2 = (-n_y, n_x);
     * r_in = sum(qi * n[ei], axis=1) - c[ei]; s_mean = bincount(ei, s_in) / max(n_in, 1);
     * r_ss = bincount(ei, r_in * r_in) */
    Py_ssize_t Kin = 0;
    for (Py_ssize_t j = 0; j < K; j++) {
        if (!(w[j] > 0))
            continue;
        Py_ssize_t g = (Py_ssize_t)gid[j];
        double x = q[2 * j], y = q[2 * j + 1], nx = n[2 * g], ny = n[2 * g + 1];
        double s = x * -ny + y * nx;
        double rr = (x * nx + y * ny) - c[g];
        ei[Kin] = g;
        s_in[Kin] = s;
        vals[Kin] = Am[j];
        n_in[g]++;
        s_mean[g] += s;
        r_ss[g] += rr * rr;
        Kin++;
    }
    for (Py_ssize_t g = 0; g < E; g++)
        s_mean[g] = s_mean[g] / (double)(n_in[g] > 1 ? n_in[g] : 1);
    /* s_ss = bincount(ei, (s_in - s_mean[ei]) ** 2) */
    for (Py_ssize_t j = 0; j < Kin; j++) {
        double d = s_in[j] - s_mean[ei[j]];
        s_ss[ei[j]] += d * d;
    }
    /* levels: _group_median(concatenate([Am[inl], Bm[inl]]), concatenate([ei, ei + E]), 2 E) */
    Py_ssize_t k2 = Kin;
    for (Py_ssize_t j = 0; j < K; j++)
        if (w[j] > 0)
            vals[k2++] = Bm[j];
    starts[0] = 0;
    for (Py_ssize_t g = 0; g < E; g++)
        starts[g + 1] = starts[g] + n_in[g];
    for (Py_ssize_t g = 0; g < E; g++)
        starts[E + g + 1] = starts[E + g] + n_in[g];
    trick_median(vals, starts, 2 * E, med, scratch);
    for (Py_ssize_t g = 0; g < E; g++) {
        levels[2 * g] = med[g];
        levels[2 * g + 1] = med[E + g];
    }
    result = PyLong_FromSsize_t(Kin);
fail:
    free(starts);
    free(vals);
    free(scratch);
    free(med);
    bufs_release(&bs);
    return result;
}

/* ------------------------------------------------------------------------------------------------ */
/* group_median: tracking._Groups(gid, n).median(values), for the tests                             */

static PyObject *py_group_median(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o_v, *o_gid, *o_out;
    Py_ssize_t n;
    BufSet bs = {.n = 0};
    Py_buffer *b_v, *b_gid, *b_out;
    Py_ssize_t *starts = NULL;
    double *scratch = NULL;
    PyObject *result = NULL;
    if (!PyArg_ParseTuple(args, "OOnO:group_median", &o_v, &o_gid, &n, &o_out))
        return NULL;
    if (n < 0) {
        PyErr_Format(PyExc_ValueError, "n: expected a number of groups >= 0, got %zd", n);
        return NULL;
    }
    GET(b_v, o_v, "values", T_F64, 0, 1, -1);
    Py_ssize_t K = b_v->shape[0];
    GET(b_gid, o_gid, "gid", T_I64, 0, 1, K);
    GET(b_out, o_out, "out", T_F64, 1, 1, n);
    if (!(starts = alloc((size_t)n + 1, sizeof(Py_ssize_t))) || !(scratch = alloc((size_t)K, sizeof(double))))
        goto fail;
    if (group_bounds(b_gid->buf, K, n, starts, "gid", 0) < 0)
        goto fail;
    trick_median(b_v->buf, starts, n, b_out->buf, scratch);
    result = Py_None;
    Py_INCREF(result);
fail:
    free(starts);
    free(scratch);
    bufs_release(&bs);
    return result;
}

/* ------------------------------------------------------------------------------------------------ */
/* the search's kernels (selfview.fingertips, the reference there)                                  */

/* clear(st, others, pdir, R, margin, ok): _edge_steps's test that no point of another edge comes within
 * ``margin`` of a profile: per station s (S, 2) the least over others o (K, 2) of |rel - tt pdir|^2,
 * rel = o - st, tt = clip(rel . pdir, -R, R). numpy computes rel @ pdir as it likes (BLAS may fuse), so
 * the answer ok (S,) uint8 is 1 where that least is certainly >= margin^2, 0 where certainly below, 2
 * where it lies within 1e-6 of it or is NaN (the caller decides those rows with numpy). */
static PyObject *py_clear(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o_st, *o_oth, *o_pd, *o_ok;
    double R, margin;
    BufSet bs = {.n = 0};
    Py_buffer *b_st, *b_oth, *b_pd, *b_ok;
    PyObject *result = NULL;
    if (!PyArg_ParseTuple(args, "OOOddO:clear", &o_st, &o_oth, &o_pd, &R, &margin, &o_ok))
        return NULL;
    if (!(R >= 0.0 && R <= (double)MAX_SIZE && margin >= 0.0 && margin <= (double)MAX_SIZE)) {
        PyErr_Format(PyExc_ValueError, "R, margin: expected 0 <= R, margin <= 2**20, got %g, %g", R, margin);
        return NULL;
    }
    GET(b_st, o_st, "st", T_F64, 0, 2, -1, 2);
    Py_ssize_t S = b_st->shape[0];
    GET(b_oth, o_oth, "others", T_F64, 0, 2, -1, 2);
    Py_ssize_t K = b_oth->shape[0];
    GET(b_pd, o_pd, "pdir", T_F64, 0, 1, 2);
    GET(b_ok, o_ok, "ok", T_U8, 1, 1, S);
    const double *st = b_st->buf, *oth = b_oth->buf, *pd = b_pd->buf;
    unsigned char *ok = b_ok->buf;
    const double px = pd[0], py = pd[1], m2 = margin * margin, lo = m2 - 1e-6, hi = m2 + 1e-6;
    for (Py_ssize_t s = 0; s < S; s++) {
        const double sx = st[2 * s], sy = st[2 * s + 1];
        unsigned char v = 1;
        for (Py_ssize_t k = 0; k < K; k++) {
            const double rx = oth[2 * k] - sx, ry = oth[2 * k + 1] - sy;
            const double tt = np_clip(rx * px + ry * py, -R, R);
            const double dx = rx - tt * px, dy = ry - tt * py;
            const double d2 = dx * dx + dy * dy;
            if (d2 < lo) {
                v = 0;
                break;
            }
            if (!(d2 >= hi))
                v = 2; /* near the margin, or NaN: numpy decides */
        }
        ok[s] = v;
    }
    result = Py_None;
    Py_INCREF(result);
fail:
    bufs_release(&bs);
    return result;
}

/* search_profiles(img, st, pdir, ph, R, out): _edge_steps's profiles, _bilinear(img, pos) at
 * pos = st + (j + ph) pdir, j = -R..R, for a float32 picture: float64 weights and sums, in its order
 * (v00 (1 - fx) + v01 fx) (1 - fy) + (v10 (1 - fx) + v11 fx) fy; out (S, 2R + 1) float64. A sample
 * outside [0, W - 1) x [0, H - 1) raises ValueError (the caller keeps its profiles inside). */
static PyObject *py_search_profiles(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o_img, *o_st, *o_pd, *o_ph, *o_out;
    Py_ssize_t R;
    BufSet bs = {.n = 0};
    Py_buffer *b_img, *b_st, *b_pd, *b_ph, *b_out;
    PyObject *result = NULL;
    if (!PyArg_ParseTuple(args, "OOOOnO:search_profiles", &o_img, &o_st, &o_pd, &o_ph, &R, &o_out))
        return NULL;
    if (R < 0 || R > MAX_SIZE) {
        PyErr_Format(PyExc_ValueError, "R: expected 0 <= R <= 2**20, got %zd", R);
        return NULL;
    }
    GET(b_img, o_img, "img", T_F32, 0, 2, -1, -1);
    GET(b_st, o_st, "st", T_F64, 0, 2, -1, 2);
    Py_ssize_t S = b_st->shape[0], L = 2 * R + 1;
    GET(b_pd, o_pd, "pdir", T_F64, 0, 1, 2);
    GET(b_ph, o_ph, "ph", T_F64, 0, 1, S);
    GET(b_out, o_out, "out", T_F64, 1, 2, S, L);
    const float *a = b_img->buf;
    const Py_ssize_t W = b_img->shape[1], H = b_img->shape[0];
    const double *st = b_st->buf, *pd = b_pd->buf, *ph = b_ph->buf;
    double *out = b_out->buf;
    const double wlim = (double)(W - 1), hlim = (double)(H - 1);
    for (Py_ssize_t s = 0; s < S; s++) {
        for (Py_ssize_t j = 0; j < L; j++) {
            const double t = (double)(j - R) + ph[s]; /* j[None, :] + ph[:, None] */
            const double x = st[2 * s] + t * pd[0], y = st[2 * s + 1] + t * pd[1];
            if (!(x >= 0.0 && x < wlim && y >= 0.0 && y < hlim)) {
                PyErr_Format(PyExc_ValueError, "st, pdir, ph: sample %zd of profile %zd lies outside the %zdx%zd picture",
                             j, s, W, H);
                goto fail;
            }
            /* np.floor: for 0 <= x < W - 1 the truncation */
            const Py_ssize_t ix = (Py_ssize_t)x, iy = (Py_ssize_t)y;
            const double fx = x - (double)ix, fy = y - (double)iy;
            const Py_ssize_t i00 = iy * W + ix;
            const double v00 = a[i00], v01 = a[i00 + 1], v10 = a[i00 + W], v11 = a[i00 + W + 1];
            out[s * L + j] = (v00 * (1 - fx) + v01 * fx) * (1 - fy) + (v10 * (1 - fx) + v11 * fx) * fy;
        }
    }
    result = Py_None;
    Py_INCREF(result);
fail:
    bufs_release(&bs);
    return result;
}

/* template_sums(Gn, q, n, out): _template_score's sums of one edge, out (n, n) float32 += Gn[qy:qy + n,
 * qx:qx + n] for each template point (qx, qy) of q (M, 2) in turn (float32 additions, in that order). */
static PyObject *py_template_sums(PyObject *self, PyObject *args)
{
    (void)self;
    PyObject *o_g, *o_q, *o_out;
    Py_ssize_t n;
    BufSet bs = {.n = 0};
    Py_buffer *b_g, *b_q, *b_out;
    PyObject *result = NULL;
    if (!PyArg_ParseTuple(args, "OOnO:template_sums", &o_g, &o_q, &n, &o_out))
        return NULL;
    if (n < 1 || n > MAX_SIZE) {
        PyErr_Format(PyExc_ValueError, "n: expected 1 <= n <= 2**20, got %zd", n);
        return NULL;
    }
    GET(b_g, o_g, "Gn", T_F32, 0, 2, -1, -1);
    GET(b_q, o_q, "q", T_I64, 0, 2, -1, 2);
    GET(b_out, o_out, "out", T_F32, 1, 2, n, n);
    const float *g = b_g->buf;
    const int64_t *q = b_q->buf;
    float *out = b_out->buf;
    const Py_ssize_t gh = b_g->shape[0], gw = b_g->shape[1], M = b_q->shape[0];
    for (Py_ssize_t m = 0; m < M; m++)
        if (q[2 * m] < 0 || q[2 * m + 1] < 0 || q[2 * m] > (int64_t)(gw - n) || q[2 * m + 1] > (int64_t)(gh - n)) {
            PyErr_Format(PyExc_ValueError, "q: point %zd (%lld, %lld) puts a %zdx%zd window outside Gn (%zdx%zd)", m,
                         (long long)q[2 * m], (long long)q[2 * m + 1], n, n, gw, gh);
            goto fail;
        }
    for (Py_ssize_t m = 0; m < M; m++) {
        const float *src = g + (Py_ssize_t)q[2 * m + 1] * gw + (Py_ssize_t)q[2 * m];
        for (Py_ssize_t i = 0; i < n; i++) {
            const float *row = src + i * gw;
            float *acc = out + i * n;
            for (Py_ssize_t j = 0; j < n; j++)
                acc[j] += row[j];
        }
    }
    result = Py_None;
    Py_INCREF(result);
fail:
    bufs_release(&bs);
    return result;
}

/* ------------------------------------------------------------------------------------------------ */

static PyMethodDef methods[] = {
    {"coarse_maps", py_coarse_maps, METH_VARARGS,
     "coarse_maps(pts, pd, sub, R, W, H, mx, my): the float32 maps (m, 2R+1) of the coarse profiles."},
    {"coarse", py_coarse, METH_VARARGS,
     "coarse(prof1, sub, pts, eid, h, levels, crease, sr1, phase, W, H, R, lim, P, min_contrast, keep_fraction, "
     "ph) -> None, or (edge, n_ok, n_sub) of the first edge that shows too few steps."},
    {"fine", py_fine, METH_VARARGS,
     "fine(img, pts, pd, ph, eid, h, levels, crease, g, R, half, P, min_contrast, cand, est, logarg) -> G."},
    {"profiles", py_profiles, METH_VARARGS,
     "profiles(img, pts, pd, phase, R, out): the bilinear profiles of tracking._profiles (no clipping)."},
    {"finish", py_finish, METH_VARARGS,
     "finish(cand, est, lg, pts, pd, ph, eid, textured, cross, eid_out, Am, Bm) -> K accepted crossings."},
    {"lines", py_lines, METH_VARARGS, "lines(q, gid, n_prev, c_prev, n, c, w): the robust lines (_robust_lines)."},
    {"line_stats", py_line_stats, METH_VARARGS,
     "line_stats(q, gid, w, n, c, Am, Bm, n_in, levels, s_mean, s_ss, r_ss, s_in, ei) -> Kin."},
    {"group_median", py_group_median, METH_VARARGS,
     "group_median(values, gid, n, out): the median per group, as tracking._Groups.median."},
    {"clear", py_clear, METH_VARARGS,
     "clear(st, others, pdir, R, margin, ok): fingertips._edge_steps's profiles clear of other edges (1, 0, 2: unsure)."},
    {"search_profiles", py_search_profiles, METH_VARARGS,
     "search_profiles(img, st, pdir, ph, R, out): fingertips._edge_steps's bilinear profiles (float64)."},
    {"template_sums", py_template_sums, METH_VARARGS,
     "template_sums(Gn, q, n, out): fingertips._template_score's sums of one edge (float32, in order)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef moddef = {
    PyModuleDef_HEAD_INIT,
    "_ctrack",
    "The fingertip tracker's per-frame kernels (see selfview/tracking.py, the reference).",
    -1,
    methods,
    NULL,
    NULL,
    NULL,
    NULL,
};

PyMODINIT_FUNC PyInit__ctrack(void)
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
