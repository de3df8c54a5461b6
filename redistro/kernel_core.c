/*
 * redistro._kernels: the per-cycle arithmetic of the I/O paths, fused.
 *
 * A cycle of the simulated chassis or of a robot-level driver is a few
 * dozen tiny operations on 7-vectors and board registers. Written as numpy
 * calls each costs about a microsecond of interpreter and call overhead,
 * which a cold cache (the process wakes after others ran) doubles; the
 * arithmetic itself is nanoseconds. These kernels do the same arithmetic in
 * one call each.
 *
 * They know no layout of their own. Every kernel works on a Plan: named
 * buffers and tables of byte offsets that the owning Python module builds
 * once, in Initialization, from its declared layouts; each kernel declares
 * the names and element types it needs (``signature(kernel)``), and
 * ``Plan(kernel, {name: buffer})`` checks them once. This file holds the
 * Plan, the copies and seqlocks every owner uses, and the module; the
 * kernels sit beside their owners (kernels.h lists them).
 */
#include "kernels.h"

#include <time.h>

static const KernelSet *const SETS[] = {
    &CORE_KERNELS,   &CHASSIS_KERNELS,   &DRIVER_KERNELS, &GUARD_KERNELS, &JOINT_KERNELS,
    &LINALG_KERNELS, &CARTESIAN_KERNELS, &WIRE_KERNELS,   &STEP_KERNELS,
};
#define NSETS ((int)(sizeof(SETS) / sizeof(SETS[0])))

static const Signature *find_signature(const char *name) {
    for (int s = 0; s < NSETS; s++)
        for (int i = 0; i < SETS[s]->nsignatures; i++)
            if (strcmp(SETS[s]->signatures[i].name, name) == 0)
                return &SETS[s]->signatures[i];
    return NULL;
}

static Py_ssize_t itemsize_of(char type) {
    switch (type) {
    case 'd': return 8;
    case 'q': return 8;
    default: return 1;
    }
}

/* -- Plan -- */

static void Plan_dealloc(PlanObject *self) {
    for (int i = 0; i < self->nargs; i++)
        PyBuffer_Release(&self->views[i]);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

/* One argument's buffer, of its element type and aligned (0 on an error). */
static int plan_take(PlanObject *self, const char *kernel, const Arg *arg, PyObject *obj, int i) {
    int flags = PyBUF_WRITABLE | PyBUF_C_CONTIGUOUS | PyBUF_FORMAT;
    if (PyObject_GetBuffer(obj, &self->views[i], flags) < 0)
        return 0;
    self->nargs = i + 1;
    Py_ssize_t size = itemsize_of(arg->type);
    if (arg->type != 'B') {
        const char *f = self->views[i].format ? self->views[i].format : "B";
        char c = f[strlen(f) - 1];
        int ok = self->views[i].itemsize == size &&
                 (arg->type == 'd' ? c == 'd' : (c == 'q' || c == 'l'));
        if (!ok) {
            PyErr_Format(PyExc_TypeError, "kernel %s: argument %s: format %s, expected %s",
                         kernel, arg->name, f, arg->type == 'd' ? "float64" : "int64");
            return 0;
        }
        if ((uintptr_t)self->views[i].buf % 8) {
            PyErr_Format(PyExc_TypeError, "kernel %s: argument %s: not 8-byte aligned", kernel,
                         arg->name);
            return 0;
        }
    }
    self->p[i] = (uint8_t *)self->views[i].buf;
    self->n[i] = self->views[i].len / size;
    return 1;
}

/* Every argument's size rule (kernels.h, Arg), once all are taken. */
static int plan_sizes(PlanObject *self, const char *kernel) {
    const Signature *sig = self->sig;
    Py_ssize_t dims[128] = {0};
    int seen[128] = {0};
    for (int i = 0; i < sig->nargs; i++) {
        const Arg *a = &sig->args[i];
        Py_ssize_t n = self->n[i];
        if (a->size && n != a->size) {
            PyErr_Format(PyExc_ValueError, "kernel %s: argument %s: %zd elements, expected %d",
                         kernel, a->name, n, a->size);
            return 0;
        }
        if (a->row && n % a->row) {
            PyErr_Format(PyExc_ValueError,
                         "kernel %s: argument %s: %zd elements, expected a multiple of %d", kernel,
                         a->name, n, a->row);
            return 0;
        }
        if (a->dim) {
            int d = (unsigned char)a->dim & 127;
            if (n % a->per || (seen[d] && dims[d] != n / a->per)) {
                PyErr_Format(PyExc_ValueError,
                             "kernel %s: argument %s: %zd elements, expected %d per '%c' "
                             "(%zd of them, from the arguments before)",
                             kernel, a->name, n, a->per, a->dim, seen[d] ? dims[d] : n / a->per);
                return 0;
            }
            seen[d] = 1;
            dims[d] = n / a->per;
        }
    }
    return 1;
}

static int Plan_init(PlanObject *self, PyObject *args, PyObject *kwds) {
    const char *kernel;
    PyObject *bufs;
    if (!PyArg_ParseTuple(args, "sO!", &kernel, &PyDict_Type, &bufs))
        return -1;
    const Signature *sig = find_signature(kernel);
    if (sig == NULL) {
        PyErr_Format(PyExc_ValueError, "no kernel %s", kernel);
        return -1;
    }
    for (int i = 0; i < self->nargs; i++)
        PyBuffer_Release(&self->views[i]);
    self->nargs = 0;
    self->sig = sig;
    for (int i = 0; i < sig->nargs; i++) {
        PyObject *obj = PyDict_GetItemString(bufs, sig->args[i].name);
        if (obj == NULL) {
            PyErr_Format(PyExc_KeyError, "kernel %s: argument %s missing", kernel,
                         sig->args[i].name);
            return -1;
        }
        if (!plan_take(self, kernel, &sig->args[i], obj, i))
            return -1;
    }
    if (!plan_sizes(self, kernel)) {
        self->sig = NULL; /* (a plan that failed its check runs nothing) */
        return -1;
    }
    return 0;
}

PyTypeObject PlanType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "redistro._kernels.Plan",
    .tp_basicsize = sizeof(PlanObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Plan_init,
    .tp_dealloc = (destructor)Plan_dealloc,
    .tp_doc = "Named buffers a kernel works on: Plan(kernel, {name: buffer}).",
};

PlanObject *plan_arg(PyObject *obj, const char *kernel) {
    if (!PyObject_TypeCheck(obj, &PlanType)) {
        PyErr_SetString(PyExc_TypeError, "expected a Plan");
        return NULL;
    }
    PlanObject *plan = (PlanObject *)obj;
    if (plan->sig == NULL) {
        PyErr_SetString(PyExc_ValueError, "a plan never initialized");
        return NULL;
    }
    if (strcmp(plan->sig->name, kernel) != 0) {
        PyErr_Format(PyExc_ValueError, "a plan of %s, not %s", plan->sig->name, kernel);
        return NULL;
    }
    return plan;
}

/* -- copies: many fields in one call -- */

enum { CP_SRC, CP_DST, CP_TABLE };

static PyObject *copy(PyObject *mod, PyObject *arg) {
    PlanObject *pl = plan_arg(arg, "copy");
    if (pl == NULL)
        return NULL;
    uint8_t *src = U8(pl, CP_SRC), *dst = U8(pl, CP_DST);
    int64_t *t = I64(pl, CP_TABLE);
    for (Py_ssize_t r = 0; r < pl->n[CP_TABLE] / COPY_TABLE__N; r++, t += COPY_TABLE__N)
        memcpy(dst + t[COPY_TABLE_DST], src + t[COPY_TABLE_SRC], (size_t)t[COPY_TABLE_SIZE]);
    Py_RETURN_NONE;
}

/* -- seqlocks: many blocks in one call -- */

#define SCRATCH 2048

int64_t now_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

void seqlock_write(uint8_t *seq_at, uint8_t *dst, const uint8_t *src, size_t n) {
    volatile uint64_t *seq = (volatile uint64_t *)seq_at;
    uint64_t s = *seq;
    s += s & 1; /* a writer that died mid-write: resume from even */
    *seq = s + 1;
    BARRIER();
    memcpy(dst, src, n);
    BARRIER();
    *seq = s + 2;
}

int seqlock_read(const uint8_t *seq_at, const uint8_t *src, uint8_t *dst, size_t n) {
    const volatile uint64_t *seq = (const volatile uint64_t *)seq_at;
    for (int a = 0; a < ATTEMPTS; a++) {
        uint64_t s1 = *seq;
        if (s1 & 1)
            continue;
        BARRIER();
        memcpy(dst, src, n);
        BARRIER();
        if (*seq == s1)
            return 1;
    }
    return 0;
}

/* seq_read: table rows of SEQ_READ_ROW (core_layout.py) */
enum { SR_SRC, SR_DST, SR_TABLE, SR_TORN };

/* Copy each table row's payload from src to dst: a consistent copy (the
 * sequence counter even and unchanged across the copy) or none at all.
 * torn[i] counts the rows that found no consistent copy in ATTEMPTS tries
 * (their dst stays as it was); returns how many rows did not copy. */
static PyObject *seq_read(PyObject *mod, PyObject *arg) {
    PlanObject *pl = plan_arg(arg, "seq_read");
    if (pl == NULL)
        return NULL;
    uint8_t *src = U8(pl, SR_SRC), *dst = U8(pl, SR_DST);
    int64_t *t = I64(pl, SR_TABLE), *torn = I64(pl, SR_TORN);
    Py_ssize_t rows = pl->n[SR_TABLE] / SEQ_READ_TABLE__N;
    uint8_t scratch[SCRATCH];
    long failed = 0;
    for (Py_ssize_t r = 0; r < rows; r++, t += SEQ_READ_TABLE__N) {
        size_t size = (size_t)t[SEQ_READ_TABLE_SIZE];
        if (size > SCRATCH) {
            PyErr_SetString(PyExc_ValueError, "seq_read: a block larger than 2048 bytes");
            return NULL;
        }
        if (seqlock_read(src + t[SEQ_READ_TABLE_SEQ], src + t[SEQ_READ_TABLE_PAYLOAD], scratch, size))
            memcpy(dst + t[SEQ_READ_TABLE_DST], scratch, size);
        else {
            torn[r] += 1;
            failed += 1;
        }
    }
    return PyLong_FromLong(failed);
}

/* seq_write: table rows of SEQ_WRITE_ROW (core_layout.py) */
enum { SW_DST, SW_SRC, SW_TABLE };

/* Publish each table row's payload from src into its seqlocked block in dst
 * (this process is the blocks' one writer). */
PyObject *seq_write(PyObject *mod, PyObject *arg) {
    PlanObject *pl = plan_arg(arg, "seq_write");
    if (pl == NULL)
        return NULL;
    uint8_t *dst = U8(pl, SW_DST), *src = U8(pl, SW_SRC);
    int64_t *t = I64(pl, SW_TABLE);
    Py_ssize_t rows = pl->n[SW_TABLE] / SEQ_WRITE_TABLE__N;
    for (Py_ssize_t r = 0; r < rows; r++, t += SEQ_WRITE_TABLE__N)
        seqlock_write(dst + t[SEQ_WRITE_TABLE_SEQ], dst + t[SEQ_WRITE_TABLE_PAYLOAD],
                      src + t[SEQ_WRITE_TABLE_SRC], (size_t)t[SEQ_WRITE_TABLE_SIZE]);
    Py_RETURN_NONE;
}

/* -- introspection -- */

static PyObject *signature(PyObject *mod, PyObject *arg) {
    const char *name = PyUnicode_AsUTF8(arg);
    if (name == NULL)
        return NULL;
    const Signature *sig = find_signature(name);
    if (sig == NULL) {
        PyErr_Format(PyExc_ValueError, "no kernel %s", name);
        return NULL;
    }
    PyObject *out = PyTuple_New(sig->nargs);
    if (out == NULL)
        return NULL;
    for (int i = 0; i < sig->nargs; i++) {
        const Arg *a = &sig->args[i];
        char t[2] = {a->type, 0}, d[2] = {a->dim, 0};
        PyObject *arg = Py_BuildValue("(ssiisi)", a->name, t, a->size, a->row, d, a->per);
        if (arg == NULL) {
            Py_DECREF(out);
            return NULL;
        }
        PyTuple_SET_ITEM(out, i, arg);
    }
    return out;
}

static const Signature CORE_SIGNATURES[] = {
    {"copy", ARGS(FREE("src", 'B'), FREE("dst", 'B'), ROWS("table", 'q', COPY_TABLE__N))},
    {"seq_read", ARGS(FREE("src", 'B'), FREE("dst", 'B'), DIM("table", 'q', 'r', SEQ_READ_TABLE__N),
                      DIM("torn", 'q', 'r', 1))},
    {"seq_write", ARGS(FREE("dst", 'B'), FREE("src", 'B'), ROWS("table", 'q', SEQ_WRITE_TABLE__N))},
};

static PyMethodDef CORE_METHODS[] = {
    {"copy", copy, METH_O, "Copy many byte ranges from one buffer to another."},
    {"seq_read", seq_read, METH_O, "Consistent copies of many seqlocked blocks."},
    {"seq_write", seq_write, METH_O, "Publish many seqlocked blocks."},
    {"signature", signature, METH_O,
     "A kernel's arguments: ((name, type, size, row, dim, per), ...) (kernels.h, Arg)."},
    {NULL, NULL, 0, NULL},
};

const KernelSet CORE_KERNELS = {CORE_SIGNATURES, 3, CORE_METHODS};

/* -- the module -- */

static struct PyModuleDef MODULE = {
    PyModuleDef_HEAD_INIT, "redistro._kernels",
    "The per-cycle arithmetic of the I/O paths, fused (see redistro/kernel_core.c).", -1, NULL,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__kernels(void) {
    if (PyType_Ready(&PlanType) < 0)
        return NULL;
    PyObject *m = PyModule_Create(&MODULE);
    if (m == NULL)
        return NULL;
    for (int s = 0; s < NSETS; s++)
        if (PyModule_AddFunctions(m, SETS[s]->methods) < 0)
            goto fail;
    if (PyModule_AddObjectRef(m, "Plan", (PyObject *)&PlanType) < 0)
        goto fail;
    if (answer_kernel_init(m) < 0)
        goto fail;
    if (PyModule_AddStringConstant(m, "LAYOUTS_DIGEST", KERNEL_LAYOUTS_DIGEST) < 0)
        goto fail;
    PyObject *names = PyList_New(0);
    if (names == NULL)
        goto fail;
    for (int s = 0; s < NSETS; s++)
        for (int i = 0; i < SETS[s]->nsignatures; i++) {
            PyObject *name = PyUnicode_FromString(SETS[s]->signatures[i].name);
            if (name == NULL || PyList_Append(names, name) < 0) {
                Py_XDECREF(name);
                Py_DECREF(names);
                goto fail;
            }
            Py_DECREF(name);
        }
    PyObject *tuple = PyList_AsTuple(names);
    Py_DECREF(names);
    if (tuple == NULL || PyModule_AddObject(m, "KERNEL_NAMES", tuple) < 0) {
        Py_XDECREF(tuple);
        goto fail;
    }
    return m;
fail:
    Py_DECREF(m);
    return NULL;
}
