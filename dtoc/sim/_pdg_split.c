/* Optional compiled core of one RF split of the PDG pre-pass (dtoc/sim/pdg_graph_step.py, split_step).
 *
 * Built at install when a C compiler is there (setup.py, optional extension); without it the numpy formulation
 * of pdg_graph_step.py runs.  Only exactly rounded operations happen here -- comparisons, integer arithmetic,
 * IEEE additions in the numpy code's order, one division and rint per key, multiplications by +-1 -- so the
 * graph is the numpy one bit for bit on any machine (tests/test_prepass_native.py).  Every operation whose bits
 * depend on the numpy build (complex products, complex abs, exp, sin) stays in numpy, in the caller.
 *
 * merge(): the kept candidate edges (cand >= min_magnitude, in (parent, slot) order), their merge keys (child
 *   type, then the parent's rounded end-of-interval k and tau, negated for the conjugating slot), the merged
 *   children in ascending key order (the order numpy's argsort of the packed keys gives), each edge's child, the
 *   children's summed probe amplitudes (each edge added in edge order from 0, as np.bincount does) and each
 *   child's representative edge (largest cand, lowest edge on ties).
 * finish(): which children survive (amplitude estimate >= min_magnitude and an edge; the equilibrium always; the
 *   max_states largest when more, ties to the lowest index) and the next interval's arrays.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <float.h>
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#if defined(__GNUC__) || defined(__clang__)
#pragma GCC optimize("fp-contract=off")
#endif

#define KEY_LIMIT (((int64_t)1) << 62)

typedef struct {
    Py_buffer b;
    int held;
} buf_t;

static int get_buf(PyObject *o, buf_t *x, int writable, Py_ssize_t min_bytes, const char *name) {
    if (PyObject_GetBuffer(o, &x->b, PyBUF_C_CONTIGUOUS | (writable ? PyBUF_WRITABLE : 0)) < 0) {
        return -1;
    }
    x->held = 1;
    if (x->b.len < min_bytes) {
        PyErr_Format(PyExc_ValueError, "_pdg_split: buffer %s too small", name);
        return -1;
    }
    return 0;
}

static void release(buf_t *bufs, int n) {
    for (int i = 0; i < n; i++) {
        if (bufs[i].held) {
            PyBuffer_Release(&bufs[i].b);
            bufs[i].held = 0;
        }
    }
}

/* ---- sorting ------------------------------------------------------------------------------------------------ */

/* LSD radix sort of (key, index) pairs, keys in [0, 2^62): ascending keys (order within equal keys irrelevant). */
static int radix_sort(int64_t *key, int64_t *idx, Py_ssize_t n, int64_t kmax) {
    enum { BITS = 11, NB = 1 << BITS };
    int64_t *k2 = (int64_t *)malloc((size_t)(n > 0 ? n : 1) * sizeof(int64_t));
    int64_t *i2 = (int64_t *)malloc((size_t)(n > 0 ? n : 1) * sizeof(int64_t));
    Py_ssize_t *cnt = (Py_ssize_t *)malloc(NB * sizeof(Py_ssize_t));
    if (!k2 || !i2 || !cnt) {
        free(k2);
        free(i2);
        free(cnt);
        return -1;
    }
    int64_t *ka = key, *ia = idx, *kb = k2, *ib = i2;
    for (int shift = 0; shift < 63 && (kmax >> shift) != 0; shift += BITS) {
        memset(cnt, 0, NB * sizeof(Py_ssize_t));
        for (Py_ssize_t i = 0; i < n; i++) cnt[(ka[i] >> shift) & (NB - 1)]++;
        Py_ssize_t s = 0;
        for (int d = 0; d < NB; d++) {
            Py_ssize_t c = cnt[d];
            cnt[d] = s;
            s += c;
        }
        for (Py_ssize_t i = 0; i < n; i++) {
            Py_ssize_t p = cnt[(ka[i] >> shift) & (NB - 1)]++;
            kb[p] = ka[i];
            ib[p] = ia[i];
        }
        int64_t *t = ka;
        ka = kb;
        kb = t;
        t = ia;
        ia = ib;
        ib = t;
    }
    if (ka != key) {
        memcpy(key, ka, (size_t)n * sizeof(int64_t));
        memcpy(idx, ia, (size_t)n * sizeof(int64_t));
    }
    free(k2);
    free(i2);
    free(cnt);
    return 0;
}

/* merge sort of row indices by the rows (n x 5 int64, lexicographic): the fallback when the keys do not pack. */
static int row_less(const int64_t *rows, int64_t a, int64_t b) {
    for (int j = 0; j < 5; j++) {
        if (rows[5 * a + j] != rows[5 * b + j]) return rows[5 * a + j] < rows[5 * b + j];
    }
    return 0;
}

static void merge_sort_rows(const int64_t *rows, int64_t *idx, int64_t *tmp, Py_ssize_t n) {
    if (n < 2) return;
    Py_ssize_t h = n / 2;
    merge_sort_rows(rows, idx, tmp, h);
    merge_sort_rows(rows, idx + h, tmp, n - h);
    Py_ssize_t i = 0, j = h, o = 0;
    while (i < h && j < n) tmp[o++] = row_less(rows, idx[j], idx[i]) ? idx[j++] : idx[i++];
    while (i < h) tmp[o++] = idx[i++];
    while (j < n) tmp[o++] = idx[j++];
    memcpy(idx, tmp, (size_t)n * sizeof(int64_t));
}

/* ---- ranks -------------------------------------------------------------------------------------------------- */

#define DIRECT_LIMIT (((int64_t)1) << 15)

static int cmp_i64(const void *a, const void *b) {
    const int64_t x = *(const int64_t *)a, y = *(const int64_t *)b;
    return (x > y) - (x < y);
}

/* Replace column ``a`` of the (S, 4) int64 rows ``q`` (no INT64_MIN) by sign(v) * rank(abs(v)) among the distinct
   absolute values and 0 (rank(0) = 0); ``*mout``: the largest rank. */
static int signed_rank_column(int64_t *q, Py_ssize_t S, int a, int64_t *mout) {
    size_t cap = 1;
    int bits = 0;
    while (cap < (size_t)(2 * S + 2)) {
        cap <<= 1;
        bits++;
    }
    if (bits == 0) {
        cap = 2;
        bits = 1;
    }
    int64_t *tab = (int64_t *)malloc(cap * sizeof(int64_t));
    int64_t *rk = (int64_t *)malloc(cap * sizeof(int64_t));
    uint8_t *used = (uint8_t *)calloc(cap, 1);
    size_t *at = (size_t *)malloc((size_t)(S > 0 ? S : 1) * sizeof(size_t));
    int64_t *uniq = (int64_t *)malloc((size_t)(S + 1) * sizeof(int64_t));
    if (!tab || !rk || !used || !at || !uniq) {
        free(tab);
        free(rk);
        free(used);
        free(at);
        free(uniq);
        return -1;
    }
    Py_ssize_t U = 0;
    for (Py_ssize_t s = -1; s < S; s++) {
        const int64_t v = s < 0 ? 0 : q[4 * s + a];
        const int64_t av = v < 0 ? -v : v;
        size_t h = (size_t)(((uint64_t)av * 0x9E3779B97F4A7C15ULL) >> (64 - bits));
        while (used[h] && tab[h] != av) h = (h + 1) & (cap - 1);
        if (!used[h]) {
            used[h] = 1;
            tab[h] = av;
            uniq[U++] = av;
        }
        if (s >= 0) at[s] = h;
    }
    qsort(uniq, (size_t)U, sizeof(int64_t), cmp_i64);
    for (Py_ssize_t i = 0; i < U; i++) {
        size_t h = (size_t)(((uint64_t)uniq[i] * 0x9E3779B97F4A7C15ULL) >> (64 - bits));
        while (tab[h] != uniq[i]) h = (h + 1) & (cap - 1);
        rk[h] = i;
    }
    for (Py_ssize_t s = 0; s < S; s++) {
        const int64_t v = q[4 * s + a];
        q[4 * s + a] = v < 0 ? -rk[at[s]] : rk[at[s]];
    }
    *mout = U - 1;
    free(tab);
    free(rk);
    free(used);
    free(at);
    free(uniq);
    return 0;
}

/* ---- arguments ------------------------------------------------------------------------------------------------ */

/* The buffers of ``arrs`` (a tuple of n C-contiguous arrays), each of at least ``need[i]`` bytes; writable from
   index ``first_out`` on. */
static int get_all(PyObject *arrs, buf_t *b, int n, const Py_ssize_t *need, int first_out) {
    if (!PyTuple_Check(arrs) || PyTuple_GET_SIZE(arrs) != n) {
        PyErr_Format(PyExc_TypeError, "_pdg_split: expected a tuple of %d arrays", n);
        return -1;
    }
    memset(b, 0, (size_t)n * sizeof(buf_t));
    for (int i = 0; i < n; i++) {
        char name[16];
        snprintf(name, sizeof(name), "#%d", i);
        if (get_buf(PyTuple_GET_ITEM(arrs, i), &b[i], i >= first_out, need[i], name) < 0) {
            release(b, n);
            return -1;
        }
    }
    return 0;
}

/* ---- merge ---------------------------------------------------------------------------------------------------- */

static PyObject *merge(PyObject *self, PyObject *args) {
    Py_ssize_t S, P;
    double min_mag, qk, qt;
    int tau_ignored;
    PyObject *arrs;
    if (!PyArg_ParseTuple(args, "nndddpO", &S, &P, &min_mag, &qk, &qt, &tau_ignored, &arrs)) return NULL;
    if (S < 0 || P < 1) {
        PyErr_SetString(PyExc_ValueError, "_pdg_split.merge: bad sizes");
        return NULL;
    }
    const Py_ssize_t E3 = 3 * S;
    /* in: cand (3S) f8, is_z (S) bool, k_end (S,3) f8, tau_end (S) f8, ccand (3S,P) c16;
       out: par, slot, kind (3S) i8, cand_k (3S) f8, inv (3S+1) i8, child_z (3S+1) bool, camp (3S+1,P) c16,
            rep (3S+1) i8 */
    const Py_ssize_t need[13] = {E3 * 8, S, S * 24, S * 8, E3 * P * 16, E3 * 8, E3 * 8,
                                 E3 * 8, E3 * 8, (E3 + 1) * 8, E3 + 1, (E3 + 1) * P * 16, (E3 + 1) * 8};
    buf_t b[13];
    if (get_all(arrs, b, 13, need, 5) < 0) return NULL;
    const double *cand = (const double *)b[0].b.buf;
    const uint8_t *is_z = (const uint8_t *)b[1].b.buf;
    const double *k_end = (const double *)b[2].b.buf;
    const double *tau_end = (const double *)b[3].b.buf;
    const double *ccand = (const double *)b[4].b.buf;
    int64_t *par = (int64_t *)b[5].b.buf;
    int64_t *slot = (int64_t *)b[6].b.buf;
    int64_t *kind = (int64_t *)b[7].b.buf;
    double *cand_k = (double *)b[8].b.buf;
    int64_t *inv = (int64_t *)b[9].b.buf;
    uint8_t *child_z = (uint8_t *)b[10].b.buf;
    double *camp = (double *)b[11].b.buf;
    int64_t *rep = (int64_t *)b[12].b.buf;

    /* kept candidate edges, in (parent, slot) order */
    Py_ssize_t E = 0;
    for (Py_ssize_t e = 0; e < E3; e++) {
        if (cand[e] >= min_mag) {
            Py_ssize_t p = e / 3;
            par[E] = p;
            slot[E] = e - 3 * p;
            kind[E] = slot[E] + 3 * (is_z[p] != 0);
            cand_k[E] = cand[e];
            E++;
        }
    }
    /* the parents' rounded keys (kx, ky, kz, tau) */
    int64_t *q = (int64_t *)malloc((size_t)(S > 0 ? S : 1) * 4 * sizeof(int64_t));
    const Py_ssize_t n = E + 1; /* the kept edges and the equilibrium state */
    int64_t *key = (int64_t *)malloc((size_t)n * sizeof(int64_t));
    int64_t *ord = (int64_t *)malloc((size_t)n * sizeof(int64_t));
    int64_t *rows = NULL, *tmp = NULL;
    PyObject *ret = NULL;
    if (!q || !key || !ord) goto nomem;
    int64_t m[4] = {0, 0, 0, 0};
    int wide = 0;
    for (Py_ssize_t s = 0; s < S; s++) {
        for (int a = 0; a < 3; a++) q[4 * s + a] = (int64_t)rint(k_end[3 * s + a] / qk);
        q[4 * s + 3] = tau_ignored ? 0 : (int64_t)rint(tau_end[s] / qt);
        for (int a = 0; a < 4; a++) {
            int64_t v = q[4 * s + a];
            if (v == INT64_MIN) {
                wide = 1;
            } else {
                int64_t av = v < 0 ? -v : v;
                if (av > m[a]) m[a] = av;
            }
        }
    }
    /* a column of large values: its signed dense rank over the absolute values and 0 (order kept for both signs) */
    for (int a = 0; a < 4 && !wide; a++) {
        if (m[a] >= DIRECT_LIMIT) {
            int r = signed_rank_column(q, S, a, &m[a]);
            if (r < 0) goto nomem;
        }
    }
    /* mixed radix: type, then the four columns offset by their largest absolute value (both signs fit) */
    int64_t radix[4];
    int64_t total = 1;
    for (int a = 3; a >= 0 && !wide; a--) {
        int64_t span = 2 * m[a] + 1;
        radix[a] = total;
        if (total > (KEY_LIMIT / 2) / span) wide = 1;
        else total *= span;
    }
    if (!wide && total > (KEY_LIMIT / 2) / 2) wide = 1;
    if (!wide) {
        int64_t kmax = 0;
        for (Py_ssize_t e = 0; e < E; e++) {
            const int64_t *qp = q + 4 * par[e];
            const int64_t sg = slot[e] == 1 ? -1 : 1;
            int64_t kk = slot[e] == 2 ? total : 0;
            for (int a = 0; a < 4; a++) kk += (sg * qp[a] + m[a]) * radix[a];
            key[e] = kk;
            ord[e] = e;
            if (kk > kmax) kmax = kk;
        }
        int64_t kz = total;
        for (int a = 0; a < 4; a++) kz += m[a] * radix[a];
        key[E] = kz;
        ord[E] = E;
        if (kz > kmax) kmax = kz;
        if (radix_sort(key, ord, n, kmax) < 0) goto nomem;
        Py_ssize_t c = -1;
        for (Py_ssize_t i = 0; i < n; i++) {
            if (i == 0 || key[i] != key[i - 1]) {
                c++;
                child_z[c] = key[i] >= total;
            }
            inv[ord[i]] = c;
        }
    } else {
        rows = (int64_t *)malloc((size_t)n * 5 * sizeof(int64_t));
        tmp = (int64_t *)malloc((size_t)n * sizeof(int64_t));
        if (!rows || !tmp) goto nomem;
        for (Py_ssize_t e = 0; e < E; e++) {
            const int64_t *qp = q + 4 * par[e];
            const int64_t sg = slot[e] == 1 ? -1 : 1;
            rows[5 * e] = slot[e] == 2;
            for (int a = 0; a < 4; a++) rows[5 * e + 1 + a] = sg * qp[a];
            ord[e] = e;
        }
        rows[5 * E] = 1;
        for (int a = 0; a < 4; a++) rows[5 * E + 1 + a] = 0;
        ord[E] = E;
        merge_sort_rows(rows, ord, tmp, n);
        Py_ssize_t c = -1;
        for (Py_ssize_t i = 0; i < n; i++) {
            if (i == 0 || memcmp(rows + 5 * ord[i], rows + 5 * ord[i - 1], 5 * sizeof(int64_t)) != 0) {
                c++;
                child_z[c] = rows[5 * ord[i]] != 0;
            }
            inv[ord[i]] = c;
        }
    }
    Py_ssize_t nU = 0;
    for (Py_ssize_t i = 0; i < n; i++)
        if (inv[i] + 1 > nU) nU = inv[i] + 1;
    /* children's probe amplitudes: every kept edge's row added in edge order from 0; representative edges */
    memset(camp, 0, (size_t)nU * P * 16);
    for (Py_ssize_t c = 0; c < nU; c++) rep[c] = -1;
    for (Py_ssize_t e = 0; e < E; e++) {
        const Py_ssize_t c = inv[e];
        const double *src = ccand + 2 * P * (3 * par[e] + slot[e]);
        double *dst = camp + 2 * P * c;
        for (Py_ssize_t j = 0; j < 2 * P; j++) dst[j] += src[j];
        if (rep[c] < 0 || cand_k[e] > cand_k[rep[c]]) rep[c] = e;
    }
    ret = Py_BuildValue("nnn", E, nU, (Py_ssize_t)inv[E]);
    goto done;
nomem:
    PyErr_NoMemory();
done:
    free(q);
    free(key);
    free(ord);
    free(rows);
    free(tmp);
    release(b, 13);
    return ret;
}

/* ---- finish --------------------------------------------------------------------------------------------------- */

/* the k-th largest (k >= 1) of v (n > k values, no NaN), by selection on a copy */
static double kth_largest(double *a, Py_ssize_t n, Py_ssize_t k) {
    Py_ssize_t lo = 0, hi = n - 1, t = k - 1; /* index t of the descending order */
    while (lo < hi) {
        double pv = a[lo + (hi - lo) / 2];
        Py_ssize_t i = lo, j = hi;
        while (i <= j) {
            while (a[i] > pv) i++;
            while (a[j] < pv) j--;
            if (i <= j) {
                double x = a[i];
                a[i] = a[j];
                a[j] = x;
                i++;
                j--;
            }
        }
        if (t <= j) hi = j;
        else if (t >= i) lo = i;
        else return a[t];
    }
    return a[t];
}

static PyObject *finish(PyObject *self, PyObject *args) {
    Py_ssize_t nU, P, E, eq_new, max_states, S;
    double min_mag;
    PyObject *arrs;
    if (!PyArg_ParseTuple(args, "nnnnndnO", &nU, &P, &E, &eq_new, &S, &min_mag, &max_states, &arrs)) return NULL;
    if (nU < 1 || P < 1 || E < 0 || eq_new < 0 || eq_new >= nU || max_states < 1) {
        PyErr_SetString(PyExc_ValueError, "_pdg_split.finish: bad sizes");
        return NULL;
    }
    /* in: cmag (nU) f8, rep (nU) i8, inv (E) i8, par, slot, kind (E) i8, cand_k (E) f8, k_end (S,3), tau_end (S),
           child_z (nU) bool, camp (nU,P) c16;
       out: z (nU) bool, k (nU,3), tau (nU), mag (nU), amp (nU,P) c16, e_child, e_par, e_kind (E) i8, e_cand (E) */
    const Py_ssize_t need[20] = {nU * 8, nU * 8, E * 8, E * 8, E * 8, E * 8, E * 8, S * 24, S * 8, nU,
                                 nU * P * 16, nU, nU * 24, nU * 8, nU * 8, nU * P * 16, E * 8, E * 8, E * 8, E * 8};
    buf_t b[20];
    if (get_all(arrs, b, 20, need, 11) < 0) return NULL;
    const double *cmag = (const double *)b[0].b.buf;
    const int64_t *rep = (const int64_t *)b[1].b.buf;
    const int64_t *inv = (const int64_t *)b[2].b.buf;
    const int64_t *par = (const int64_t *)b[3].b.buf;
    const int64_t *slot = (const int64_t *)b[4].b.buf;
    const int64_t *kind = (const int64_t *)b[5].b.buf;
    const double *cand_k = (const double *)b[6].b.buf;
    const double *k_end = (const double *)b[7].b.buf;
    const double *tau_end = (const double *)b[8].b.buf;
    const uint8_t *child_z = (const uint8_t *)b[9].b.buf;
    const double *camp = (const double *)b[10].b.buf;
    uint8_t *z = (uint8_t *)b[11].b.buf;
    double *k = (double *)b[12].b.buf;
    double *tau = (double *)b[13].b.buf;
    double *mag = (double *)b[14].b.buf;
    double *amp = (double *)b[15].b.buf;
    int64_t *e_child = (int64_t *)b[16].b.buf;
    int64_t *e_par = (int64_t *)b[17].b.buf;
    int64_t *e_kind = (int64_t *)b[18].b.buf;
    double *e_cand = (double *)b[19].b.buf;
    /* the indices come from merge(); checked all the same (a wrong one would read outside the arrays) */
    for (Py_ssize_t e = 0; e < E; e++) {
        if (inv[e] < 0 || inv[e] >= nU || par[e] < 0 || par[e] >= S || slot[e] < 0 || slot[e] > 2) {
            release(b, 20);
            PyErr_SetString(PyExc_ValueError, "_pdg_split.finish: edge index out of range");
            return NULL;
        }
    }
    for (Py_ssize_t c = 0; c < nU; c++) {
        if (rep[c] < -1 || rep[c] >= E) {
            release(b, 20);
            PyErr_SetString(PyExc_ValueError, "_pdg_split.finish: representative edge out of range");
            return NULL;
        }
    }
    PyObject *ret = NULL;
    const size_t nu = (size_t)(nU > 0 ? nU : 1); /* nU >= 1 (checked above); said again for the compiler */
    uint8_t *alive = (uint8_t *)malloc(nu);
    int64_t *new_idx = (int64_t *)malloc(nu * sizeof(int64_t));
    double *score = NULL;
    if (!alive || !new_idx) goto nomem;
    Py_ssize_t n_alive = 0;
    for (Py_ssize_t c = 0; c < nU; c++) {
        alive[c] = (cmag[c] >= min_mag && rep[c] >= 0) || c == eq_new;
        n_alive += alive[c];
    }
    if (n_alive > max_states) { /* the max_states largest estimates (the equilibrium first), ties to the lowest index */
        score = (double *)malloc((size_t)nU * sizeof(double));
        if (!score) goto nomem;
        for (Py_ssize_t c = 0; c < nU; c++) score[c] = c == eq_new ? INFINITY : (alive[c] ? cmag[c] : -1.0);
        double *cp = (double *)malloc((size_t)nU * sizeof(double));
        if (!cp) goto nomem;
        memcpy(cp, score, (size_t)nU * sizeof(double));
        const double v = kth_largest(cp, nU, max_states);
        free(cp);
        Py_ssize_t cnt = 0;
        for (Py_ssize_t c = 0; c < nU; c++) {
            alive[c] = score[c] > v;
            cnt += alive[c];
        }
        for (Py_ssize_t c = 0; c < nU && cnt < max_states; c++) {
            if (score[c] == v) {
                alive[c] = 1;
                cnt++;
            }
        }
    }
    Py_ssize_t nS = 0;
    for (Py_ssize_t c = 0; c < nU; c++) {
        new_idx[c] = nS - 1 + alive[c];
        if (!alive[c]) continue;
        z[nS] = child_z[c];
        const int64_t r = rep[c];
        if (r >= 0) {
            const double sg = slot[r] == 1 ? -1.0 : 1.0;
            const int64_t rp = par[r];
            for (int a = 0; a < 3; a++) k[3 * nS + a] = k_end[3 * rp + a] * sg;
            tau[nS] = tau_end[rp] * sg;
        } else {
            k[3 * nS] = k[3 * nS + 1] = k[3 * nS + 2] = 0.0;
            tau[nS] = 0.0;
        }
        mag[nS] = cmag[c];
        memcpy(amp + 2 * P * nS, camp + 2 * P * c, (size_t)P * 16);
        nS++;
    }
    const Py_ssize_t eq = new_idx[eq_new];
    k[3 * eq] = k[3 * eq + 1] = k[3 * eq + 2] = 0.0;
    tau[eq] = 0.0;
    z[eq] = 1;
    Py_ssize_t nE = 0;
    for (Py_ssize_t e = 0; e < E; e++) {
        if (!alive[inv[e]]) continue;
        e_child[nE] = new_idx[inv[e]];
        e_par[nE] = par[e];
        e_kind[nE] = kind[e];
        e_cand[nE] = cand_k[e];
        nE++;
    }
    ret = Py_BuildValue("nnn", nS, nE, eq);
    goto done;
nomem:
    PyErr_NoMemory();
done:
    free(alive);
    free(new_idx);
    free(score);
    release(b, 20);
    return ret;
}

/* ---- emission bound ------------------------------------------------------------------------------------------- */

/* unique_bits(values (n,) f8, uniq (n,) f8 out, inv (n,) i8 out) -> U: the distinct values (by their bits, so
   -0.0 and 0.0 are distinct) in order of first occurrence and each value's index among them. */
static PyObject *unique_bits(PyObject *self, PyObject *args) {
    Py_ssize_t n;
    PyObject *arrs;
    if (!PyArg_ParseTuple(args, "nO", &n, &arrs)) return NULL;
    const Py_ssize_t need[3] = {n * 8, n * 8, n * 8};
    buf_t b[3];
    if (get_all(arrs, b, 3, need, 1) < 0) return NULL;
    const uint64_t *v = (const uint64_t *)b[0].b.buf;
    uint64_t *u = (uint64_t *)b[1].b.buf;
    int64_t *inv = (int64_t *)b[2].b.buf;
    size_t cap = 2;
    int bits = 1;
    while (cap < (size_t)(2 * n + 2)) {
        cap <<= 1;
        bits++;
    }
    int64_t *slot_u = (int64_t *)malloc(cap * sizeof(int64_t));
    if (!slot_u) {
        release(b, 3);
        return PyErr_NoMemory();
    }
    for (size_t i = 0; i < cap; i++) slot_u[i] = -1;
    Py_ssize_t U = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        size_t h = (size_t)((v[i] * 0x9E3779B97F4A7C15ULL) >> (64 - bits));
        while (slot_u[h] >= 0 && u[slot_u[h]] != v[i]) h = (h + 1) & (cap - 1);
        if (slot_u[h] < 0) {
            slot_u[h] = U;
            u[U++] = v[i];
        }
        inv[i] = slot_u[h];
    }
    free(slot_u);
    release(b, 3);
    return PyLong_FromSsize_t(U);
}

/* ---- the emission bound of pdg_graph._Emission.exact, element by element --------------------------------------

   Per state s and ADC sample t of the interval: k_a = ks[s, a] + mt[t or 0, a] (0 where the axis' moment is
   constant over the window, as exact() broadcasts), then
       env = ((1 * vox_x) * vox_y) * vox_z                         (the axes with a voxel size)
       spec = min(F[iz, iy, ix] * |sinc_x * sinc_y| (* |sinc_z|), 1)  (object spectrum, 'box' voxels; 'sinc' voxels:
                                                                     0/1 masks instead of the sincs)
       value = (min(env, spec) * e2[t]) * etau[it[s], t]
   and the state's bound is the largest value over t.  Everything here is exactly rounded (adds, products,
   quotients, rint, comparisons); only the sincs need sin, which stays numpy's: the caller evaluates them for the
   elements that can still hold the maximum.  With a 'box' spectrum, pass 1 gives each state's sample of largest
   upper bound (every |sinc| replaced by min(1, 1 / (pi |u|)) (1 + 1e-9), which is above numpy's |sinc|; every
   later operation is monotone, so the bound is above the value as computed), pass 2 the value there (the sincs
   given) and the elements whose bound exceeds it, pass 3 the maximum over those (sincs given).  Without a 'box'
   spectrum pass 1 gives the values themselves. */

typedef struct {
    Py_ssize_t S, T;
    int fixed[3];
    int vshape;     /* 0 none, 1 box, 2 sinc */
    double vd[3];   /* voxel size per axis, 0: no factor */
    int sshape;     /* -1 no spectrum, 0 spectrum without shape factor, 1 box, 2 sinc */
    int s3d;        /* spectrum over (kz, ky, kx) */
    Py_ssize_t n[3]; /* spectrum size along x, y, z */
    double step[3], sd[3];
    const double *ks, *mt, *e2, *etau, *F;
    const int64_t *it;
    double mtmin[3], mtmax[3], fmax, inv_n[3];
} em_t;

static const double SINC_MARGIN = 1.0 + 1e-9;

/* rint(x) for the conversion to an integer index: round half to even by the 1.5 * 2^52 shift (exact for
   abs(x) < 2^51; larger doubles are integers), without a libm call where SSE4.1 is not assumed */
static inline double rint_fast(double x) {
#if defined(FLT_EVAL_METHOD) && FLT_EVAL_METHOD == 0
    const double shift = 6755399441055744.0; /* 1.5 * 2^52 */
    if (fabs(x) < 2251799813685248.0) {       /* 2^51 */
        const double y = x + shift; /* no -ffast-math here: the compiler keeps both roundings */
        return y - shift;
    }
    return x;
#else
    return rint(x);
#endif
}

/* one axis' parts of an element: voxel factor, spectrum index, sinc bound or mask */
typedef struct {
    double vox, bnd;
    int64_t ix;
    int ok;
} ax_t;

static inline void em_axis(const em_t *m, int a, double k, ax_t *o, int envelope) {
    o->vox = 1.0;
    if (m->vshape && m->vd[a] > 0) {
        const double ka = fabs(k);
        if (m->vshape == 1) {
            const double q = 2.0 / (ka * m->vd[a]);
            o->vox = q < 1.0 ? q : 1.0;
        } else {
            o->vox = ka <= M_PI / m->vd[a] + 1e-9 ? 1.0 : 0.0;
        }
    }
    o->ix = 0;
    o->bnd = 1.0;
    o->ok = 1;
    if (m->sshape >= 0 && (a < 2 || m->s3d)) {
        int64_t v = (int64_t)rint_fast(k / m->step[a]);
        const int64_t n = (int64_t)m->n[a];
        if (v < 0 || v >= n) { /* floor modulo (numpy's %) without an integer division where v is not huge */
            if (v > -((int64_t)1 << 52) && v < ((int64_t)1 << 52)) {
                v -= (int64_t)((double)v * m->inv_n[a]) * n; /* truncated: off by at most one */
                while (v < 0) v += n;
                while (v >= n) v -= n;
            } else {
                v %= n;
                if (v < 0) v += n;
            }
        }
        o->ix = v;
        if (m->sshape == 1) {
            /* |sin x| <= min(1, distance of x to the nearest multiple of pi), that distance computed with an
               absolute allowance far above its rounding and numpy's error of sin */
            const double x = M_PI * (k * m->sd[a] / (2 * M_PI)), ax = fabs(x);
            if (ax > 1.0) {
                /* envelope (1 / ax, non-increasing in abs(k)) for the state's bound over a range of k */
                const double r = envelope ? 1.0 : fabs(x - rint_fast(x * M_1_PI) * M_PI) + (ax + 1.0) * 1e-12;
                o->bnd = (r < 1.0 ? r : 1.0) / ax * SINC_MARGIN;
            } else {
                o->bnd = SINC_MARGIN;
            }
        } else if (m->sshape == 2) {
            o->ok = fabs(k) <= M_PI / m->sd[a];
        }
    }
}

/* the value of element (s, t) from its axes' parts; sinc: the three sinc values (NULL: their upper bounds) */
static inline double em_combine(const em_t *m, const ax_t *x, Py_ssize_t s, Py_ssize_t t, const double *sinc) {
    double env = 1.0;
    if (m->vshape)
        for (int a = 0; a < 3; a++)
            if (m->vd[a] > 0) env = env * x[a].vox;
    if (m->sshape >= 0) {
        double val = m->F[(x[2].ix * m->n[1] + x[1].ix) * m->n[0] + x[0].ix];
        if (m->sshape == 1) {
            const double f0 = sinc ? sinc[0] : x[0].bnd, f1 = sinc ? sinc[1] : x[1].bnd;
            val = val * fabs(f0 * f1);
            if (m->s3d) val = val * fabs(sinc ? sinc[2] : x[2].bnd);
        } else if (m->sshape == 2) {
            val = val * (x[0].ok && x[1].ok ? 1.0 : 0.0);
            if (m->s3d) val = val * (x[2].ok ? 1.0 : 0.0);
        }
        val = val < 1.0 ? val : 1.0; /* np.minimum(val, 1.0) (no NaN here) */
        env = val < env ? val : env; /* np.minimum(e, spec) */
    }
    env = env * m->e2[t];
    return env * m->etau[m->it[s] * m->T + t];
}

/* the parts of element (s, t); the fixed axes' parts (from sample 0) are kept in x between the samples of a state */
static inline void em_parts(const em_t *m, Py_ssize_t s, Py_ssize_t t, ax_t *x, int fixed_too) {
    for (int a = 0; a < 3; a++)
        if (fixed_too || !m->fixed[a]) em_axis(m, a, m->ks[3 * s + a] + m->mt[3 * (m->fixed[a] ? 0 : t) + a], &x[a], 0);
}

/* an upper bound of every element of state s (box spectrum): the voxel factors and the sinc bounds at each axis'
   smallest abs(k) over the window (fl(ks + mt) is monotone in mt; every factor is non-increasing in abs(k)), the
   spectrum's largest value (its row's where ky and the spectrum are 2D and ky is fixed), gmax of the state's tau,
   and a relative margin for the order of the two last products */
static double state_bound(const em_t *m, Py_ssize_t s, const double *gmax, const double *rowmax) {
    ax_t x[3];
    for (int a = 0; a < 3; a++) {
        const double k0 = m->ks[3 * s + a];
        double lo = k0 + m->mt[a], hi = lo;
        if (!m->fixed[a]) {
            lo = k0 + m->mtmin[a];
            hi = k0 + m->mtmax[a];
        }
        const double dist = (lo <= 0 && hi >= 0) ? 0.0 : (fabs(lo) < fabs(hi) ? fabs(lo) : fabs(hi));
        em_axis(m, a, dist, &x[a], 1);
    }
    double env = 1.0;
    if (m->vshape)
        for (int a = 0; a < 3; a++)
            if (m->vd[a] > 0) env = env * x[a].vox;
    double val = m->fmax;
    if (rowmax && !m->s3d && m->fixed[1]) {
        ax_t y;
        em_axis(m, 1, m->ks[3 * s + 1] + m->mt[1], &y, 1);
        val = rowmax[y.ix];
    }
    val = val * fabs(x[0].bnd * x[1].bnd);
    if (m->s3d) val = val * fabs(x[2].bnd);
    if (!(val <= 1.0)) val = 1.0;
    if (val < env) env = val;
    return env * gmax[m->it[s]] * (1.0 + 1e-12);
}

static double em_value(const em_t *m, Py_ssize_t s, Py_ssize_t t, const double *sinc) {
    ax_t x[3];
    em_parts(m, s, t, x, 1);
    return em_combine(m, x, s, t, sinc);
}

/* emission(pass, S, T, fx, fy, fz, vshape, vdx, vdy, vdz, sshape, s3d, nx, ny, nz, stepx, stepy, stepz, sdx, sdy,
            sdz, thr, fmax, arrays) -> int   (fmax: the spectrum's largest value, 1 without a spectrum)
   arrays: ks (S,3), mt (T,3), e2 (T), it (S) i8, etau (U,T), F (flat) or None, best (S) or None, mag (S),
   gmax (U) (the largest e2[t] * etau[u, t] of each tau), rowmax (ny) or None (each spectrum row's largest), then
     pass 1: out (S) f8, tstar (S) i8, ub (S,T) f8, ns (S) i8 -> the number of states ns that need pass 2: out
             holds the maxima (no box spectrum: the values; a state whose bound can change neither its latent
             bound nor its emitter decision, see pdg_graph._Emission.of: 0; else the bound's maximum);
     pass 2: ns (N) i8, tstar (S) i8, ub (S,T) f8, sinc_star (N,3) f8, out (S) f8, cs (S*T) i8 out, ct (S*T) i8 out
             -> the number of candidate elements (out: the value at tstar);
     pass 3: cs (C) i8, ct (C) i8, sinc_c (C,3) f8, out (S) f8 -> 0 (out: the maximum with the candidates). */
static PyObject *emission(PyObject *self, PyObject *args) {
    int pass;
    em_t m;
    double thr;
    PyObject *arrs;
    if (!PyArg_ParseTuple(args, "inniiiidddiinnndddddddd" "O", &pass, &m.S, &m.T, &m.fixed[0], &m.fixed[1],
                          &m.fixed[2], &m.vshape, &m.vd[0], &m.vd[1], &m.vd[2], &m.sshape, &m.s3d, &m.n[0], &m.n[1],
                          &m.n[2], &m.step[0], &m.step[1], &m.step[2], &m.sd[0], &m.sd[1], &m.sd[2], &thr, &m.fmax,
                          &arrs))
        return NULL;
    const Py_ssize_t S = m.S, T = m.T;
    const int nin = 10, nout = pass == 1 ? 4 : (pass == 2 ? 7 : 4);
    if (pass < 1 || pass > 3 || S < 0 || T < 1 || !PyTuple_Check(arrs) || PyTuple_GET_SIZE(arrs) != nin + nout ||
        (m.sshape >= 0 && (m.n[0] < 1 || m.n[1] < 1 || m.n[2] < 1))) {
        PyErr_SetString(PyExc_ValueError, "_pdg_split.emission: bad arguments");
        return NULL;
    }
    buf_t b[18];
    memset(b, 0, sizeof(b));
    const void *p[18];
    Py_ssize_t len[18];
    for (int i = 0; i < nin + nout; i++) {
        PyObject *o = PyTuple_GET_ITEM(arrs, i);
        p[i] = NULL;
        len[i] = 0;
        if (o == Py_None) continue;
        if (get_buf(o, &b[i], i >= nin, 0, "emission") < 0) {
            release(b, 18);
            return NULL;
        }
        p[i] = b[i].b.buf;
        len[i] = b[i].b.len;
    }
    m.ks = (const double *)p[0];
    m.mt = (const double *)p[1];
    m.e2 = (const double *)p[2];
    m.it = (const int64_t *)p[3];
    m.etau = (const double *)p[4];
    m.F = (const double *)p[5];
    const double *best = (const double *)p[6];
    const double *mag = (const double *)p[7];
    const double *gmax = (const double *)p[8];   /* (U) max over t of e2[t] * etau[u, t] */
    const double *rowmax = (const double *)p[9]; /* (ny) max of each spectrum row, or None */
    const Py_ssize_t nF = m.n[0] * m.n[1] * (m.s3d ? m.n[2] : 1);
    int bad = len[0] < S * 24 || len[1] < T * 24 || len[2] < T * 8 || len[3] < S * 8 || !m.etau ||
              (m.sshape >= 0 && len[5] < nF * 8) || (best && len[6] < S * 8) || len[7] < S * 8;
    for (int i = nin; i < nin + nout && !bad; i++) bad = p[i] == NULL;
    for (Py_ssize_t s = 0; s < S && !bad; s++)
        bad = m.it[s] < 0 || (m.it[s] + 1) * T * 8 > len[4] || (m.it[s] + 1) * 8 > len[8];
    if (rowmax && len[9] < m.n[1] * 8) bad = 1;
    const int filter = best != NULL && thr > 0;
    for (int a = 0; a < 3 && !bad; a++) {
        m.mtmin[a] = m.mtmax[a] = m.mt[a];
        for (Py_ssize_t t = 1; t < T; t++) {
            const double v = m.mt[3 * t + a];
            if (v < m.mtmin[a]) m.mtmin[a] = v;
            if (v > m.mtmax[a]) m.mtmax[a] = v;
        }
    }
    for (int a = 0; a < 3; a++) m.inv_n[a] = 1.0 / (double)(m.n[a] > 0 ? m.n[a] : 1);

    Py_ssize_t ret = 0;
    ax_t x[3];
    if (!bad && pass == 1) {
        double *out = (double *)p[10];
        int64_t *tstar = (int64_t *)p[11];
        double *ub = (double *)p[12];
        int64_t *ns = (int64_t *)p[13];
        bad = len[10] < S * 8 || len[11] < S * 8 || len[12] < S * T * 8 || len[13] < S * 8;
        for (Py_ssize_t s = 0; s < S && !bad; s++) {
            if (filter && m.sshape == 1 && state_bound(&m, s, gmax, rowmax) <= best[s] &&
                mag[s] * state_bound(&m, s, gmax, rowmax) < thr) {
                out[s] = 0.0; /* no sample can change anything used: as pdg_graph._Emission.of leaves out states */
                tstar[s] = 0;
                continue;
            }
            double top = 0.0;
            Py_ssize_t tb = 0;
            for (Py_ssize_t t = 0; t < T; t++) {
                em_parts(&m, s, t, x, t == 0);
                const double v = em_combine(&m, x, s, t, NULL);
                ub[s * T + t] = v;
                if (t == 0 || v > top) {
                    top = v;
                    tb = t;
                }
            }
            tstar[s] = tb;
            if (m.sshape != 1) {
                out[s] = top; /* no sinc: the values themselves */
            } else if (filter && top <= best[s] && mag[s] * top < thr) {
                out[s] = 0.0;
            } else {
                out[s] = top;
                ns[ret++] = s;
            }
        }
    } else if (!bad && pass == 2) {
        const int64_t *ns = (const int64_t *)p[10];
        const int64_t *tstar = (const int64_t *)p[11];
        const double *ub = (const double *)p[12];
        const double *sinc = (const double *)p[13];
        double *out = (double *)p[14];
        int64_t *cs = (int64_t *)p[15];
        int64_t *ct = (int64_t *)p[16];
        const Py_ssize_t N = len[10] / 8;
        bad = len[11] < S * 8 || len[12] < S * T * 8 || len[13] < N * 24 || len[14] < S * 8 || len[15] < S * T * 8 ||
              len[16] < S * T * 8;
        for (Py_ssize_t i = 0; i < N && !bad; i++) {
            const Py_ssize_t s = ns[i];
            if (s < 0 || s >= S || tstar[s] < 0 || tstar[s] >= T) {
                bad = 1;
                break;
            }
            const double v = em_value(&m, s, tstar[s], sinc + 3 * i);
            double cut = v; /* an element at or below cut changes nothing that is used */
            if (filter && mag[s] * out[s] < thr && best[s] > cut) cut = best[s];
            out[s] = v;
            for (Py_ssize_t t = 0; t < T; t++) {
                if (t != tstar[s] && ub[s * T + t] > cut) {
                    cs[ret] = s;
                    ct[ret] = t;
                    ret++;
                }
            }
        }
    } else if (!bad) {
        const int64_t *cs = (const int64_t *)p[10];
        const int64_t *ct = (const int64_t *)p[11];
        const double *sinc = (const double *)p[12];
        double *out = (double *)p[13];
        const Py_ssize_t C = len[10] / 8;
        bad = len[11] < C * 8 || len[12] < C * 24 || len[13] < S * 8;
        for (Py_ssize_t c = 0; c < C && !bad; c++) {
            if (cs[c] < 0 || cs[c] >= S || ct[c] < 0 || ct[c] >= T) {
                bad = 1;
                break;
            }
            const double v = em_value(&m, cs[c], ct[c], sinc + 3 * c);
            if (v > out[cs[c]]) out[cs[c]] = v;
        }
    }
    release(b, 18);
    if (bad) {
        PyErr_SetString(PyExc_ValueError, "_pdg_split.emission: bad arrays");
        return NULL;
    }
    return PyLong_FromSsize_t(ret);
}

/* ---- prune ---------------------------------------------------------------------------------------------------- */

/* prune(S, E, Sprev, eq, thr_latent, thr_emit, has_adc, arrays) -> (nS, nE, n_emit, eqn): one interval (n > 0) of
   pdg_graph._prune -- keep the states whose amplitude bound x latent bound reaches thr_latent (and the
   restriction's; the equilibrium always) and that keep an edge from a kept parent; re-index; the kept edges, each
   state's representative (largest candidate estimate, lowest edge on ties) and the emitters.
   arrays: mag, latent (S) f8, restrict (S) bool or None, e_child, e_par, e_kind (E) i8, e_cand (E) f8, prev_keep
   (Sprev) bool, prev_newi (Sprev) i8, emit_b (S) f8, is_z (S) bool, k (S,3) f8, tau (S) f8; out: keep (S) bool,
   newi (S) i8, ec, ep, ek (E) i8, rep (S) i8, rconj (S) bool, emit (S) i8, z (S) bool, k_sel (S,3), tau_sel (S),
   mag_sel (S) f8: 25 arrays. */
static PyObject *prune(PyObject *self, PyObject *args) {
    Py_ssize_t S, E, Sp, eq;
    double thr_l, thr_e;
    int has_adc;
    PyObject *arrs;
    if (!PyArg_ParseTuple(args, "nnnnddpO", &S, &E, &Sp, &eq, &thr_l, &thr_e, &has_adc, &arrs)) return NULL;
    if (S < 1 || E < 0 || Sp < 0 || eq < 0 || eq >= S || !PyTuple_Check(arrs) || PyTuple_GET_SIZE(arrs) != 25) {
        PyErr_SetString(PyExc_ValueError, "_pdg_split.prune: bad arguments");
        return NULL;
    }
    const Py_ssize_t need[25] = {S * 8, S * 8, S,     E * 8, E * 8, E * 8, E * 8, Sp,    Sp * 8,
                                 S * 8, S,     S * 24, S * 8, S,    S * 8, E * 8, E * 8, E * 8,
                                 S * 8, S,     S * 8, S,     S * 24, S * 8, S * 8};
    buf_t b[25];
    memset(b, 0, sizeof(b));
    for (int i = 0; i < 25; i++) {
        PyObject *o = PyTuple_GET_ITEM(arrs, i);
        if (o == Py_None && i == 2) continue; /* restrict */
        if (get_buf(o, &b[i], i >= 13, need[i], "prune") < 0) {
            release(b, 25);
            return NULL;
        }
    }
    const double *mag = (const double *)b[0].b.buf, *latent = (const double *)b[1].b.buf;
    const uint8_t *restr = b[2].held ? (const uint8_t *)b[2].b.buf : NULL;
    const int64_t *e_child = (const int64_t *)b[3].b.buf, *e_par = (const int64_t *)b[4].b.buf;
    const int64_t *e_kind = (const int64_t *)b[5].b.buf;
    const double *e_cand = (const double *)b[6].b.buf;
    const uint8_t *prev_keep = (const uint8_t *)b[7].b.buf;
    const int64_t *prev_newi = (const int64_t *)b[8].b.buf;
    const double *emit_b = (const double *)b[9].b.buf;
    const uint8_t *is_z = (const uint8_t *)b[10].b.buf;
    const double *k = (const double *)b[11].b.buf, *tau = (const double *)b[12].b.buf;
    uint8_t *keep = (uint8_t *)b[13].b.buf;
    int64_t *newi = (int64_t *)b[14].b.buf, *ec = (int64_t *)b[15].b.buf, *ep = (int64_t *)b[16].b.buf;
    int64_t *ek = (int64_t *)b[17].b.buf, *rep = (int64_t *)b[18].b.buf;
    uint8_t *rconj = (uint8_t *)b[19].b.buf;
    int64_t *emit = (int64_t *)b[20].b.buf;
    uint8_t *z = (uint8_t *)b[21].b.buf;
    double *k_sel = (double *)b[22].b.buf, *tau_sel = (double *)b[23].b.buf, *mag_sel = (double *)b[24].b.buf;
    uint8_t *has_in = (uint8_t *)calloc((size_t)S, 1);
    int64_t *best = (int64_t *)malloc((size_t)S * sizeof(int64_t));
    double *bcand = (double *)malloc((size_t)S * sizeof(double));
    if (!has_in || !best || !bcand) {
        free(has_in);
        free(best);
        free(bcand);
        release(b, 25);
        return PyErr_NoMemory();
    }
    int bad = 0;
    for (Py_ssize_t e = 0; e < E && !bad; e++)
        bad = e_child[e] < 0 || e_child[e] >= S || e_par[e] < 0 || e_par[e] >= Sp || e_kind[e] < 0 || e_kind[e] > 5;
    Py_ssize_t nS = 0, nE = 0, nem = 0;
    if (!bad) {
        for (Py_ssize_t s = 0; s < S; s++) keep[s] = (mag[s] * latent[s] >= thr_l && (!restr || restr[s])) || s == eq;
        for (Py_ssize_t e = 0; e < E; e++)
            if (keep[e_child[e]] && prev_keep[e_par[e]]) has_in[e_child[e]] = 1;
        for (Py_ssize_t s = 0; s < S; s++) {
            keep[s] = keep[s] && (has_in[s] || s == eq);
            newi[s] = nS - 1 + keep[s];
            if (keep[s]) {
                z[nS] = is_z[s];
                for (int a = 0; a < 3; a++) k_sel[3 * nS + a] = k[3 * s + a];
                tau_sel[nS] = tau[s];
                mag_sel[nS] = mag[s];
                best[nS] = -1;
                nS++;
            }
        }
        /* the kept edges in edge order; each state's representative: the first edge of largest candidate estimate */
        for (Py_ssize_t e = 0; e < E; e++) {
            if (!(keep[e_child[e]] && prev_keep[e_par[e]])) continue;
            const int64_t c = newi[e_child[e]];
            ec[nE] = c;
            ep[nE] = prev_newi[e_par[e]];
            ek[nE] = e_kind[e];
            if (best[c] < 0 || e_cand[e] > bcand[c]) {
                best[c] = nE;
                bcand[c] = e_cand[e];
            }
            nE++;
        }
        for (Py_ssize_t c = 0; c < nS; c++) {
            rep[c] = best[c] >= 0 ? ep[best[c]] : -1;
            rconj[c] = best[c] >= 0 && (ek[best[c]] == 1 || ek[best[c]] == 4);
        }
        rep[newi[eq]] = -1;
        if (has_adc)
            for (Py_ssize_t s = 0; s < S; s++)
                if (!is_z[s] && mag[s] * emit_b[s] >= thr_e && keep[s]) emit[nem++] = newi[s];
    }
    const Py_ssize_t eqn = bad ? -1 : newi[eq];
    free(has_in);
    free(best);
    free(bcand);
    release(b, 25);
    if (bad) {
        PyErr_SetString(PyExc_ValueError, "_pdg_split.prune: edge index out of range");
        return NULL;
    }
    return Py_BuildValue("nnnn", nS, nE, nem, eqn);
}

static PyMethodDef methods[] = {
    {"prune", prune, METH_VARARGS, "prune(S, E, Sprev, eq, thr_latent, thr_emit, has_adc, arrays) -> (nS, nE, n_emit, eq)"},
    {"unique_bits", unique_bits, METH_VARARGS, "unique_bits(n, (values, uniq, inv)) -> U"},
    {"emission", emission, METH_VARARGS, "emission(pass, S, T, ..., arrays) -> int (see the source)"},
    {"merge", merge, METH_VARARGS, "merge(S, P, min_magnitude, qk, qt, tau_ignored, arrays) -> (E, nU, eq)"},
    {"finish", finish, METH_VARARGS, "finish(nU, P, E, eq, S, min_magnitude, max_states, arrays) -> (nS, nE, eq)"},
    {NULL, NULL, 0, NULL}};
static struct PyModuleDef moddef = {PyModuleDef_HEAD_INIT, "_pdg_split", NULL, -1, methods};
PyMODINIT_FUNC PyInit__pdg_split(void) { return PyModule_Create(&moddef); }
