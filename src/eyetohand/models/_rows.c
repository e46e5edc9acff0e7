/* eyetohand.models._rows: many pixels through a lens-free planar map into (N, 3) rows, in one pass.
 *
 * The maps are a few multiply-adds per point; what costs is memory. NumPy needs a pass per
 * operation and OpenCV writes (N, 2), so the (N, 3) rows cost copies on top; one fused loop here
 * reads each (u, v) once and writes each (x, y, z) once (docs/performance.md).
 *
 * The arithmetic is the NumPy paths' own, in the same order (models/planar.py `_map_chunk`,
 * models/paper.py): built with -ffp-contract=off (no fused multiply-add), so the results are equal
 * to them bit for bit, vectorised or not.  Each call also tells whether every pixel was finite (the
 * caller refuses the batch with its own words when not); the test is on the exponent bits, integer
 * operations the compiler vectorises with the rest.
 *
 * Optional: when it cannot be built, the package falls back to NumPy and OpenCV (models/base.py).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

#include "_buffers.h"

/* 1 when x is NaN or ±inf: its 11 exponent bits are all ones. */
#define NOT_FINITE_BITS(b) (((((b) >> 52) & 0x7ffu) + 1u) >> 11)

static inline __attribute__((always_inline)) int
planar_loop(const double *restrict uv, double *restrict out, const double *restrict h, int projective,
            double z, const double *restrict zs, Py_ssize_t n)
{
    const double h0 = h[0], h1 = h[1], h2 = h[2], h3 = h[3], h4 = h[4], h5 = h[5];
    const double h6 = h[6], h7 = h[7], h8 = h[8];
    uint64_t bad = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        const double u = uv[2 * i], v = uv[2 * i + 1];
        uint64_t bu, bv;
        memcpy(&bu, &uv[2 * i], 8);
        memcpy(&bv, &uv[2 * i + 1], 8);
        bad |= NOT_FINITE_BITS(bu) | NOT_FINITE_BITS(bv);
        double x = (u * h0 + v * h1) + h2;
        double y = (u * h3 + v * h4) + h5;
        if (projective) {
            const double w = (u * h6 + v * h7) + h8;
            x = x / w;
            y = y / w;
        }
        out[3 * i] = x;
        out[3 * i + 1] = y;
        out[3 * i + 2] = zs ? zs[i] : z;
    }
    return bad == 0;
}

static inline __attribute__((always_inline)) int
affine3_loop(const double *restrict uv, double *restrict out, const double *restrict m, double t0,
             double t1, Py_ssize_t n)
{
    const double a0 = m[0], a1 = m[1], a2 = m[2], b0 = m[3], b1 = m[4], b2 = m[5];
    const double c0 = m[6], c1 = m[7], c2 = m[8];
    uint64_t bad = 0;
    for (Py_ssize_t i = 0; i < n; i++) {
        const double du = uv[2 * i] - t0, dv = uv[2 * i + 1] - t1;
        uint64_t bu, bv;
        memcpy(&bu, &uv[2 * i], 8);
        memcpy(&bv, &uv[2 * i + 1], 8);
        bad |= NOT_FINITE_BITS(bu) | NOT_FINITE_BITS(bv);
        out[3 * i] = (du * a0 + dv * a1) + a2;
        out[3 * i + 1] = (du * b0 + dv * b1) + b2;
        out[3 * i + 2] = (du * c0 + dv * c1) + c2;
    }
    return bad == 0;
}

PyDoc_STRVAR(planar_rows_doc,
"planar_rows(uv, h, projective, z, out) -> bool\n\n"
"(N, 2) float64 pixels ``uv`` through the 3x3 px -> mm matrix ``h`` (9 float64, row-major) into the\n"
"(N, 3) float64 rows ``out``: x = (h0 u + h1 v) + h2, y likewise, each divided by\n"
"w = (h6 u + h7 v) + h8 when ``projective``; z is ``z`` (a float) or ``z[i]`` ((N,) float64).\n"
"True when every pixel was finite.");

static PyObject *
planar_rows(PyObject *self, PyObject *args)
{
    PyObject *uv_o, *h_o, *z_o, *out_o;
    int projective;
    if (!PyArg_ParseTuple(args, "OOpOO:planar_rows", &uv_o, &h_o, &projective, &z_o, &out_o)) {
        return NULL;
    }
    Py_buffer uv, h, out, zb;
    int have_zs = !PyFloat_Check(z_o) && !PyLong_Check(z_o);
    double z = 0.0;
    if (!have_zs) {
        z = PyFloat_AsDouble(z_o);
        if (z == -1.0 && PyErr_Occurred()) {
            return NULL;
        }
    }
    if (get_doubles(uv_o, &uv, 0, -2, "uv") < 0) {
        return NULL;
    }
    Py_ssize_t n = uv.len / 16;
    if (get_doubles(h_o, &h, 0, 9, "h") < 0) {
        goto fail_uv;
    }
    if (get_doubles(out_o, &out, 1, 3 * n, "out") < 0) {
        goto fail_h;
    }
    if (have_zs && get_doubles(z_o, &zb, 0, n, "z") < 0) {
        goto fail_out;
    }
    int finite;
    const double *U = uv.buf, *Hm = h.buf, *Z = have_zs ? zb.buf : NULL;
    double *O = out.buf;
    Py_BEGIN_ALLOW_THREADS
    if (projective) {
        finite = Z ? planar_loop(U, O, Hm, 1, 0.0, Z, n) : planar_loop(U, O, Hm, 1, z, NULL, n);
    } else {
        finite = Z ? planar_loop(U, O, Hm, 0, 0.0, Z, n) : planar_loop(U, O, Hm, 0, z, NULL, n);
    }
    Py_END_ALLOW_THREADS
    if (have_zs) {
        PyBuffer_Release(&zb);
    }
    PyBuffer_Release(&out);
    PyBuffer_Release(&h);
    PyBuffer_Release(&uv);
    return PyBool_FromLong(finite);
fail_out:
    PyBuffer_Release(&out);
fail_h:
    PyBuffer_Release(&h);
fail_uv:
    PyBuffer_Release(&uv);
    return NULL;
}

PyDoc_STRVAR(affine3_rows_doc,
"affine3_rows(uv, m, t0, t1, out) -> bool\n\n"
"(N, 2) float64 pixels ``uv`` into the (N, 3) float64 rows ``out`` by a map affine in (u, v):\n"
"out[i, r] = (m[r, 0] (u - t0) + m[r, 1] (v - t1)) + m[r, 2], ``m`` 9 float64, row-major.\n"
"True when every pixel was finite.");

static PyObject *
affine3_rows(PyObject *self, PyObject *args)
{
    PyObject *uv_o, *m_o, *out_o;
    double t0, t1;
    if (!PyArg_ParseTuple(args, "OOddO:affine3_rows", &uv_o, &m_o, &t0, &t1, &out_o)) {
        return NULL;
    }
    Py_buffer uv, m, out;
    if (get_doubles(uv_o, &uv, 0, -2, "uv") < 0) {
        return NULL;
    }
    Py_ssize_t n = uv.len / 16;
    if (get_doubles(m_o, &m, 0, 9, "m") < 0) {
        PyBuffer_Release(&uv);
        return NULL;
    }
    if (get_doubles(out_o, &out, 1, 3 * n, "out") < 0) {
        PyBuffer_Release(&m);
        PyBuffer_Release(&uv);
        return NULL;
    }
    int finite;
    const double *U = uv.buf, *M = m.buf;
    double *O = out.buf;
    Py_BEGIN_ALLOW_THREADS
    finite = affine3_loop(U, O, M, t0, t1, n);
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&out);
    PyBuffer_Release(&m);
    PyBuffer_Release(&uv);
    return PyBool_FromLong(finite);
}

static PyMethodDef methods[] = {
    {"planar_rows", planar_rows, METH_VARARGS, planar_rows_doc},
    {"affine3_rows", affine3_rows, METH_VARARGS, affine3_rows_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_rows", "Lens-free planar maps of many pixels into (N, 3) rows, one pass.",
    -1, methods,
};

PyMODINIT_FUNC
PyInit__rows(void)
{
    return PyModule_Create(&module);
}
