/* eyetohand.solve._swarm: the hybrid PSO's per-iteration swarm arithmetic, one pass per step.
 *
 * optimize.hybrid_pso spends, on a cheap fitness, most of an iteration in ~30 NumPy calls on
 * (2, n, D) arrays of a few thousand numbers each, about a microsecond apiece whatever their size.
 * Four of its steps are here as single loops over the swarm: the move (eqs 14, 15, with the clip
 * into the bounds), the two crossover children, the elitist choice among the moved particle and
 * its children, and the personal and global bests.  The random numbers are still drawn by the
 * caller, with the same calls in the same order, so a seed gives the same run.
 *
 * The arithmetic is the NumPy steps' own, in their order (optimize.py), built with -ffp-contract=off
 * (no fused multiply-add): positions, velocities and bests equal theirs bit for bit.  Without a C
 * compiler the package runs those NumPy steps instead.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "_buffers.h"

/* np.clip(x, lo, hi) for float64 (NumPy's _NPY_CLIP: max then min, a NaN passes through). */
static inline double
numpy_clip(double x, double lo, double hi)
{
    const double t = isnan(x) ? x : (x > lo ? x : lo);
    return isnan(t) ? t : (t < hi ? t : hi);
}

PyDoc_STRVAR(move_doc,
"move(x, v, partner, r, w, c1, c2, lower, upper) -> None\n\n"
"Equations (14) and (15) in place, for (n, D) float64 positions ``x`` and velocities ``v``:\n"
"v = ((w v + (c1 r[0]) (partner[0] - x)) + (c2 r[1]) (partner[1] - x)); x = x + v, then clipped\n"
"into ``lower`` .. ``upper`` ((D,) float64 each) unless both are None. ``partner`` and ``r`` are\n"
"(2, n, D) float64: the personal and global bests, and the uniform draws.");

static PyObject *
swarm_move(PyObject *self, PyObject *args)
{
    PyObject *x_o, *v_o, *p_o, *r_o, *lo_o, *hi_o;
    double w, c1, c2;
    if (!PyArg_ParseTuple(args, "OOOOdddOO:move", &x_o, &v_o, &p_o, &r_o, &w, &c1, &c2, &lo_o, &hi_o)) {
        return NULL;
    }
    int clip = lo_o != Py_None || hi_o != Py_None;
    if (clip && (lo_o == Py_None || hi_o == Py_None)) {
        PyErr_SetString(PyExc_ValueError, "lower and upper: both or neither");
        return NULL;
    }
    Py_buffer x, v, p, r, lo, hi;
    if (get_doubles(x_o, &x, 1, -1, "x") < 0) {
        return NULL;
    }
    const Py_ssize_t nd = x.len / 8;
    if (get_doubles(v_o, &v, 1, nd, "v") < 0) {
        goto fail_x;
    }
    if (get_doubles(p_o, &p, 0, 2 * nd, "partner") < 0) {
        goto fail_v;
    }
    if (get_doubles(r_o, &r, 0, 2 * nd, "r") < 0) {
        goto fail_p;
    }
    Py_ssize_t dim = 1;
    if (clip) {
        if (get_doubles(lo_o, &lo, 0, -1, "lower") < 0) {
            goto fail_r;
        }
        dim = lo.len / 8;
        if (dim == 0 || nd % dim != 0) {
            PyErr_SetString(PyExc_ValueError, "lower: expected D float64 values, D dividing x's size");
            PyBuffer_Release(&lo);
            goto fail_r;
        }
        if (get_doubles(hi_o, &hi, 0, dim, "upper") < 0) {
            PyBuffer_Release(&lo);
            goto fail_r;
        }
    }
    double *X = x.buf, *V = v.buf;
    const double *P0 = p.buf, *P1 = (const double *)p.buf + nd;
    const double *R0 = r.buf, *R1 = (const double *)r.buf + nd;
    for (Py_ssize_t i = 0; i < nd; i++) {
        const double xi = X[i];
        const double a = (R0[i] * c1) * (P0[i] - xi);
        const double b = (R1[i] * c2) * (P1[i] - xi);
        double vi = V[i] * w;
        vi = vi + a;
        vi = vi + b;
        V[i] = vi;
        X[i] = xi + vi;
    }
    if (clip) {
        const double *L = lo.buf, *H = hi.buf;
        for (Py_ssize_t i = 0; i < nd; i++) {
            X[i] = numpy_clip(X[i], L[i % dim], H[i % dim]);
        }
        PyBuffer_Release(&hi);
        PyBuffer_Release(&lo);
    }
    PyBuffer_Release(&r);
    PyBuffer_Release(&p);
    PyBuffer_Release(&v);
    PyBuffer_Release(&x);
    Py_RETURN_NONE;
fail_r:
    PyBuffer_Release(&r);
fail_p:
    PyBuffer_Release(&p);
fail_v:
    PyBuffer_Release(&v);
fail_x:
    PyBuffer_Release(&x);
    return NULL;
}

PyDoc_STRVAR(children_doc,
"children(children, x, partner, ends) -> None\n\n"
"The two segment crossovers: children[k, i] is x[i] with columns min(e0, e1) .. max(e0, e1)\n"
"(inclusive, (e0, e1) = ends[k, i]) taken from partner[k, i]. ``children`` and ``partner`` are\n"
"(2, n, D) float64, ``x`` (n, D) float64, ``ends`` (2, n, 2) int64.");

static PyObject *
swarm_children(PyObject *self, PyObject *args)
{
    PyObject *c_o, *x_o, *p_o, *e_o;
    if (!PyArg_ParseTuple(args, "OOOO:children", &c_o, &x_o, &p_o, &e_o)) {
        return NULL;
    }
    Py_buffer c, x, p, e;
    if (get_int64s(e_o, &e, 0, -4, "ends") < 0) {
        return NULL;
    }
    const Py_ssize_t n = e.len / 32;
    if (n == 0) {
        PyErr_SetString(PyExc_ValueError, "ends: expected (2, n, 2) int64 values, n >= 1");
        goto fail_e;
    }
    if (get_doubles(x_o, &x, 0, -n, "x") < 0) {
        goto fail_e;
    }
    const Py_ssize_t dim = x.len / 8 / n;
    if (get_doubles(c_o, &c, 1, 2 * n * dim, "children") < 0) {
        goto fail_x;
    }
    if (get_doubles(p_o, &p, 0, 2 * n * dim, "partner") < 0) {
        goto fail_c;
    }
    double *C = c.buf;
    const double *X = x.buf, *P = p.buf;
    const int64_t *E = e.buf;
    for (Py_ssize_t k = 0; k < 2; k++) {
        for (Py_ssize_t i = 0; i < n; i++) {
            const int64_t e0 = E[2 * (k * n + i)], e1 = E[2 * (k * n + i) + 1];
            const int64_t lo = e0 < e1 ? e0 : e1, hi = e0 < e1 ? e1 : e0;
            double *out = C + (k * n + i) * dim;
            const double *from = P + (k * n + i) * dim, *xi = X + i * dim;
            for (Py_ssize_t j = 0; j < dim; j++) {
                out[j] = (j >= lo && j <= hi) ? from[j] : xi[j];
            }
        }
    }
    PyBuffer_Release(&p);
    PyBuffer_Release(&c);
    PyBuffer_Release(&x);
    PyBuffer_Release(&e);
    Py_RETURN_NONE;
fail_c:
    PyBuffer_Release(&c);
fail_x:
    PyBuffer_Release(&x);
fail_e:
    PyBuffer_Release(&e);
    return NULL;
}

PyDoc_STRVAR(select_doc,
"select(moved_and_children, fx, f) -> None\n\n"
"The elitist choice: for each particle i, the first of (moved, child with the personal best,\n"
"child with the global best) with the least fitness fx[k, i] (as argmin: ties keep the earlier)\n"
"becomes moved_and_children[0, i] (the swarm) and its fitness f[i]. ``moved_and_children`` is\n"
"(3, n, D) float64, ``fx`` (3, n) float64 (no NaN), ``f`` (n,) float64.");

static PyObject *
swarm_select(PyObject *self, PyObject *args)
{
    PyObject *m_o, *fx_o, *f_o;
    if (!PyArg_ParseTuple(args, "OOO:select", &m_o, &fx_o, &f_o)) {
        return NULL;
    }
    Py_buffer m, fx, f;
    if (get_doubles(f_o, &f, 1, -1, "f") < 0) {
        return NULL;
    }
    const Py_ssize_t n = f.len / 8;
    if (n == 0) {
        PyErr_SetString(PyExc_ValueError, "f: expected n >= 1 float64 values");
        goto fail_f;
    }
    if (get_doubles(fx_o, &fx, 0, 3 * n, "fx") < 0) {
        goto fail_f;
    }
    if (get_doubles(m_o, &m, 1, -3 * n, "moved_and_children") < 0) {
        goto fail_fx;
    }
    const Py_ssize_t dim = m.len / 8 / (3 * n);
    double *M = m.buf, *F = f.buf;
    const double *FX = fx.buf;
    for (Py_ssize_t i = 0; i < n; i++) {
        Py_ssize_t k = 0;
        double best = FX[i];
        if (FX[n + i] < best) {
            k = 1;
            best = FX[n + i];
        }
        if (FX[2 * n + i] < best) {
            k = 2;
            best = FX[2 * n + i];
        }
        F[i] = best;
        if (k) {
            memcpy(M + i * dim, M + (k * n + i) * dim, (size_t)dim * sizeof(double));
        }
    }
    PyBuffer_Release(&m);
    PyBuffer_Release(&fx);
    PyBuffer_Release(&f);
    Py_RETURN_NONE;
fail_fx:
    PyBuffer_Release(&fx);
fail_f:
    PyBuffer_Release(&f);
    return NULL;
}

PyDoc_STRVAR(bests_doc,
"bests(pbest_x, pbest_f, x, f) -> int\n\n"
"Each particle's personal best becomes (x[i], f[i]) where f[i] < pbest_f[i]; returns the index of\n"
"the least personal best (as argmin: the first). ``pbest_x`` and ``x`` are (n, D) float64,\n"
"``pbest_f`` and ``f`` (n,) float64 (no NaN).");

static PyObject *
swarm_bests(PyObject *self, PyObject *args)
{
    PyObject *px_o, *pf_o, *x_o, *f_o;
    if (!PyArg_ParseTuple(args, "OOOO:bests", &px_o, &pf_o, &x_o, &f_o)) {
        return NULL;
    }
    Py_buffer px, pf, x, f;
    if (get_doubles(f_o, &f, 0, -1, "f") < 0) {
        return NULL;
    }
    const Py_ssize_t n = f.len / 8;
    if (n == 0) {
        PyErr_SetString(PyExc_ValueError, "f: expected n >= 1 float64 values");
        goto fail_f;
    }
    if (get_doubles(pf_o, &pf, 1, n, "pbest_f") < 0) {
        goto fail_f;
    }
    if (get_doubles(x_o, &x, 0, -n, "x") < 0) {
        goto fail_pf;
    }
    const Py_ssize_t dim = x.len / 8 / n;
    if (get_doubles(px_o, &px, 1, n * dim, "pbest_x") < 0) {
        goto fail_x;
    }
    double *PX = px.buf, *PF = pf.buf;
    const double *X = x.buf, *F = f.buf;
    Py_ssize_t g = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        if (F[i] < PF[i]) {
            PF[i] = F[i];
            memcpy(PX + i * dim, X + i * dim, (size_t)dim * sizeof(double));
        }
        if (PF[i] < PF[g]) {
            g = i;
        }
    }
    PyBuffer_Release(&px);
    PyBuffer_Release(&x);
    PyBuffer_Release(&pf);
    PyBuffer_Release(&f);
    return PyLong_FromSsize_t(g);
fail_x:
    PyBuffer_Release(&x);
fail_pf:
    PyBuffer_Release(&pf);
fail_f:
    PyBuffer_Release(&f);
    return NULL;
}

static PyMethodDef methods[] = {
    {"move", swarm_move, METH_VARARGS, move_doc},
    {"children", swarm_children, METH_VARARGS, children_doc},
    {"select", swarm_select, METH_VARARGS, select_doc},
    {"bests", swarm_bests, METH_VARARGS, bests_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_swarm", "The hybrid PSO's per-iteration swarm arithmetic, one pass per step.",
    -1, methods,
};

PyMODINIT_FUNC
PyInit__swarm(void)
{
    return PyModule_Create(&module);
}
