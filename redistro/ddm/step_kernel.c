/*
 * A ddm's exchange in compiled code (its reference: the ddm's Python path,
 * ddm/worker.py and ddm/record.py; the plans are built in ddm/kernel_path.py):
 * the common case of a record admitted and of a record emitted, and the
 * stream sockets' receive and send around them.
 *
 * Anything else (a record to refuse or count, an e-stop, the first record
 * of a link, a torn read) is left untouched for the Python path, which
 * handles every case; the two share one state (the plans' rows).
 */
#include "step.h"

#include <errno.h>
#include <sys/socket.h>

#define AP(f) DDM_ADMIT_PARAMS_##f
#define AR(f) DDM_ADMIT_ROWS_##f
#define AS(f) DDM_ADMIT_STATE_##f
#define EP(f) DDM_EMIT_PARAMS_##f
#define ER(f) DDM_EMIT_ROWS_##f

#define MAX_ROBOTS 62     /* a robot a bit in a long */
#define MAX_RECORDS 64    /* records a receive admits (a bit each) */
#define SOURCE_SIZE 16    /* a record's source name */

enum { DS_WIRE, DS_FDS, DS_STATUS, DS_REPLY }; /* ddm_send's arguments */

/* An offset and a width that lie inside a buffer of n bytes. */
static inline int inside(int64_t at, int64_t width, Py_ssize_t n) {
    return at >= 0 && width >= 0 && at + width <= n;
}

/* -- admission -- */

/* The admit plan's codec, read, and its parameters inside the record, the
 * exchange record and Local Data (else an error is set, 0). */
static int admit_plan_ok(PlanObject *pl, Codec *c) {
    if (!codec_read(U8(pl, DA_CODEC), c))
        return 0;
    const int64_t *P = I64(pl, DA_PARAMS);
    Py_ssize_t nrows = pl->n[DA_ROWS] / DDM_ADMIT_ROWS__N, body = c->body;
    int ok = inside(P[AP(PAYLOAD_AT)], P[AP(SIZE)], body) && inside(P[AP(H_MAGIC)], 4, body) &&
             inside(P[AP(H_VERSION)], 2, body) && inside(P[AP(H_KIND)], 1, body) &&
             inside(P[AP(H_ROBOT)], 1, body) && inside(P[AP(H_SOURCE)], SOURCE_SIZE, body) &&
             inside(P[AP(H_SEQ)], 8, body) && inside(P[AP(H_STAMP)], 8, body) &&
             inside(P[AP(H_ESTOP)], 1, body) && P[AP(SIZE)] >= 8 &&
             pl->n[DA_EX] == nrows * P[AP(EX_SIZE)] &&
             inside(P[AP(EX_UPDATES)], 8, P[AP(EX_SIZE)]) &&
             inside(P[AP(EX_LAST)], 8, P[AP(EX_SIZE)]) &&
             inside(P[AP(EX_FRESH)], 1, P[AP(EX_SIZE)]) &&
             (P[AP(DELIV_SEQ)] < 0 ||
              (inside(P[AP(SENT_SEQ)], 8, pl->n[DA_LD]) && inside(P[AP(SENT_PAY)], 8, pl->n[DA_LD]) &&
               inside(P[AP(DELIV_SEQ)], 8, pl->n[DA_LD]) &&
               inside(P[AP(DELIV_PAY)], 16, pl->n[DA_LD])));
    if (!ok)
        PyErr_SetString(PyExc_ValueError,
                        "ddm_admit: parameters outside the record, exchange or Local Data");
    return ok;
}

/* The row of robot gid that its source claimed, or -1. */
static Py_ssize_t claimed_row(PlanObject *pl, const int64_t *P, const uint8_t *r) {
    Py_ssize_t nrows = pl->n[DA_ROWS] / DDM_ADMIT_ROWS__N;
    for (Py_ssize_t i = 0; i < nrows; i++) {
        const int64_t *row = I64(pl, DA_ROWS) + i * DDM_ADMIT_ROWS__N;
        if (row[AR(GID)] != r[P[AP(H_ROBOT)]])
            continue;
        if (!row[AR(CLAIMED)] ||
            memcmp(r + P[AP(H_SOURCE)], U8(pl, DA_SRC) + SOURCE_SIZE * i, SOURCE_SIZE) != 0)
            return -1;
        return i;
    }
    return -1;
}

/* An admitted record's effects: its payload into the robot's block, the
 * exchange counted, an ESC's starving index paid back, the latency. */
static void admitted(PlanObject *pl, const int64_t *P, int64_t *row, uint8_t *ex, const uint8_t *r) {
    uint8_t *ld = U8(pl, DA_LD);
    int64_t now = now_ns();
    seqlock_write(ld + row[AR(SEQ_OFF)], ld + row[AR(PAY_OFF)], r + P[AP(PAYLOAD_AT)],
                  (size_t)P[AP(SIZE)]);
    st_u64(ex + P[AP(EX_UPDATES)], ld_u64(ex + P[AP(EX_UPDATES)]) + 1);
    st_u64(ex + P[AP(EX_LAST)], (uint64_t)now);
    int64_t *state = I64(pl, DA_STATE);
    if (P[AP(DELIV_SEQ)] >= 0) {
        uint8_t counter[16];
        if (seqlock_read(ld + P[AP(SENT_SEQ)], ld + P[AP(SENT_PAY)], counter, 8)) {
            st_u64(counter + 8, (uint64_t)now);
            seqlock_write(ld + P[AP(DELIV_SEQ)], ld + P[AP(DELIV_PAY)], counter, 16);
        }
        int64_t pstamp = (int64_t)ld_u64(r + P[AP(PAYLOAD_AT)]);
        Py_ssize_t ring = pl->n[DA_LAT];
        if (ring > 0 && 0 < pstamp && pstamp <= now) {
            I64(pl, DA_LAT)[state[AS(LATENCY_COUNT)] % ring] = now - pstamp;
            state[AS(LATENCY_COUNT)] += 1;
        }
    }
    state[AS(TAKEN)] += 1;
}

/* The common case of one record: the local robot whose block took it, or
 * -1 (nothing changed: the Python path decides). It takes a record only if
 * it is sound (size, magic, version, crc32, tag), of the kind this ddm
 * receives, for one of its robots, without an e-stop, from the source that
 * robot's row has claimed (the row's last seq and stamp are that source's
 * admission state), newer than the last in seq and stamp, and the robot's
 * exchange already fresh. -2: libcrypto failed (an error is set). */
static long admit_record(PlanObject *pl, const Codec *c, const uint8_t *r, Py_ssize_t len) {
    const int64_t *P = I64(pl, DA_PARAMS);
    if (len != c->body + TAG_SIZE || ld_u32(r + P[AP(H_MAGIC)]) != (uint32_t)P[AP(MAGIC)] ||
        (r[P[AP(H_VERSION)]] | r[P[AP(H_VERSION)] + 1] << 8) != P[AP(VERSION)] ||
        r[P[AP(H_KIND)]] != P[AP(KIND)] || r[P[AP(H_ESTOP)]] != 0)
        return -1;
    Py_ssize_t i = claimed_row(pl, P, r);
    if (i < 0)
        return -1;
    int64_t *row = I64(pl, DA_ROWS) + i * DDM_ADMIT_ROWS__N;
    uint8_t *ex = U8(pl, DA_EX) + i * P[AP(EX_SIZE)];
    if (!ex[P[AP(EX_FRESH)]])
        return -1;
    uint64_t seq = ld_u64(r + P[AP(H_SEQ)]);
    int64_t stamp = (int64_t)ld_u64(r + P[AP(H_STAMP)]);
    if (seq <= (uint64_t)row[AR(LAST_SEQ)] || stamp <= row[AR(LAST_STAMP)])
        return -1; /* a drop to count: the Python path */
    int why = codec_check(c, r);
    if (why)
        return why < 0 ? -2 : -1;
    row[AR(LAST_SEQ)] = (int64_t)seq;
    row[AR(LAST_STAMP)] = stamp;
    admitted(pl, P, row, ex, r);
    return (long)i;
}

/* Whole records received into buf (got bytes) offered to admit_record: the
 * mask of those taken into the state's mask (0: not whole records). -1:
 * libcrypto failed. */
static int admit_received(PlanObject *pl, const Codec *c, const uint8_t *buf, Py_ssize_t cap,
                          ssize_t got) {
    Py_ssize_t size = c->body + TAG_SIZE;
    int64_t *state = I64(pl, DA_STATE);
    state[AS(MASK)] = 0;
    if (got <= 0 || got % size || got >= cap || got / size > MAX_RECORDS)
        return 0;
    uint64_t mask = 0;
    for (Py_ssize_t k = 0; k < got / size; k++) {
        long i = admit_record(pl, c, buf + k * size, size);
        if (i == -2)
            return -1;
        if (i >= 0)
            mask |= (uint64_t)1 << k;
    }
    state[AS(MASK)] = (int64_t)mask;
    return 0;
}

/* ddm_admit(plan, record) -> the local robot whose block took the record,
 * or -1 (the Python path decides). */
static PyObject *ddm_admit(PyObject *mod, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "ddm_admit(plan, record)");
        return NULL;
    }
    Codec c;
    PlanObject *pl = plan_arg(args[0], "ddm_admit");
    Py_buffer b;
    if (pl == NULL || !admit_plan_ok(pl, &c) || PyObject_GetBuffer(args[1], &b, PyBUF_SIMPLE) < 0)
        return NULL;
    long result = admit_record(pl, &c, b.buf, b.len);
    PyBuffer_Release(&b);
    return result == -2 ? NULL : PyLong_FromLong(result);
}

/* ddm_recv(admit_plan, rx, fd) -> one non-blocking recv(2) from the stream
 * socket fd into the writable buffer rx: the bytes received (0: the peer
 * closed) or -errno (-EAGAIN: nothing). When they are whole records (rx
 * not filled to the brim, at most 64), each is offered to ddm_admit's
 * common case; the plan's state mask has bit k set for each record k
 * admitted, the others stay in rx for the caller. */
static PyObject *ddm_recv(PyObject *mod, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "ddm_recv(plan, rx, fd)");
        return NULL;
    }
    Codec c;
    PlanObject *pl = plan_arg(args[0], "ddm_admit");
    if (pl == NULL || !admit_plan_ok(pl, &c))
        return NULL;
    int fd = (int)PyLong_AsLong(args[2]);
    Py_buffer b;
    if ((fd == -1 && PyErr_Occurred()) || PyObject_GetBuffer(args[1], &b, PyBUF_WRITABLE) < 0)
        return NULL;
    ssize_t got = recv(fd, b.buf, (size_t)b.len, MSG_DONTWAIT);
    long result = got < 0 ? -errno : (long)got;
    int failed = admit_received(pl, &c, b.buf, b.len, got);
    PyBuffer_Release(&b);
    return failed ? NULL : PyLong_FromLong(result);
}

/* -- emission -- */

/* The emit plan's codec, read, and its sizes sound (else an error is set, 0). */
static int emit_plan_ok(PlanObject *pl, Codec *c) {
    if (!codec_read(U8(pl, DE_CODEC), c))
        return 0;
    const int64_t *P = I64(pl, DE_PARAMS);
    Py_ssize_t nrows = pl->n[DE_ROWS] / DDM_EMIT_ROWS__N, size = P[EP(SIZE)];
    int ok = nrows <= MAX_ROBOTS && size >= 8 && pl->n[DE_OUT] == nrows * size &&
             pl->n[DE_WIRE] == nrows * (c->body + TAG_SIZE) &&
             inside(P[EP(PAYLOAD_AT)], size, c->body) && inside(P[EP(SEQSRC_AT)], 8, size) &&
             inside(P[EP(H_SEQ)], 8, c->body) && inside(P[EP(H_STAMP)], 8, c->body) &&
             inside(P[EP(H_ESTOP)], 1, c->body) && pl->n[DE_EX] == nrows * P[EP(EX_SIZE)] &&
             inside(P[EP(EX_SENT)], 8, P[EP(EX_SIZE)]);
    if (!ok)
        PyErr_SetString(PyExc_ValueError, "ddm_emit: a plan of the wrong sizes or offsets");
    return ok;
}

/* One robot's new record encoded and sealed into w (0: libcrypto failed). */
static int encode(PlanObject *pl, const Codec *c, int64_t *row, const uint8_t *out, uint8_t *w,
                  uint8_t *ex) {
    const int64_t *P = I64(pl, DE_PARAMS);
    row[ER(SEQ)] += 1;
    st_u64(w + P[EP(H_SEQ)], (uint64_t)row[ER(SEQ)]);
    st_u64(w + P[EP(H_STAMP)], (uint64_t)now_ns());
    w[P[EP(H_ESTOP)]] = 0;
    memcpy(w + P[EP(PAYLOAD_AT)], out, (size_t)P[EP(SIZE)]);
    if (!codec_seal(c, w))
        return 0;
    st_u64(ex + P[EP(EX_SENT)], ld_u64(ex + P[EP(EX_SENT)]) + 1);
    return 1;
}

/* ddm_emit's work over a valid plan: the mask of the robots whose wire row
 * holds a new record, -1 a torn read, -2 libcrypto failed (an error set).
 * Every row is read before any is encoded: a torn read of one row (its
 * writer inside its write) leaves every row's state as it was, so that the
 * Python path, reading again, sends them all (a row encoded before a later
 * one tore would be counted sent, and never sent). */
static long emit_rows(PlanObject *pl, const Codec *c) {
    const int64_t *P = I64(pl, DE_PARAMS);
    Py_ssize_t nrows = pl->n[DE_ROWS] / DDM_EMIT_ROWS__N, size = P[EP(SIZE)];
    Py_ssize_t wsize = c->body + TAG_SIZE;
    uint8_t *ld = U8(pl, DE_LD);
    long mask = 0;
    for (Py_ssize_t i = 0; i < nrows; i++) {
        const int64_t *row = I64(pl, DE_ROWS) + i * DDM_EMIT_ROWS__N;
        uint8_t *out = U8(pl, DE_OUT) + i * size;
        if (!seqlock_read(ld + row[ER(SEQ_OFF)], ld + row[ER(PAY_OFF)], out, (size_t)size))
            return -1;
    }
    for (Py_ssize_t i = 0; i < nrows; i++) {
        int64_t *row = I64(pl, DE_ROWS) + i * DDM_EMIT_ROWS__N;
        uint8_t *out = U8(pl, DE_OUT) + i * size;
        int64_t produced = (int64_t)ld_u64(out + P[EP(SEQSRC_AT)]);
        if (produced == 0 || produced == row[ER(LAST_OUT)])
            continue;
        row[ER(LAST_OUT)] = produced;
        if (!encode(pl, c, row, out, U8(pl, DE_WIRE) + i * wsize, U8(pl, DE_EX) + i * P[EP(EX_SIZE)]))
            return -2;
        mask |= 1L << i;
    }
    return mask;
}

/* ddm_emit(plan) -> a bit mask of the robots whose wire row holds a new
 * record to send, or -1 (a torn read: the Python path reads again). For
 * each robot the out block (its node's command or feedback) is read into
 * the out record; a newly produced one (seq_src not 0 and not the last
 * sent) is encoded behind the row's next seq, now, no e-stop, and sealed;
 * the exchange record counts it sent. */
static PyObject *ddm_emit(PyObject *mod, PyObject *arg) {
    Codec c;
    PlanObject *pl = plan_arg(arg, "ddm_emit");
    if (pl == NULL || !emit_plan_ok(pl, &c))
        return NULL;
    long mask = emit_rows(pl, &c);
    return mask == -2 ? NULL : PyLong_FromLong(mask);
}

/* -- sending -- */

/* The send plan's rows (robots), or 0 (an error is set). */
static Py_ssize_t send_rows_ok(PlanObject *pl) {
    Py_ssize_t n = pl->n[DS_FDS];
    if (n < 1 || n > MAX_ROBOTS || pl->n[DS_WIRE] % n || pl->n[DS_WIRE] == 0) {
        PyErr_SetString(PyExc_ValueError, "ddm_send: a plan of the wrong sizes");
        return 0;
    }
    return n;
}

/* The records of mask sent, each with one non-blocking send(2) to its
 * row's socket (-1: none), rows in order or reversed; status[i]: the
 * bytes sent or -errno. Returns the bits of those not sent whole. */
static long send_rows(PlanObject *pl, Py_ssize_t n, long mask, long reverse) {
    Py_ssize_t size = pl->n[DS_WIRE] / n;
    long trouble = 0;
    for (Py_ssize_t k = 0; k < n; k++) {
        Py_ssize_t i = reverse ? n - 1 - k : k;
        if (!(mask >> i & 1))
            continue;
        int fd = (int)I64(pl, DS_FDS)[i];
        int64_t *status = I64(pl, DS_STATUS) + i;
        if (fd < 0) {
            *status = 0;
            trouble |= 1L << i;
            continue;
        }
        ssize_t sent =
            send(fd, U8(pl, DS_WIRE) + i * size, (size_t)size, MSG_DONTWAIT | MSG_NOSIGNAL);
        *status = sent < 0 ? -errno : (int64_t)sent;
        if (sent != size)
            trouble |= 1L << i;
    }
    return trouble;
}

/* ddm_send(plan, mask, reverse) -> the bits of the records not sent whole
 * (no socket, a full buffer, an error, a short send): the records ddm_emit
 * encoded (bits of mask) sent, see send_rows. */
static PyObject *ddm_send(PyObject *mod, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "ddm_send(plan, mask, reverse)");
        return NULL;
    }
    PlanObject *pl = plan_arg(args[0], "ddm_send");
    if (pl == NULL)
        return NULL;
    long mask = PyLong_AsLong(args[1]);
    long reverse = PyLong_AsLong(args[2]);
    if (PyErr_Occurred())
        return NULL;
    Py_ssize_t n = send_rows_ok(pl);
    return n == 0 ? NULL : PyLong_FromLong(send_rows(pl, n, mask, reverse));
}

/* -- an ESC ddm's receive and reply in one call -- */

#define DDM_REPLIED ((int64_t)1 << 40)

/* ddm_reply(admit_plan, emit_plan, send_plan, rx, fd) -> int: ddm_recv,
 * and when every record received was admitted, ddm_emit and ddm_send (the
 * node's new feedback sealed and sent back on fd, the socket the command
 * came on: the send plan's row 0 is set to it). Returns what recv
 * returned (bytes, 0 closed, -errno), or DDM_REPLIED (2^40, not a byte
 * count) when the step was done whole (every record admitted, the reply
 * sent or none new). The send plan's reply record holds the emit's mask
 * (-2: not run; -1: a torn read) and the send's trouble bits. Anything not
 * done whole is the general path's, with the bytes left in rx. */
static PyObject *ddm_reply(PyObject *mod, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 5) {
        PyErr_SetString(PyExc_TypeError, "ddm_reply(admit_plan, emit_plan, send_plan, rx, fd)");
        return NULL;
    }
    Codec ac, ec;
    PlanObject *ap = plan_arg(args[0], "ddm_admit");
    PlanObject *ep = ap == NULL ? NULL : plan_arg(args[1], "ddm_emit");
    PlanObject *sp = ep == NULL ? NULL : plan_arg(args[2], "ddm_send");
    if (sp == NULL || !admit_plan_ok(ap, &ac) || !emit_plan_ok(ep, &ec))
        return NULL;
    Py_ssize_t n = send_rows_ok(sp);
    int fd = n == 0 ? -1 : (int)PyLong_AsLong(args[4]);
    Py_buffer b;
    if (n == 0 || (fd == -1 && PyErr_Occurred()) ||
        PyObject_GetBuffer(args[3], &b, PyBUF_WRITABLE) < 0)
        return NULL;
    int64_t *reply = I64(sp, DS_REPLY);
    I64(sp, DS_FDS)[0] = fd;
    reply[DDM_SEND_REPLY_EMITTED] = -2;
    reply[DDM_SEND_REPLY_TROUBLE] = 0;
    ssize_t got = recv(fd, b.buf, (size_t)b.len, MSG_DONTWAIT);
    int64_t result = got < 0 ? -errno : (int64_t)got;
    int failed = admit_received(ap, &ac, b.buf, b.len, got);
    uint64_t mask = (uint64_t)I64(ap, DA_STATE)[AS(MASK)];
    PyBuffer_Release(&b);
    Py_ssize_t records = got > 0 ? got / (ac.body + TAG_SIZE) : 0;
    uint64_t all = records >= MAX_RECORDS ? ~(uint64_t)0 : ((uint64_t)1 << records) - 1;
    if (!failed && records > 0 && mask == all) {
        long emitted = emit_rows(ep, &ec);
        if (emitted == -2)
            return NULL;
        reply[DDM_SEND_REPLY_EMITTED] = emitted;
        if (emitted > 0)
            reply[DDM_SEND_REPLY_TROUBLE] = send_rows(sp, n, emitted, 0);
        if (emitted >= 0 && reply[DDM_SEND_REPLY_TROUBLE] == 0)
            result = DDM_REPLIED;
    }
    return failed ? NULL : PyLong_FromLongLong(result);
}

/* -- for the CompiledAnswer (step.h) -- */

int step_plans_ok(PlanObject *admit, PlanObject *emit) {
    Codec c;
    return admit_plan_ok(admit, &c) && emit_plan_ok(emit, &c);
}

long step_admit(PlanObject *admit, const uint8_t *raw, Py_ssize_t len) {
    Codec c;
    if (!admit_plan_ok(admit, &c))
        return -2;
    return admit_record(admit, &c, raw, len);
}

long step_emit(PlanObject *emit, Py_ssize_t *wsize) {
    Codec c;
    if (!emit_plan_ok(emit, &c))
        return -2;
    *wsize = c.body + TAG_SIZE;
    return emit_rows(emit, &c);
}

static const Signature STEP_SIGNATURES[] = {
    {"ddm_admit",
     ARGS(FREE("ld", 'B'), REC("codec", 'B', DDM_ADMIT_CODEC__N),
          REC("params", 'q', DDM_ADMIT_PARAMS__N), DIM("rows", 'q', 'r', DDM_ADMIT_ROWS__N),
          DIM("src", 'B', 'r', SOURCE_SIZE), FREE("ex", 'B'), FREE("lat", 'q'),
          REC("state", 'q', DDM_ADMIT_STATE__N))},
    {"ddm_emit",
     ARGS(FREE("ld", 'B'), REC("codec", 'B', DDM_EMIT_CODEC__N),
          REC("params", 'q', DDM_EMIT_PARAMS__N), DIM("rows", 'q', 'r', DDM_EMIT_ROWS__N),
          FREE("out", 'B'), FREE("wire", 'B'), FREE("ex", 'B'))},
    {"ddm_send",
     ARGS(FREE("wire", 'B'), DIM("fds", 'q', 'r', 1), DIM("status", 'q', 'r', 1),
          REC("reply", 'q', DDM_SEND_REPLY__N))},
};

#define FASTCALL(f) (PyCFunction)(void (*)(void))(f), METH_FASTCALL

static PyMethodDef STEP_METHODS[] = {
    {"ddm_admit", FASTCALL(ddm_admit), "A ddm: a record admitted (the common case)."},
    {"ddm_emit", ddm_emit, METH_O, "A ddm: its node's new records encoded and sealed."},
    {"ddm_recv", FASTCALL(ddm_recv), "A ddm: one recv(2) and its records admitted."},
    {"ddm_send", FASTCALL(ddm_send), "A ddm: the records emitted, sent."},
    {"ddm_reply", FASTCALL(ddm_reply), "An ESC ddm: receive and reply in one call."},
    {NULL, NULL, 0, NULL},
};

const KernelSet STEP_KERNELS = {STEP_SIGNATURES, 3, STEP_METHODS};
