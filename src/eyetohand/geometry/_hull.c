/* eyetohand.geometry._hull: which of many pixels lie outside a convex hull, in one pass (the calibrated
 * region's guard, geometry/region.py `CalibratedRegion.scan`).
 *
 * A pixel is inside when, for every edge k (start a_k, direction e_k), the cross product
 * e_u (v - a_v) - e_v (u - a_u) is >= 0: the region's own test, the same arithmetic in the same order,
 * built with -ffp-contract=off (no fused multiply-add), so every pixel gets the NumPy path's verdict bit
 * for bit (a NaN fails it, as there).  Most pixels are decided by a lookup first: the hull is cut into
 * horizontal bands of equal height, and each band carries a u interval that region.py has proven to lie
 * inside every edge with room to spare for rounding (each rectangle's corners checked with the same
 * cross products and a margin far above their rounding error); a pixel in its band's interval passes
 * every edge test, so it is inside without them (and finite: the intervals are).  The others take the K
 * tests.  Each call also tells whether every pixel was finite (exponent bits, as models/_rows.c).
 * `unproven`: one trapezoid lookup of the hull grown by its margin (`CalibratedRegion.unproven`), the
 * indices of the pixels it does not prove within the margin.
 *
 * Optional: when it cannot be built, region.py runs the K tests in NumPy chunks: the same verdicts.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <stdint.h>
#include <string.h>

#include "_buffers.h"

#define NOT_FINITE_BITS(b) (((((b) >> 52) & 0x7ffu) + 1u) >> 11)

static Py_ssize_t
scan_loop(const double *restrict uv, const double *restrict edges, Py_ssize_t k, const double *restrict bands,
          Py_ssize_t nb, double v0, double inv_h, unsigned char *restrict mask, Py_ssize_t n, int *finite)
{
    Py_ssize_t outside = 0;
    uint64_t bad = 0;
    const double top = (double)nb;
    for (Py_ssize_t i = 0; i < n; i++) {
        const double u = uv[2 * i], v = uv[2 * i + 1];
        const double t = (v - v0) * inv_h;
        int in = 0;
        if (t >= 0.0 && t < top) { /* in a band, and in its (finite) interval: finite, and inside */
            const Py_ssize_t b = (Py_ssize_t)t;
            in = u >= bands[2 * b] && u <= bands[2 * b + 1];
        }
        if (!in) { /* the K tests; the finiteness of the pixels that get here */
            uint64_t bu, bv;
            memcpy(&bu, &uv[2 * i], 8);
            memcpy(&bv, &uv[2 * i + 1], 8);
            bad |= NOT_FINITE_BITS(bu) | NOT_FINITE_BITS(bv);
            in = 1;
            for (Py_ssize_t j = 0; j < k; j++) {
                const double *e = edges + 4 * j; /* a_u, a_v, e_u, e_v */
                const double c = e[2] * (v - e[1]) - e[3] * (u - e[0]);
                if (!(c >= 0.0)) {
                    in = 0;
                    break;
                }
            }
        }
        mask[i] = (unsigned char)!in;
        outside += !in;
    }
    *finite = bad == 0;
    return outside;
}

/* The pixels a trapezoid lookup does not prove: for v in band b = floor((v - v0) * inv_h), 0 <= b < B,
 * with row (v_b, L, l, R, r) of `rows`, a pixel with L + l (v - v_b) <= u <= R + r (v - v_b) is proven
 * (region.py `_chord_bands` proves each trapezoid inside a polygon); the indices of the
 * others (NaN and infinities among them) are written to `idx`.  No branch on the data: every pixel's
 * index is stored and the count moves on only for the unproven, so a random order of pixels costs no
 * mispredicted branches (this loop bounds the guarded many-point path: docs/performance.md). */
static Py_ssize_t
unproven_loop(const double *restrict uv, const double *restrict rows, Py_ssize_t nb, double v0, double inv_h,
              int64_t *restrict idx, Py_ssize_t n)
{
    Py_ssize_t c = 0;
    const double top = (double)nb;
    for (Py_ssize_t i = 0; i < n; i++) {
        const double u = uv[2 * i], v = uv[2 * i + 1];
        const double t = (v - v0) * inv_h;
        const int in_t = (t >= 0.0) & (t < top);
        const double *r = rows + 5 * (in_t ? (Py_ssize_t)t : 0); /* v_b, L, l, R, r */
        const double dv = v - r[0];
        const int ok = in_t & (u >= r[1] + r[2] * dv) & (u <= r[3] + r[4] * dv);
        idx[c] = (int64_t)i;
        c += !ok;
    }
    return c;
}

PyDoc_STRVAR(unproven_doc,
"unproven(uv, rows, v0, inv_h, idx) -> count\n\n"
"The (N, 2) float64 pixels ``uv`` outside their band's trapezoid, (B, 5) float64 ``rows`` (v_b, L, l,\n"
"R, r) for band b = floor((v - v0) * inv_h): a pixel with L + l (v - v_b) <= u <= R + r (v - v_b) is\n"
"proven. Their indices, in order, into the first ``count`` items of ``idx`` (N int64).");

static PyObject *
unproven(PyObject *self, PyObject *args)
{
    PyObject *uv_o, *bands_o, *idx_o;
    double v0, inv_h;
    if (!PyArg_ParseTuple(args, "OOddO:unproven", &uv_o, &bands_o, &v0, &inv_h, &idx_o)) {
        return NULL;
    }
    Py_buffer uv, bands, idx;
    if (get_doubles(uv_o, &uv, 0, -2, "uv") < 0) {
        return NULL;
    }
    Py_ssize_t n = uv.len / 16;
    if (get_doubles(bands_o, &bands, 0, -5, "rows") < 0) {
        PyBuffer_Release(&uv);
        return NULL;
    }
    if (get_items(idx_o, &idx, 1, n, "idx", "ql", "int64") < 0) {
        PyBuffer_Release(&bands);
        PyBuffer_Release(&uv);
        return NULL;
    }
    Py_ssize_t count;
    const double *U = uv.buf, *B = bands.buf;
    int64_t *I = idx.buf;
    Py_ssize_t nb = bands.len / 40;
    Py_BEGIN_ALLOW_THREADS
    count = unproven_loop(U, B, nb, v0, inv_h, I, n);
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&idx);
    PyBuffer_Release(&bands);
    PyBuffer_Release(&uv);
    return PyLong_FromSsize_t(count);
}

PyDoc_STRVAR(scan_doc,
"scan(uv, edges, bands, v0, inv_h, mask) -> (outside, finite)\n\n"
"(N, 2) float64 pixels ``uv`` against the convex hull of (K, 4) float64 ``edges`` rows (a_u, a_v, e_u,\n"
"e_v): ``mask[i]`` (N uint8) is 1 where some e_u (v - a_v) - e_v (u - a_u) is not >= 0, else 0.\n"
"``bands`` (B, 2) float64: for v in band b = floor((v - v0) * inv_h), 0 <= b < B, a pixel with\n"
"bands[b, 0] <= u <= bands[b, 1] is inside without the tests (the caller proves it). Returns how many\n"
"pixels are outside and whether every pixel was finite.");

static PyObject *
scan(PyObject *self, PyObject *args)
{
    PyObject *uv_o, *edges_o, *bands_o, *mask_o;
    double v0, inv_h;
    if (!PyArg_ParseTuple(args, "OOOddO:scan", &uv_o, &edges_o, &bands_o, &v0, &inv_h, &mask_o)) {
        return NULL;
    }
    Py_buffer uv, edges, bands, mask;
    if (get_doubles(uv_o, &uv, 0, -2, "uv") < 0) {
        return NULL;
    }
    Py_ssize_t n = uv.len / 16;
    if (get_doubles(edges_o, &edges, 0, -4, "edges") < 0) {
        goto fail_uv;
    }
    if (get_doubles(bands_o, &bands, 0, -2, "bands") < 0) {
        goto fail_edges;
    }
    if (PyObject_GetBuffer(mask_o, &mask, PyBUF_C_CONTIGUOUS | PyBUF_WRITABLE) < 0) {
        goto fail_bands;
    }
    if (mask.len != n || mask.itemsize != 1) {
        PyErr_Format(PyExc_ValueError, "mask: expected %zd one-byte items", n);
        goto fail_mask;
    }
    int finite;
    Py_ssize_t outside;
    const double *U = uv.buf, *E = edges.buf, *B = bands.buf;
    unsigned char *M = mask.buf;
    Py_ssize_t k = edges.len / 32, nb = bands.len / 16;
    Py_BEGIN_ALLOW_THREADS
    outside = scan_loop(U, E, k, B, nb, v0, inv_h, M, n, &finite);
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&mask);
    PyBuffer_Release(&bands);
    PyBuffer_Release(&edges);
    PyBuffer_Release(&uv);
    return Py_BuildValue("(nN)", outside, PyBool_FromLong(finite));
fail_mask:
    PyBuffer_Release(&mask);
fail_bands:
    PyBuffer_Release(&bands);
fail_edges:
    PyBuffer_Release(&edges);
fail_uv:
    PyBuffer_Release(&uv);
    return NULL;
}

static PyMethodDef methods[] = {
    {"scan", scan, METH_VARARGS, scan_doc},
    {"unproven", unproven, METH_VARARGS, unproven_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_hull", "Many pixels against a convex hull, one pass.", -1, methods,
};

PyMODINIT_FUNC
PyInit__hull(void)
{
    return PyModule_Create(&module);
}
