/* The buffer checks of eyetohand's compiled loops (_rows.c, _swarm.c): C-contiguous arrays of 8-byte
 * items of one kind, with a known count, refused with TypeError/ValueError naming the argument. */
#ifndef EYETOHAND_BUFFERS_H
#define EYETOHAND_BUFFERS_H

#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <string.h>

/* `view` of `obj`: C-contiguous, 8-byte items of struct format `fmt` ("d" float64; "q" or "l"
 * int64), `count` items (count < 0: any multiple of -count); `kind` names them in errors. */
static int
get_items(PyObject *obj, Py_buffer *view, int writable, Py_ssize_t count, const char *what,
          const char *fmt, const char *kind)
{
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(obj, view, flags) < 0) {
        PyErr_Clear();
        PyErr_Format(PyExc_TypeError, "%s: expected a C-contiguous%s %s array", what,
                     writable ? " writable" : "", kind);
        return -1;
    }
    const char *f = view->format ? view->format : "B";
    if (f[0] == '<' || f[0] == '=' || f[0] == '@') {
        f++;
    }
    Py_ssize_t items = view->len / 8;
    int ok = view->itemsize == 8 && view->len % 8 == 0 && f[0] != '\0' && f[1] == '\0' &&
             strchr(fmt, f[0]) != NULL;
    if (ok) {
        ok = count >= 0 ? items == count : items % (-count) == 0;
    }
    if (!ok) {
        PyBuffer_Release(view);
        if (count >= 0) {
            PyErr_Format(PyExc_ValueError, "%s: expected %zd %s values", what, count, kind);
        } else {
            PyErr_Format(PyExc_ValueError, "%s: expected %s values in groups of %zd", what, kind, -count);
        }
        return -1;
    }
    return 0;
}

static inline int
get_doubles(PyObject *obj, Py_buffer *view, int writable, Py_ssize_t count, const char *what)
{
    return get_items(obj, view, writable, count, what, "d", "float64");
}

static inline int
get_int64s(PyObject *obj, Py_buffer *view, int writable, Py_ssize_t count, const char *what)
{
    return get_items(obj, view, writable, count, what, sizeof(long) == 8 ? "ql" : "q", "int64");
}

#endif
