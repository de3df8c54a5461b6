/*
 * A ddm's answer, whole, in the transport's thread (its reference: the
 * ddm's Python answer, Ddm._answer in ddm/worker.py).
 *
 * CompiledAnswer(admit_plan, emit_plan, publish_plan, state, estop_at, lock, put,
 * inbox, fallback, wake, before): the callable a transport that delivers
 * records on a thread of its own (zenoh's) hands each record to, in that
 * thread. Called with a record (a bytes-like object) or a sample (its
 * ``payload.to_bytes()``), it makes a ddm's usual step for it whole. An
 * ESC's: the command admitted (ddm_admit's common case), the node's newest
 * feedback emitted (ddm_emit) and handed to ``put`` as the reply, and every
 * 64th answer the exchange records published (publish_plan, seq_write's).
 * The SSC's (``put`` None): the feedback admitted and the exchange
 * published (its manager watches every robot's updates). It takes a record
 * only while its state (ANSWER_STATE in ddm/wire_layout.py) says it answers, the manager's
 * e-stop byte (Local Data byte estop_at) is clear, ``inbox`` is empty
 * (records queued before it go first), and ``lock`` (the ddm's step lock)
 * is free; anything else goes to ``fallback(raw)`` untouched (the ddm's own
 * step). A torn read of the feedback, or a put that raised, leaves the
 * reply to the ddm: its reply_owed set and ``wake()`` called; its answered
 * counts the records taken. ``before``: None, or a callable run first on
 * every call (a bench's stand-in for the acquisition). The first call in
 * each thread keeps that thread's Python thread state (one
 * PyGILState_Ensure never released), as zenoh's threads otherwise make and
 * free one around every record.
 */
#include "step.h"

#define STATE(f) ANSWER_STATE_##f
#define KEPT_THREADS 8
#define PUBLISH_EVERY 64 /* an ESC's answers between publishing the exchange */
typedef struct {
    PyObject_HEAD
    PyObject *admit, *emit, *publish, *state_obj, *acquire, *release, *put, *inbox, *fallback,
        *wake, *before;
    Py_buffer state;
    Py_ssize_t estop_at;
    int closed;
    int nkept;
    unsigned long kept[KEPT_THREADS];
} CompiledAnswerObject;

static PyObject *STR_PAYLOAD, *STR_TO_BYTES;

static int CompiledAnswer_traverse(CompiledAnswerObject *self, visitproc visit, void *arg) {
    Py_VISIT(self->admit);
    Py_VISIT(self->emit);
    Py_VISIT(self->publish);
    Py_VISIT(self->state_obj);
    Py_VISIT(self->acquire);
    Py_VISIT(self->release);
    Py_VISIT(self->put);
    Py_VISIT(self->inbox);
    Py_VISIT(self->fallback);
    Py_VISIT(self->wake);
    Py_VISIT(self->before);
    return 0;
}

static int CompiledAnswer_clear(CompiledAnswerObject *self) {
    if (self->state_obj != NULL && self->state.obj != NULL)
        PyBuffer_Release(&self->state);
    Py_CLEAR(self->admit);
    Py_CLEAR(self->emit);
    Py_CLEAR(self->publish);
    Py_CLEAR(self->state_obj);
    Py_CLEAR(self->acquire);
    Py_CLEAR(self->release);
    Py_CLEAR(self->put);
    Py_CLEAR(self->inbox);
    Py_CLEAR(self->fallback);
    Py_CLEAR(self->wake);
    Py_CLEAR(self->before);
    return 0;
}

static void CompiledAnswer_dealloc(CompiledAnswerObject *self) {
    PyObject_GC_UnTrack(self);
    CompiledAnswer_clear(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int CompiledAnswer_init(CompiledAnswerObject *self, PyObject *args, PyObject *kwds) {
    PyObject *admit, *emit, *publish, *state, *lock, *put, *inbox, *fallback, *wake, *before;
    Py_ssize_t estop_at;
    if (!PyArg_ParseTuple(args, "O!O!O!OnOOOOOO", &PlanType, &admit, &PlanType, &emit, &PlanType,
                          &publish, &state, &estop_at, &lock, &put, &inbox, &fallback, &wake,
                          &before))
        return -1;
    PlanObject *ap = plan_arg(admit, "ddm_admit");
    PlanObject *ep = ap == NULL ? NULL : plan_arg(emit, "ddm_emit");
    if (ep == NULL || plan_arg(publish, "seq_write") == NULL || !step_plans_ok(ap, ep))
        return -1;
    if (estop_at < 0 || estop_at >= ap->n[DA_LD]) {
        PyErr_SetString(PyExc_ValueError, "CompiledAnswer: the e-stop byte is outside Local Data");
        return -1;
    }
    CompiledAnswer_clear(self);
    if (PyObject_GetBuffer(state, &self->state, PyBUF_WRITABLE | PyBUF_C_CONTIGUOUS) < 0)
        return -1;
    if (self->state.len != STATE(_N) * 8 || (uintptr_t)self->state.buf % 8) {
        PyBuffer_Release(&self->state);
        PyErr_Format(PyExc_ValueError, "CompiledAnswer: the state is %d aligned int64 (ANSWER_STATE)", STATE(_N));
        return -1;
    }
    self->state_obj = Py_NewRef(state);
    self->acquire = PyObject_GetAttrString(lock, "acquire");
    self->release = PyObject_GetAttrString(lock, "release");
    if (self->acquire == NULL || self->release == NULL) {
        CompiledAnswer_clear(self);
        return -1;
    }
    self->admit = Py_NewRef(admit);
    self->emit = Py_NewRef(emit);
    self->publish = Py_NewRef(publish);
    self->put = put == Py_None ? NULL : Py_NewRef(put);
    self->inbox = Py_NewRef(inbox);
    self->fallback = Py_NewRef(fallback);
    self->wake = Py_NewRef(wake);
    self->before = before == Py_None ? NULL : Py_NewRef(before);
    self->estop_at = estop_at;
    self->closed = 0;
    self->nkept = 0;
    return 0;
}

/* The step's lock, not waited for: 1 taken, 0 busy, -1 an error. */
static int answer_try_lock(CompiledAnswerObject *self) {
    PyObject *r = PyObject_CallOneArg(self->acquire, Py_False);
    if (r == NULL)
        return -1;
    int taken = r == Py_True;
    Py_DECREF(r);
    return taken;
}

/* The reply (the node's newest feedback) emitted and put: 1 when it is
 * owed to the ddm (a torn read, a put that raised), -1 an error. */
static int answer_reply(CompiledAnswerObject *self, PlanObject *ep) {
    Py_ssize_t wsize = 0;
    long mask = step_emit(ep, &wsize);
    if (mask == -2)
        return -1;
    if (mask < 0)
        return 1; /* a torn read of the feedback: the ddm reads it again */
    if (mask == 0)
        return 0;
    PyObject *out = PyBytes_FromStringAndSize((const char *)U8(ep, DE_WIRE), wsize);
    PyObject *r = out == NULL ? NULL : PyObject_CallOneArg(self->put, out);
    Py_XDECREF(out);
    if (r == NULL) {
        PyErr_Clear(); /* (a closing session): the ddm's step sends, or learns why */
        return 1;
    }
    Py_DECREF(r);
    return 0;
}

/* Under the step's lock: the record admitted and answered (1; 2 with the
 * reply owed to the ddm), or not taken (0), -1 an error. */
static int answer_locked(CompiledAnswerObject *self, const uint8_t *raw, Py_ssize_t len) {
    int64_t *state = (int64_t *)self->state.buf;
    PlanObject *ap = (PlanObject *)self->admit, *ep = (PlanObject *)self->emit;
    /* (the ddm may have stopped answering meanwhile) */
    if (!state[STATE(ANSWERING)] || U8(ap, DA_LD)[self->estop_at])
        return 0;
    long robot = step_admit(ap, raw, len);
    if (robot < 0)
        return robot == -2 ? -1 : 0;
    state[STATE(ANSWERED)] += 1;
    int owed = self->put == NULL ? 0 : answer_reply(self, ep);
    if (owed < 0)
        return -1;
    if (self->put == NULL || state[STATE(ANSWERED)] % PUBLISH_EVERY == 0) {
        PyObject *r = seq_write(NULL, self->publish);
        if (r == NULL)
            return -1;
        Py_DECREF(r);
    }
    if (owed)
        state[STATE(REPLY_OWED)] = 1;
    return owed ? 2 : 1;
}

/* The usual record taken whole (1), or left to the fallback (0), -1 an error. */
static int answer_record(CompiledAnswerObject *self, const uint8_t *raw, Py_ssize_t len) {
    int64_t *state = (int64_t *)self->state.buf;
    PlanObject *ap = (PlanObject *)self->admit;
    if (self->closed || !state[STATE(ANSWERING)] || U8(ap, DA_LD)[self->estop_at] ||
        PyObject_Size(self->inbox) != 0)
        return 0;
    int taken = answer_try_lock(self);
    if (taken <= 0)
        return taken;
    int done = answer_locked(self, raw, len);
    PyObject *type = NULL, *value = NULL, *tb = NULL;
    if (done < 0)
        PyErr_Fetch(&type, &value, &tb);
    PyObject *r = PyObject_CallNoArgs(self->release);
    if (done < 0) {
        Py_XDECREF(r);
        PyErr_Restore(type, value, tb);
        return -1;
    }
    if (r == NULL)
        return -1;
    Py_DECREF(r);
    if (done == 2) {
        r = PyObject_CallNoArgs(self->wake);
        if (r == NULL)
            return -1;
        Py_DECREF(r);
    }
    return done > 0;
}

static PyObject *CompiledAnswer_call(CompiledAnswerObject *self, PyObject *args, PyObject *kwds) {
    PyObject *arg;
    if (!PyArg_UnpackTuple(args, "CompiledAnswer", 1, 1, &arg))
        return NULL;
    if (self->admit == NULL) {
        PyErr_SetString(PyExc_ValueError, "CompiledAnswer: not initialized");
        return NULL;
    }
    unsigned long me = PyThread_get_thread_ident();
    int known = 0;
    for (int k = 0; k < self->nkept && !known; k++)
        known = self->kept[k] == me;
    if (!known && self->nkept < KEPT_THREADS) {
        self->kept[self->nkept++] = me;
        (void)PyGILState_Ensure(); /* never released: the thread keeps its state */
    }
    PyObject *raw;
    if (PyObject_CheckBuffer(arg))
        raw = Py_NewRef(arg);
    else {
        PyObject *payload = PyObject_GetAttr(arg, STR_PAYLOAD);
        if (payload == NULL)
            return NULL;
        raw = PyObject_CallMethodNoArgs(payload, STR_TO_BYTES);
        Py_DECREF(payload);
        if (raw == NULL)
            return NULL;
    }
    if (self->before != NULL) {
        PyObject *r = PyObject_CallNoArgs(self->before);
        if (r == NULL) {
            Py_DECREF(raw);
            return NULL;
        }
        Py_DECREF(r);
    }
    Py_buffer b;
    if (PyObject_GetBuffer(raw, &b, PyBUF_SIMPLE) < 0) {
        Py_DECREF(raw);
        return NULL;
    }
    int done = answer_record(self, b.buf, b.len);
    PyBuffer_Release(&b);
    if (done < 0) {
        Py_DECREF(raw);
        return NULL;
    }
    if (done) {
        Py_DECREF(raw);
        Py_RETURN_NONE;
    }
    PyObject *r = PyObject_CallOneArg(self->fallback, raw);
    Py_DECREF(raw);
    return r;
}

static PyObject *CompiledAnswer_close(CompiledAnswerObject *self, PyObject *unused) {
    self->closed = 1;
    Py_RETURN_NONE;
}

static PyMethodDef ANSWERER_METHODS[] = {
    {"close", (PyCFunction)(void (*)(void))CompiledAnswer_close, METH_NOARGS,
     "Take no more records (each goes to the fallback)."},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject CompiledAnswerType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "redistro._kernels.CompiledAnswer",
    .tp_basicsize = sizeof(CompiledAnswerObject),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)CompiledAnswer_init,
    .tp_dealloc = (destructor)CompiledAnswer_dealloc,
    .tp_traverse = (traverseproc)CompiledAnswer_traverse,
    .tp_clear = (inquiry)CompiledAnswer_clear,
    .tp_call = (ternaryfunc)CompiledAnswer_call,
    .tp_methods = ANSWERER_METHODS,
    .tp_doc = "An ESC ddm's answer in the transport's thread (see the C source).",
};


int answer_kernel_init(PyObject *module) {
    STR_PAYLOAD = PyUnicode_InternFromString("payload");
    STR_TO_BYTES = PyUnicode_InternFromString("to_bytes");
    if (STR_PAYLOAD == NULL || STR_TO_BYTES == NULL || PyType_Ready(&CompiledAnswerType) < 0)
        return -1;
    return PyModule_AddObjectRef(module, "CompiledAnswer", (PyObject *)&CompiledAnswerType);
}
