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
 * They know no layout. Every kernel works on a Plan: named buffers (numpy
 * arrays, shared memory) and tables of byte offsets that the owning Python
 * module builds once, in Initialization, from its own declared layouts
 * (the register datasheet, the register bank, Local Data). Each kernel
 * declares the names and element types it needs (``signature(kernel)``);
 * ``Plan(kernel, {name: buffer})`` checks them once. The Python modules keep
 * a numpy reference implementation of each kernel; the unit tests run both
 * on the same inputs.
 *
 * Registers and records are packed: multi-byte values are loaded and stored
 * with memcpy (no alignment is assumed).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <dlfcn.h>
#include <errno.h>
#include <math.h>
#include <stdint.h>
#include <string.h>
#include <sys/socket.h>
#include <time.h>

#define BARRIER() __asm__ __volatile__("" ::: "memory")

/* -- unaligned loads and stores -- */

static inline uint32_t ld_u32(const uint8_t *p) { uint32_t v; memcpy(&v, p, 4); return v; }
static inline int32_t ld_i32(const uint8_t *p) { int32_t v; memcpy(&v, p, 4); return v; }
static inline int16_t ld_i16(const uint8_t *p) { int16_t v; memcpy(&v, p, 2); return v; }
static inline uint64_t ld_u64(const uint8_t *p) { uint64_t v; memcpy(&v, p, 8); return v; }
static inline float ld_f32(const uint8_t *p) { float v; memcpy(&v, p, 4); return v; }
static inline void st_u32(uint8_t *p, uint32_t v) { memcpy(p, &v, 4); }
static inline void st_i32(uint8_t *p, int32_t v) { memcpy(p, &v, 4); }
static inline void st_i16(uint8_t *p, int16_t v) { memcpy(p, &v, 2); }
static inline void st_u64(uint8_t *p, uint64_t v) { memcpy(p, &v, 8); }

/* -- kernel signatures: argument names and element types -- */

typedef struct {
    const char *name;
    char type; /* d f8, q i8, B u1 */
} Arg;

typedef struct {
    const char *name;
    const Arg *args;
    int nargs;
} Signature;

#define ARGS(...) (const Arg[]){__VA_ARGS__}, (int)(sizeof((const Arg[]){__VA_ARGS__}) / sizeof(Arg))

/* plain batch copy: table rows (src_off, dst_off, size) */
enum { CP_SRC, CP_DST, CP_TABLE };
/* seqlock batch read: table rows (seq_off, payload_off, size, dst_off) */
enum { SR_SRC, SR_DST, SR_TABLE, SR_TORN };
/* seqlock batch publish: table rows (seq_off, payload_off, size, src_off) */
enum { SW_DST, SW_SRC, SW_TABLE };

enum {
    CA_IMAGE, CA_BRAKE_OFF, CA_BRAKE_BIT, CA_DAC_OFF, CA_CUT, CA_AMPS, CA_IMAX, CA_NM,
    CA_MOTOR_TAU, CA_BRAKE, CA_BRAKED, CA_COPY, CA_REQ, CA_SEEN
};

enum {
    CS_IMAGE, CS_Q, CS_QD, CS_TAU, CS_APPLIED, CS_MOTOR_TAU, CS_BRAKED, CS_HELD, CS_STOPPED,
    CS_CPR, CS_ENC_OFFSET, CS_COUNTS, CS_COUNTER_OFF, CS_CENTER, CS_ON, CS_OFF, CS_SWITCH,
    CS_FORCE, CS_HOME, CS_LAST_HOME, CS_EDGES, CS_HOME_OFF, CS_DIO_CLEAR, CS_HOME_WORD,
    CS_HOME_BIT, CS_ADC_SRC, CS_ADC_SCALE, CS_ADC_OFF, CS_WRENCH, CS_INVERSE, CS_NOISE,
    CS_NOISE_AT, CS_STRAIN_OFF, CS_SAMPLE_OFF, CS_STEP_OFF, CS_STEP
};

enum {
    DD_IMAGE, DD_STEP_OFF, DD_COUNTER_OFF, DD_LATCH_OFF, DD_LCOUNT_OFF, DD_LEDGE_OFF,
    DD_TACH_OFF, DD_TORQUE_OFF, DD_READBACK_OFF, DD_HOME_WORD, DD_HOME_BIT, DD_BRAKE_WORD,
    DD_BRAKE_BIT, DD_STRAIN_OFF, DD_CAL_OFF, DD_CPR, DD_TACH_SCALE, DD_TORQUE_SCALE,
    DD_DAC_SCALE, DD_RAW, DD_ACC, DD_QREF, DD_PREV_Q, DD_STATE, DD_PARAMS, DD_Q, DD_QD,
    DD_TAU, DD_WRENCH, DD_HOME, DD_BRAKES, DD_LCOUNT, DD_LEDGE, DD_LATCH_Q, DD_OUT
};

enum { DT_IMAGE, DT_TAU, DT_VOLTS_PER_NM, DT_CODE_OFF };

enum { JP_Q, JP_QD, JP_QREF, JP_QDREF, JP_G, JP_ON, JP_TAU, JP_INTEGRAL, JP_GAINS, JP_DT };
enum { QU_Q0, QU_D, QU_Q, QU_QD, QU_QDD, QU_TIME };

enum {
    GP_FB, GP_FB_OFF, GP_SRC, GP_SRC_OFF, GP_HOME, GP_HOME_OFF, GP_LIMITS, GP_ON,
    GP_RELEASED, GP_TAU, GP_TRACE, GP_TRACE_AT
};

static const Signature SIGNATURES[] = {
    {"copy", ARGS({"src", 'B'}, {"dst", 'B'}, {"table", 'q'})},
    {"seq_read", ARGS({"src", 'B'}, {"dst", 'B'}, {"table", 'q'}, {"torn", 'q'})},
    {"seq_write", ARGS({"dst", 'B'}, {"src", 'B'}, {"table", 'q'})},
    {"chassis_apply",
     ARGS({"image", 'B'}, {"brake_off", 'q'}, {"brake_bit", 'q'}, {"dac_off", 'q'},
          {"cut", 'B'}, {"amps_per_code", 'd'}, {"max_current", 'd'}, {"nm_per_amp", 'd'},
          {"motor_tau", 'd'}, {"brake", 'B'}, {"braked", 'B'}, {"copy", 'q'}, {"req_off", 'q'},
          {"req_seen", 'B'})},
    {"chassis_sample",
     ARGS({"image", 'B'}, {"q", 'd'}, {"qd", 'd'}, {"tau", 'd'}, {"applied", 'd'},
          {"motor_tau", 'd'}, {"braked", 'B'}, {"held", 'B'}, {"stopped", 'B'},
          {"counts_per_rad", 'd'}, {"enc_offset", 'q'}, {"counts", 'q'}, {"counter_off", 'q'},
          {"home_center", 'd'}, {"home_on", 'd'}, {"home_off", 'd'}, {"switch", 'B'},
          {"force", 'B'}, {"home", 'B'}, {"last_home", 'B'}, {"edges", 'B'},
          {"home_reg_off", 'q'}, {"dio_clear", 'q'}, {"home_word", 'q'}, {"home_bit", 'q'},
          {"adc_src", 'q'}, {"adc_scale", 'd'}, {"adc_off", 'q'}, {"wrench", 'd'},
          {"inverse", 'd'}, {"noise", 'd'}, {"noise_at", 'q'}, {"strain_off", 'q'},
          {"sample_off", 'q'}, {"step_off", 'q'}, {"step", 'q'})},
    {"driver_decode",
     ARGS({"image", 'B'}, {"step_off", 'q'}, {"counter_off", 'q'}, {"latch_off", 'q'},
          {"latch_count_off", 'q'}, {"latch_edge_off", 'q'}, {"tach_off", 'q'},
          {"torque_off", 'q'}, {"readback_off", 'q'}, {"home_word", 'q'}, {"home_bit", 'q'},
          {"brake_word", 'q'}, {"brake_bit", 'q'}, {"strain_off", 'q'}, {"cal_off", 'q'},
          {"counts_per_rad", 'd'}, {"tach_scale", 'd'}, {"torque_scale", 'd'},
          {"dac_scale", 'd'}, {"raw", 'q'}, {"acc", 'q'}, {"q_ref", 'd'}, {"prev_q", 'd'},
          {"state", 'q'}, {"params", 'd'}, {"q", 'd'}, {"qd", 'd'}, {"tau", 'd'},
          {"wrench", 'd'}, {"home", 'B'}, {"brakes", 'B'}, {"latch_count", 'B'},
          {"latch_edge", 'B'}, {"latch_q", 'd'}, {"out", 'd'})},
    {"driver_dac",
     ARGS({"image", 'B'}, {"tau", 'd'}, {"volts_per_nm", 'd'}, {"code_off", 'q'})},
    {"joint_pid",
     ARGS({"q", 'd'}, {"qd", 'd'}, {"q_ref", 'd'}, {"qd_ref", 'd'}, {"g", 'd'}, {"on", 'B'},
          {"tau", 'd'}, {"integral", 'd'}, {"gains", 'd'}, {"dt", 'd'})},
    {"quintic", ARGS({"q0", 'd'}, {"d", 'd'}, {"q", 'd'}, {"qd", 'd'}, {"qdd", 'd'}, {"time", 'd'})},
    {"cartesian_law",
     ARGS({"kin", 'd'}, {"ref", 'd'}, {"cmd", 'd'}, {"gains", 'd'}, {"state", 'd'}, {"out", 'd'})},
    {"ddm_admit",
     ARGS({"ld", 'B'}, {"codec", 'B'}, {"params", 'q'}, {"rows", 'q'}, {"src", 'B'}, {"ex", 'B'},
          {"lat", 'q'}, {"state", 'q'})},
    {"ddm_emit",
     ARGS({"ld", 'B'}, {"codec", 'B'}, {"params", 'q'}, {"rows", 'q'}, {"out", 'B'},
          {"wire", 'B'}, {"ex", 'B'})},
    {"ddm_send", ARGS({"wire", 'B'}, {"fds", 'q'}, {"status", 'q'})},
    {"guard_prepare",
     ARGS({"fb", 'B'}, {"fb_off", 'q'}, {"src", 'B'}, {"src_off", 'q'}, {"home", 'B'},
          {"home_off", 'q'}, {"limits", 'd'}, {"on", 'B'}, {"released", 'B'}, {"tau", 'd'},
          {"trace", 'd'}, {"trace_at", 'q'})},
};
#define NSIG ((int)(sizeof(SIGNATURES) / sizeof(SIGNATURES[0])))
#define MAX_ARGS 40

static int find_signature(const char *name) {
    for (int i = 0; i < NSIG; i++)
        if (strcmp(SIGNATURES[i].name, name) == 0)
            return i;
    return -1;
}

static Py_ssize_t itemsize_of(char type) {
    switch (type) {
    case 'd': return 8;
    case 'q': return 8;
    default: return 1;
    }
}

/* -- Plan -- */

typedef struct {
    PyObject_HEAD
    int kernel;
    int nargs;
    Py_buffer views[MAX_ARGS];
    uint8_t *p[MAX_ARGS];
    Py_ssize_t n[MAX_ARGS]; /* elements */
} PlanObject;

static void Plan_dealloc(PlanObject *self) {
    for (int i = 0; i < self->nargs; i++)
        PyBuffer_Release(&self->views[i]);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int Plan_init(PlanObject *self, PyObject *args, PyObject *kwds) {
    const char *kernel;
    PyObject *bufs;
    if (!PyArg_ParseTuple(args, "sO!", &kernel, &PyDict_Type, &bufs))
        return -1;
    int k = find_signature(kernel);
    if (k < 0) {
        PyErr_Format(PyExc_ValueError, "no kernel %s", kernel);
        return -1;
    }
    const Signature *sig = &SIGNATURES[k];
    for (int i = 0; i < self->nargs; i++)
        PyBuffer_Release(&self->views[i]);
    self->nargs = 0;
    self->kernel = k;
    for (int i = 0; i < sig->nargs; i++) {
        PyObject *obj = PyDict_GetItemString(bufs, sig->args[i].name);
        if (obj == NULL) {
            PyErr_Format(PyExc_KeyError, "kernel %s: argument %s missing", kernel,
                         sig->args[i].name);
            return -1;
        }
        int flags = PyBUF_WRITABLE | PyBUF_C_CONTIGUOUS | PyBUF_FORMAT;
        if (PyObject_GetBuffer(obj, &self->views[i], flags) < 0)
            return -1;
        self->nargs = i + 1;
        char type = sig->args[i].type;
        Py_ssize_t size = itemsize_of(type);
        if (type != 'B') {
            const char *f = self->views[i].format ? self->views[i].format : "B";
            char c = f[strlen(f) - 1];
            int ok = self->views[i].itemsize == size &&
                     (type == 'd' ? c == 'd' : (c == 'q' || c == 'l'));
            if (!ok) {
                PyErr_Format(PyExc_TypeError, "kernel %s: argument %s: format %s, expected %s",
                             kernel, sig->args[i].name, f, type == 'd' ? "float64" : "int64");
                return -1;
            }
            if ((uintptr_t)self->views[i].buf % 8) {
                PyErr_Format(PyExc_TypeError, "kernel %s: argument %s: not 8-byte aligned",
                             kernel, sig->args[i].name);
                return -1;
            }
        }
        self->p[i] = (uint8_t *)self->views[i].buf;
        self->n[i] = self->views[i].len / size;
    }
    return 0;
}

static PyTypeObject PlanType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "redistro._kernels.Plan",
    .tp_basicsize = sizeof(PlanObject),
    .tp_flags = Py_TPFLAGS_DEFAULT,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Plan_init,
    .tp_dealloc = (destructor)Plan_dealloc,
    .tp_doc = "Named buffers a kernel works on: Plan(kernel, {name: buffer}).",
};

static PlanObject *plan_arg(PyObject *obj, const char *kernel) {
    if (!PyObject_TypeCheck(obj, &PlanType)) {
        PyErr_SetString(PyExc_TypeError, "expected a Plan");
        return NULL;
    }
    PlanObject *plan = (PlanObject *)obj;
    if (strcmp(SIGNATURES[plan->kernel].name, kernel) != 0) {
        PyErr_Format(PyExc_ValueError, "a plan of %s, not %s", SIGNATURES[plan->kernel].name,
                     kernel);
        return NULL;
    }
    return plan;
}

#define F64(plan, i) ((double *)(plan)->p[i])
#define I64(plan, i) ((int64_t *)(plan)->p[i])
#define U8(plan, i) ((plan)->p[i])

/* -- copies: many fields in one call -- */

static PyObject *copy(PyObject *mod, PyObject *arg) {
    PlanObject *pl = plan_arg(arg, "copy");
    if (pl == NULL)
        return NULL;
    uint8_t *src = U8(pl, CP_SRC), *dst = U8(pl, CP_DST);
    int64_t *t = I64(pl, CP_TABLE);
    for (Py_ssize_t r = 0; r < pl->n[CP_TABLE] / 3; r++, t += 3)
        memcpy(dst + t[1], src + t[0], t[2]);
    Py_RETURN_NONE;
}

/* -- seqlocks: many blocks in one call -- */

#define SCRATCH 2048
#define ATTEMPTS 4

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
    Py_ssize_t rows = pl->n[SR_TABLE] / 4;
    uint8_t scratch[SCRATCH];
    long failed = 0;
    for (Py_ssize_t r = 0; r < rows; r++, t += 4) {
        volatile uint64_t *seq = (volatile uint64_t *)(src + t[0]);
        Py_ssize_t size = t[2];
        int ok = 0;
        for (int a = 0; a < ATTEMPTS && !ok; a++) {
            uint64_t s1 = *seq;
            if (s1 & 1)
                continue;
            BARRIER();
            memcpy(scratch, src + t[1], size);
            BARRIER();
            if (*seq == s1)
                ok = 1;
        }
        if (ok)
            memcpy(dst + t[3], scratch, size);
        else {
            torn[r] += 1;
            failed += 1;
        }
    }
    return PyLong_FromLong(failed);
}

/* Publish each table row's payload from src into its seqlocked block in dst
 * (this process is the blocks' one writer). */
static PyObject *seq_write(PyObject *mod, PyObject *arg) {
    PlanObject *pl = plan_arg(arg, "seq_write");
    if (pl == NULL)
        return NULL;
    uint8_t *dst = U8(pl, SW_DST), *src = U8(pl, SW_SRC);
    int64_t *t = I64(pl, SW_TABLE);
    Py_ssize_t rows = pl->n[SW_TABLE] / 4;
    for (Py_ssize_t r = 0; r < rows; r++, t += 4) {
        volatile uint64_t *seq = (volatile uint64_t *)(dst + t[0]);
        uint64_t s = *seq;
        s += s & 1; /* a writer that died mid-write: resume from even */
        *seq = s + 1;
        BARRIER();
        memcpy(dst + t[1], src + t[3], t[2]);
        BARRIER();
        *seq = s + 2;
    }
    Py_RETURN_NONE;
}

/* -- the simulated chassis -- */

/* Controller outputs -> joints: brakes (fail-safe: engaged unless the
 * release bit is on, or the amplifiers' watchdog cut the robot), motor
 * torques from the DAC codes (current saturated; none on a braked joint),
 * the boards' readbacks (copy rows: src_off, dst_off, nbytes, mask where
 * mask != 0 means a 32-bit word masked), new encoder requests.
 * Returns bit 1: a brake changes; bit 2: an encoder request is new. */
static PyObject *chassis_apply(PyObject *mod, PyObject *arg) {
    PlanObject *pl = plan_arg(arg, "chassis_apply");
    if (pl == NULL)
        return NULL;
    uint8_t *img = U8(pl, CA_IMAGE);
    Py_ssize_t n = pl->n[CA_MOTOR_TAU];
    int64_t *boff = I64(pl, CA_BRAKE_OFF), *bbit = I64(pl, CA_BRAKE_BIT);
    int64_t *doff = I64(pl, CA_DAC_OFF);
    uint8_t *cut = U8(pl, CA_CUT), *brake = U8(pl, CA_BRAKE), *braked = U8(pl, CA_BRAKED);
    double *amps = F64(pl, CA_AMPS), *imax = F64(pl, CA_IMAX), *nm = F64(pl, CA_NM);
    double *tau = F64(pl, CA_MOTOR_TAU);
    long flags = 0;
    for (Py_ssize_t j = 0; j < n; j++) {
        uint32_t word = ld_u32(img + boff[j]);
        uint8_t b = ((word >> bbit[j]) & 1u) == 0 || cut[j];
        brake[j] = b;
        if (b != braked[j])
            flags |= 1;
        double cur = (double)ld_i16(img + doff[j]) * amps[j];
        if (cur > imax[j])
            cur = imax[j];
        else if (cur < -imax[j])
            cur = -imax[j];
        tau[j] = b ? 0.0 : cur * nm[j];
    }
    int64_t *c = I64(pl, CA_COPY);
    for (Py_ssize_t r = 0; r < pl->n[CA_COPY] / 4; r++, c += 4) {
        if (c[3])
            st_u32(img + c[1], ld_u32(img + c[0]) & (uint32_t)c[3]);
        else
            memcpy(img + c[1], img + c[0], c[2]);
    }
    int64_t *ro = I64(pl, CA_REQ);
    uint8_t *seen = U8(pl, CA_SEEN);
    for (Py_ssize_t r = 0; r < pl->n[CA_REQ]; r++)
        if (memcmp(img + ro[r], seen + 32 * r, 32) != 0)
            flags |= 2;
    return PyLong_FromLong(flags);
}

/* Joint states -> the boards' in banks: the joint torque (a braked joint's
 * is its brake's), stopped braked joints (to be held), encoder counters
 * (24-bit, wrapping), home switches with hysteresis (force[j]: 0 as the
 * switch, 1 stuck off, 2 stuck on), the encoder boards' home levels, the
 * DIO home words, the ADC codes (torque sensors, tachometers: rounded,
 * saturated), the wrist gauges (counts = inverse @ wrench + noise), the
 * sample counters and every board's step.
 * Returns bit 1: a braked joint stopped; bit 2: a home input changed;
 * bit 4: the wrist noise block is used up (the next call needs a new one). */
static PyObject *chassis_sample(PyObject *mod, PyObject *arg) {
    PlanObject *pl = plan_arg(arg, "chassis_sample");
    if (pl == NULL)
        return NULL;
    uint8_t *img = U8(pl, CS_IMAGE);
    Py_ssize_t n = pl->n[CS_Q];
    double *q = F64(pl, CS_Q), *qd = F64(pl, CS_QD), *tau = F64(pl, CS_TAU);
    double *applied = F64(pl, CS_APPLIED), *mtau = F64(pl, CS_MOTOR_TAU);
    uint8_t *braked = U8(pl, CS_BRAKED), *held = U8(pl, CS_HELD), *stopped = U8(pl, CS_STOPPED);
    double *cpr = F64(pl, CS_CPR);
    int64_t *eoff = I64(pl, CS_ENC_OFFSET), *counts = I64(pl, CS_COUNTS);
    int64_t *coff = I64(pl, CS_COUNTER_OFF);
    double *center = F64(pl, CS_CENTER), *on_w = F64(pl, CS_ON), *off_b = F64(pl, CS_OFF);
    uint8_t *sw = U8(pl, CS_SWITCH), *force = U8(pl, CS_FORCE), *home = U8(pl, CS_HOME);
    uint8_t *last = U8(pl, CS_LAST_HOME), *edges = U8(pl, CS_EDGES);
    int64_t *hreg = I64(pl, CS_HOME_OFF), *hword = I64(pl, CS_HOME_WORD);
    int64_t *hbit = I64(pl, CS_HOME_BIT);
    long flags = 0;
    for (Py_ssize_t j = 0; j < n; j++) {
        tau[j] = braked[j] ? applied[j] : mtau[j];
        stopped[j] = braked[j] && !held[j] && fabs(qd[j]) < 1e-3;
        if (stopped[j])
            flags |= 1;
        int64_t c = (int64_t)floor(q[j] * cpr[j]) + eoff[j];
        c &= (int64_t)0xFFFFFF;
        counts[j] = c;
        st_u32(img + coff[j], (uint32_t)c);
        double d = fabs(q[j] - center[j]);
        uint8_t s = (sw[j] && d <= off_b[j]) || d < on_w[j];
        sw[j] = s;
        uint8_t h = force[j] ? force[j] == 2 : s;
        home[j] = h;
        edges[j] = h != last[j];
        if (edges[j])
            flags |= 2;
        img[hreg[j]] = h;
    }
    int64_t *clear = I64(pl, CS_DIO_CLEAR);
    for (Py_ssize_t r = 0; r < pl->n[CS_DIO_CLEAR]; r++)
        st_u32(img + clear[r], 0);
    for (Py_ssize_t j = 0; j < n; j++)
        if (home[j])
            st_u32(img + hword[j], ld_u32(img + hword[j]) | (1u << hbit[j]));
    int64_t *src = I64(pl, CS_ADC_SRC), *aoff = I64(pl, CS_ADC_OFF);
    double *scale = F64(pl, CS_ADC_SCALE);
    for (Py_ssize_t i = 0; i < pl->n[CS_ADC_SRC]; i++) {
        double v = src[i] < n ? tau[src[i]] : qd[src[i] - n];
        v = nearbyint(v * scale[i]);
        if (v > 32767.0)
            v = 32767.0;
        else if (v < -32768.0)
            v = -32768.0;
        st_i16(img + aoff[i], (int16_t)v);
    }
    Py_ssize_t wrists = pl->n[CS_STRAIN_OFF];
    if (wrists) {
        double *w = F64(pl, CS_WRENCH), *inv = F64(pl, CS_INVERSE);
        int64_t *at = I64(pl, CS_NOISE_AT);
        Py_ssize_t rows = pl->n[CS_NOISE] / (6 * wrists);
        if (*at >= rows) {
            PyErr_SetString(PyExc_IndexError, "chassis_sample: the wrist noise block is used up");
            return NULL;
        }
        double *noise = F64(pl, CS_NOISE) + (*at) * 6 * wrists;
        *at += 1;
        if (*at >= rows)
            flags |= 4; /* the noise block is used up: draw the next */
        int64_t *soff = I64(pl, CS_STRAIN_OFF), *smp = I64(pl, CS_SAMPLE_OFF);
        for (Py_ssize_t k = 0; k < wrists; k++) {
            for (int i = 0; i < 6; i++) {
                double v = noise[6 * k + i];
                for (int m = 0; m < 6; m++)
                    v += inv[36 * k + 6 * i + m] * w[6 * k + m];
                v = nearbyint(v);
                if (v > 8388607.0)
                    v = 8388607.0;
                else if (v < -8388608.0)
                    v = -8388608.0;
                st_i32(img + soff[k] + 4 * i, (int32_t)v);
            }
            st_u32(img + smp[k], ld_u32(img + smp[k]) + 1);
        }
    }
    int64_t *stoff = I64(pl, CS_STEP_OFF);
    uint64_t step = (uint64_t)I64(pl, CS_STEP)[0];
    for (Py_ssize_t b = 0; b < pl->n[CS_STEP_OFF]; b++)
        st_u64(img + stoff[b], step);
    return PyLong_FromLong(flags);
}

/* -- the robot-level driver -- */

static inline int64_t wrap24(int64_t d) { return ((d + (1 << 23)) & 0xFFFFFF) - (1 << 23); }

/* The boards' snapshot -> robot units (see RobotDriver.read_feedback).
 * state: [have_ref, prev_step (-1: none), step, coherent]; params:
 * [jump_limit_rad_s (0: off), physics_hz, has_tach, has_torque, retry]:
 * with retry != 0, a snapshot whose encoder boards come from different
 * plant steps returns -1 at once (nothing decoded: take it again);
 * out: [jump delta, jump limit, steps] of a refused counter change.
 * Returns 0, or 1 + the joint whose counter jumped (nothing updated then). */
static PyObject *driver_decode(PyObject *mod, PyObject *arg) {
    PlanObject *pl = plan_arg(arg, "driver_decode");
    if (pl == NULL)
        return NULL;
    uint8_t *img = U8(pl, DD_IMAGE);
    Py_ssize_t n = pl->n[DD_Q];
    int64_t *stoff = I64(pl, DD_STEP_OFF), *st = I64(pl, DD_STATE);
    double *par = F64(pl, DD_PARAMS), *out = F64(pl, DD_OUT);
    uint64_t lo = UINT64_MAX, hi = 0;
    for (Py_ssize_t b = 0; b < pl->n[DD_STEP_OFF]; b++) {
        uint64_t s = ld_u64(img + stoff[b]);
        lo = s < lo ? s : lo;
        hi = s > hi ? s : hi;
    }
    int64_t step = (int64_t)lo;
    st[2] = step;
    st[3] = lo == hi;
    if (lo != hi && par[4] != 0)
        return PyLong_FromLong(-1); /* boards of two plant steps: read again first */
    int64_t *coff = I64(pl, DD_COUNTER_OFF), *raw = I64(pl, DD_RAW), *acc = I64(pl, DD_ACC);
    double *cpr = F64(pl, DD_CPR), *qref = F64(pl, DD_QREF), *q = F64(pl, DD_Q);
    int64_t now_raw[64];
    if (n > 64) {
        PyErr_SetString(PyExc_ValueError, "driver_decode: at most 64 joints");
        return NULL;
    }
    for (Py_ssize_t j = 0; j < n; j++)
        now_raw[j] = (int64_t)ld_u32(img + coff[j]);
    if (!st[0]) {
        for (Py_ssize_t j = 0; j < n; j++) {
            int64_t s = now_raw[j] >= (1 << 23) ? now_raw[j] - (1 << 24) : now_raw[j];
            qref[j] = (double)s / cpr[j];
            acc[j] = 0;
        }
        st[0] = 1;
    } else {
        int64_t deltas[64];
        for (Py_ssize_t j = 0; j < n; j++)
            deltas[j] = wrap24(now_raw[j] - raw[j]);
        if (par[0] > 0 && st[1] >= 0) {
            int64_t steps = step - st[1];
            if (steps < 1)
                steps = 1;
            for (Py_ssize_t j = 0; j < n; j++) {
                double limit = par[0] * cpr[j] * (double)steps / par[1] + 2.0;
                if (fabs((double)deltas[j]) > limit) {
                    out[0] = (double)deltas[j];
                    out[1] = limit;
                    out[2] = (double)steps;
                    return PyLong_FromLong((long)j + 1);
                }
            }
        }
        for (Py_ssize_t j = 0; j < n; j++)
            acc[j] += deltas[j];
    }
    for (Py_ssize_t j = 0; j < n; j++) {
        raw[j] = now_raw[j];
        q[j] = qref[j] + (double)acc[j] / cpr[j];
    }
    /* latches: where each joint was at its last home edge */
    int64_t *loff = I64(pl, DD_LATCH_OFF), *lcoff = I64(pl, DD_LCOUNT_OFF);
    int64_t *leoff = I64(pl, DD_LEDGE_OFF);
    uint8_t *lcount = U8(pl, DD_LCOUNT); /* uint32 each */
    uint8_t *ledge = U8(pl, DD_LEDGE);
    double *lq = F64(pl, DD_LATCH_Q);
    for (Py_ssize_t j = 0; j < n; j++) {
        int64_t back = wrap24((int64_t)ld_u32(img + loff[j]) - now_raw[j]);
        lq[j] = q[j] + (double)back / cpr[j];
        st_u32(lcount + 4 * j, ld_u32(img + lcoff[j]));
        ledge[j] = img[leoff[j]];
    }
    /* speeds: tachometers, or the counters differentiated on the boards' clock */
    double *qd = F64(pl, DD_QD), *prev_q = F64(pl, DD_PREV_Q);
    if (par[2] != 0) {
        int64_t *toff = I64(pl, DD_TACH_OFF);
        double *ts = F64(pl, DD_TACH_SCALE);
        for (Py_ssize_t j = 0; j < n; j++)
            qd[j] = (double)ld_i16(img + toff[j]) * ts[j];
    } else if (st[1] >= 0 && step > st[1]) {
        double dt = (double)(step - st[1]) / par[1];
        for (Py_ssize_t j = 0; j < n; j++)
            qd[j] = (q[j] - prev_q[j]) / dt;
    }
    st[1] = step;
    for (Py_ssize_t j = 0; j < n; j++)
        prev_q[j] = q[j];
    /* joint torques: torque sensors, or the DAC readback through the motor model */
    double *tau = F64(pl, DD_TAU);
    if (par[3] != 0) {
        int64_t *toff = I64(pl, DD_TORQUE_OFF);
        double *ts = F64(pl, DD_TORQUE_SCALE);
        for (Py_ssize_t j = 0; j < n; j++)
            tau[j] = (double)ld_i16(img + toff[j]) * ts[j];
    } else {
        int64_t *roff = I64(pl, DD_READBACK_OFF);
        double *ds = F64(pl, DD_DAC_SCALE);
        for (Py_ssize_t j = 0; j < n; j++)
            tau[j] = (double)ld_i16(img + roff[j]) * ds[j];
    }
    int64_t *hw = I64(pl, DD_HOME_WORD), *hb = I64(pl, DD_HOME_BIT);
    int64_t *bw = I64(pl, DD_BRAKE_WORD), *bb = I64(pl, DD_BRAKE_BIT);
    uint8_t *home = U8(pl, DD_HOME), *brakes = U8(pl, DD_BRAKES);
    for (Py_ssize_t j = 0; j < n; j++) {
        home[j] = (ld_u32(img + hw[j]) >> hb[j]) & 1u;
        brakes[j] = ((ld_u32(img + bw[j]) >> bb[j]) & 1u) == 0;
    }
    double *w = F64(pl, DD_WRENCH);
    int64_t soff = I64(pl, DD_STRAIN_OFF)[0], caloff = I64(pl, DD_CAL_OFF)[0];
    if (soff >= 0) {
        for (int i = 0; i < 6; i++) {
            double v = 0.0;
            for (int k = 0; k < 6; k++)
                v += (double)ld_f32(img + caloff + 4 * (6 * i + k)) *
                     (double)ld_i32(img + soff + 4 * k);
            w[i] = v;
        }
    } else {
        for (int i = 0; i < 6; i++)
            w[i] = 0.0;
    }
    return PyLong_FromLong(0);
}

/* Joint torques -> DAC codes (rounded, saturated) in the DAC boards' out
 * banks. Returns 0, or 1 + the first joint whose torque is not finite
 * (nothing is written then). */
static PyObject *driver_dac(PyObject *mod, PyObject *arg) {
    PlanObject *pl = plan_arg(arg, "driver_dac");
    if (pl == NULL)
        return NULL;
    uint8_t *img = U8(pl, DT_IMAGE);
    double *tau = F64(pl, DT_TAU), *vpn = F64(pl, DT_VOLTS_PER_NM);
    int64_t *off = I64(pl, DT_CODE_OFF);
    Py_ssize_t n = pl->n[DT_TAU];
    for (Py_ssize_t j = 0; j < n; j++)
        if (!isfinite(tau[j]))
            return PyLong_FromLong((long)j + 1);
    for (Py_ssize_t j = 0; j < n; j++) {
        double v = nearbyint(tau[j] * vpn[j] * 204.8); /* 2048 codes per 10 V */
        if (v > 2047.0)
            v = 2047.0;
        else if (v < -2048.0)
            v = -2048.0;
        st_i16(img + off[j], (int16_t)v);
    }
    return PyLong_FromLong(0);
}

static inline double clampd(double x, double lo, double hi);

/* -- joint control -- */

/* Joint PID with gravity compensation (see control/pid.py: pid_update):
 * gains: kp[n], ki[n], kd[n], i_lim[n]; the integral (state) clamped to
 * +-i_lim and zeroed on joints off; tau = (g + kp e + kd (qd_ref - qd) +
 * ki integral) on joints on, 0 off. */
static PyObject *joint_pid(PyObject *mod, PyObject *arg) {
    PlanObject *pl = plan_arg(arg, "joint_pid");
    if (pl == NULL)
        return NULL;
    const double *q = F64(pl, JP_Q), *qd = F64(pl, JP_QD), *qr = F64(pl, JP_QREF);
    const double *qdr = F64(pl, JP_QDREF), *g = F64(pl, JP_G), *gn = F64(pl, JP_GAINS);
    const uint8_t *on = U8(pl, JP_ON);
    double *tau = F64(pl, JP_TAU), *I = F64(pl, JP_INTEGRAL), dt = F64(pl, JP_DT)[0];
    Py_ssize_t n = pl->n[JP_TAU];
    const double *kp = gn, *ki = gn + n, *kd = gn + 2 * n, *lim = gn + 3 * n;
    for (Py_ssize_t j = 0; j < n; j++) {
        double e = qr[j] - q[j];
        double integ = clampd(I[j] + e * dt, -lim[j], lim[j]);
        double m = on[j] ? 1.0 : 0.0;
        I[j] = integ * m;
        tau[j] = (kp[j] * e + kd[j] * (qdr[j] - qd[j]) + ki[j] * I[j] + g[j]) * m;
    }
    Py_RETURN_NONE;
}

/* The quintic from q0 over d (= q1 - q0) in T seconds at t (time: [T, t]),
 * clamped to its ends: q, qd, qdd (see control/trajectory.py). */
static PyObject *quintic(PyObject *mod, PyObject *arg) {
    PlanObject *pl = plan_arg(arg, "quintic");
    if (pl == NULL)
        return NULL;
    const double *q0 = F64(pl, QU_Q0), *d = F64(pl, QU_D), *tm = F64(pl, QU_TIME);
    double *q = F64(pl, QU_Q), *qd = F64(pl, QU_QD), *qdd = F64(pl, QU_QDD);
    double T = tm[0], s = clampd(tm[1] / T, 0.0, 1.0), s2 = s * s, s3 = s2 * s;
    double pos = 10 * s3 - 15 * s3 * s + 6 * s3 * s2;
    double vel = (30 * s2 - 60 * s3 + 30 * s2 * s2) / T;
    double acc = (60 * s - 180 * s2 + 120 * s3) / (T * T);
    for (Py_ssize_t j = 0; j < pl->n[QU_Q]; j++) {
        q[j] = q0[j] + d[j] * pos;
        qd[j] = d[j] * vel;
        qdd[j] = d[j] * acc;
    }
    Py_RETURN_NONE;
}

/* -- the sender's safety guard -- */

static inline double ld_f64(const uint8_t *p) { double v; memcpy(&v, p, 8); return v; }

/* One command, prepared and screened (see esc/sender.py):
 * on[j]: the joint is under control (src joint_on, none once the session
 * status says finished: src_off[2] >= 0 and status == 2); tau[j]: its
 * commanded torque (0 for a joint off, NaN or not); a trace row (cycle
 * trace_at[1], the boards' step, q, qd, tau, tau commanded) at row
 * trace_at[0] % rows, trace_at[0] += 1. fb_off: offsets of q, qd, tau,
 * wrench in the feedback record; src_off: of the torques, joints on and
 * session status (-1: none) in the command; limits: qd_max[7], tau_max[7],
 * force_max, moment_max.
 * Returns bit 1: a figure is not finite or over its limit (the guard's
 * check decides what); bit 2: the joints on differ from ``released``. */
static PyObject *guard_prepare(PyObject *mod, PyObject *arg) {
    PlanObject *pl = plan_arg(arg, "guard_prepare");
    if (pl == NULL)
        return NULL;
    const uint8_t *fb = U8(pl, GP_FB), *src = U8(pl, GP_SRC), *home = U8(pl, GP_HOME);
    int64_t *fo = I64(pl, GP_FB_OFF), *so = I64(pl, GP_SRC_OFF), *at = I64(pl, GP_TRACE_AT);
    double *lim = F64(pl, GP_LIMITS), *tau = F64(pl, GP_TAU), *trace = F64(pl, GP_TRACE);
    uint8_t *on = U8(pl, GP_ON), *released = U8(pl, GP_RELEASED);
    Py_ssize_t rows = pl->n[GP_TRACE] / 30;
    /* limits: qd_max[7] tau_max[7] force moment, then (when given) the
       position limits less the margin lo[7] hi[7] and 1/(2 decel)[7] */
    int pos_limits = pl->n[GP_LIMITS] >= 37;
    int finished = so[2] >= 0 && src[so[2]] == 2;
    long flags = 0;
    double *row = trace + 30 * (at[0] % rows);
    at[0] += 1;
    row[0] = (double)at[1];
    row[1] = (double)ld_u64(home + I64(pl, GP_HOME_OFF)[0]);
    for (int j = 0; j < 7; j++) {
        double q = ld_f64(fb + fo[0] + 8 * j), qd = ld_f64(fb + fo[1] + 8 * j);
        double t = ld_f64(fb + fo[2] + 8 * j);
        on[j] = !finished && src[so[1] + j] != 0;
        double c = on[j] ? ld_f64(src + so[0] + 8 * j) : 0.0;
        tau[j] = c;
        row[2 + j] = q;
        row[9 + j] = qd;
        row[16 + j] = t;
        row[23 + j] = c;
        if (!isfinite(q) || !isfinite(qd) || !isfinite(t) || !isfinite(c))
            flags |= 1;
        if (fabs(qd) > lim[j] || fabs(t) > lim[7 + j] || fabs(c) > lim[7 + j])
            flags |= 1;
        if (pos_limits) { /* inside the limits, and able to stop inside them */
            double stop = q + qd * fabs(qd) * lim[30 + j];
            if (q < lim[16 + j] || q > lim[23 + j] || stop < lim[16 + j] || stop > lim[23 + j])
                flags |= 1;
        }
        if (on[j] != released[j])
            flags |= 2;
    }
    double w[6];
    for (int i = 0; i < 6; i++) {
        w[i] = ld_f64(fb + fo[3] + 8 * i);
        if (!isfinite(w[i]))
            flags |= 1;
    }
    if (sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]) > lim[14] ||
        sqrt(w[3] * w[3] + w[4] * w[4] + w[5] * w[5]) > lim[15])
        flags |= 1;
    return PyLong_FromLong(flags);
}

/* -- the SSC's Cartesian law (see control/cartesian.py: the reference) -- */

/* row-major 3x3 helpers */
static void m3_mul(const double *a, const double *b, double *out) {
    double t[9];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            t[3 * i + j] = a[3 * i] * b[j] + a[3 * i + 1] * b[3 + j] + a[3 * i + 2] * b[6 + j];
    memcpy(out, t, sizeof t);
}
static void m3_mul_bt(const double *a, const double *b, double *out) { /* a @ b.T */
    double t[9];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            t[3 * i + j] = a[3 * i] * b[3 * j] + a[3 * i + 1] * b[3 * j + 1] + a[3 * i + 2] * b[3 * j + 2];
    memcpy(out, t, sizeof t);
}
static void m3_vec(const double *a, const double *v, double *out) {
    double t[3];
    for (int i = 0; i < 3; i++)
        t[i] = a[3 * i] * v[0] + a[3 * i + 1] * v[1] + a[3 * i + 2] * v[2];
    memcpy(out, t, sizeof t);
}
static void m3t_vec(const double *a, const double *v, double *out) { /* a.T @ v */
    double t[3];
    for (int i = 0; i < 3; i++)
        t[i] = a[i] * v[0] + a[3 + i] * v[1] + a[6 + i] * v[2];
    memcpy(out, t, sizeof t);
}

static void rotvec_to_matrix(const double *r, double *R) {
    double x = r[0], y = r[1], z = r[2];
    double angle = sqrt(x * x + y * y + z * z);
    if (angle < 1e-12) {
        static const double I[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1};
        memcpy(R, I, sizeof I);
        return;
    }
    x /= angle, y /= angle, z /= angle;
    double s = sin(angle), c = cos(angle), v = 1.0 - c;
    R[0] = c + x * x * v, R[1] = x * y * v - z * s, R[2] = x * z * v + y * s;
    R[3] = y * x * v + z * s, R[4] = c + y * y * v, R[5] = y * z * v - x * s;
    R[6] = z * x * v - y * s, R[7] = z * y * v + x * s, R[8] = c + z * z * v;
}

static void matrix_to_rotvec(const double *R, double *r) {
    double c = (R[0] + R[4] + R[8] - 1.0) / 2.0;
    c = c > 1.0 ? 1.0 : (c < -1.0 ? -1.0 : c);
    double angle = acos(c);
    double wx = R[7] - R[5], wy = R[2] - R[6], wz = R[3] - R[1];
    if (angle < 1e-9) {
        r[0] = 0.5 * wx, r[1] = 0.5 * wy, r[2] = 0.5 * wz;
        return;
    }
    if (M_PI - angle < 1e-6) { /* near pi: the axis from the symmetric part */
        double M[9];
        for (int i = 0; i < 9; i++)
            M[i] = (R[i] + (i % 4 == 0 ? 1.0 : 0.0)) / 2.0;
        double ax[3];
        int k = 0;
        for (int i = 0; i < 3; i++) {
            ax[i] = sqrt(M[4 * i] > 0 ? M[4 * i] : 0.0);
            if (ax[i] > ax[k])
                k = i;
        }
        double d = ax[k] > 1e-12 ? ax[k] : 1e-12;
        double a[3] = {M[k] / d, M[3 + k] / d, M[6 + k] / d};
        double n = sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]);
        for (int i = 0; i < 3; i++)
            r[i] = a[i] / n * angle;
        return;
    }
    double scale = angle / (2.0 * sin(angle));
    r[0] = wx * scale, r[1] = wy * scale, r[2] = wz * scale;
}

/* symmetric 3x3 eigen-decomposition (cyclic Jacobi): A = V diag(w) V^T */
static void eig3(const double *A, double *w, double *V) {
    double a[9];
    memcpy(a, A, sizeof a);
    static const double I[9] = {1, 0, 0, 0, 1, 0, 0, 0, 1};
    memcpy(V, I, sizeof I);
    for (int sweep = 0; sweep < 50; sweep++) {
        double off = a[1] * a[1] + a[2] * a[2] + a[5] * a[5];
        if (off < 1e-30 * (a[0] * a[0] + a[4] * a[4] + a[8] * a[8]) || off == 0.0)
            break;
        for (int p = 0; p < 2; p++)
            for (int q = p + 1; q < 3; q++) {
                double apq = a[3 * p + q];
                if (apq == 0.0)
                    continue;
                double theta = (a[3 * q + q] - a[3 * p + p]) / (2.0 * apq);
                double t = (theta >= 0 ? 1.0 : -1.0) / (fabs(theta) + sqrt(theta * theta + 1.0));
                double c = 1.0 / sqrt(t * t + 1.0), s = t * c;
                for (int k = 0; k < 3; k++) { /* a = J^T a J */
                    double akp = a[3 * k + p], akq = a[3 * k + q];
                    a[3 * k + p] = c * akp - s * akq;
                    a[3 * k + q] = s * akp + c * akq;
                }
                for (int k = 0; k < 3; k++) {
                    double apk = a[3 * p + k], aqk = a[3 * q + k];
                    a[3 * p + k] = c * apk - s * aqk;
                    a[3 * q + k] = s * apk + c * aqk;
                }
                for (int k = 0; k < 3; k++) {
                    double vkp = V[3 * k + p], vkq = V[3 * k + q];
                    V[3 * k + p] = c * vkp - s * vkq;
                    V[3 * k + q] = s * vkp + c * vkq;
                }
            }
    }
    w[0] = a[0], w[1] = a[4], w[2] = a[8];
}

/* V diag(f) V^T */
static void from_eig3(const double *V, const double *f, double *out) {
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            out[3 * i + j] = V[3 * i] * f[0] * V[3 * j] + V[3 * i + 1] * f[1] * V[3 * j + 1] +
                             V[3 * i + 2] * f[2] * V[3 * j + 2];
}

/* D = 2 zeta L^1/2 (L^-1/2 K L^-1/2)^1/2 L^1/2 (see damping_matrix) */
static void damping3(const double *lam, const double *k, double zeta, double *D) {
    double w[3], V[9], fs[3], fi[3], half[9], inv_half[9], B[9], t[9];
    eig3(lam, w, V);
    for (int i = 0; i < 3; i++) {
        double x = w[i] > 1e-9 ? w[i] : 1e-9;
        fs[i] = sqrt(x), fi[i] = 1.0 / sqrt(x);
    }
    from_eig3(V, fs, half);
    from_eig3(V, fi, inv_half);
    for (int i = 0; i < 3; i++) /* inv_half diag(k) inv_half */
        for (int j = 0; j < 3; j++)
            t[3 * i + j] = inv_half[3 * i + j] * k[j];
    m3_mul(t, inv_half, B);
    double aw[3], aV[9], af[3], ah[9];
    eig3(B, aw, aV);
    for (int i = 0; i < 3; i++)
        af[i] = sqrt(aw[i] > 0 ? aw[i] : 0.0);
    from_eig3(aV, af, ah);
    m3_mul(half, ah, t);
    m3_mul(t, half, D);
    for (int i = 0; i < 9; i++)
        D[i] *= 2.0 * zeta;
}

/* Cholesky of an n x n SPD matrix (row-major, lower L); 0 if not positive */
static int cholesky(const double *A, double *L, int n) {
    memset(L, 0, sizeof(double) * n * n);
    for (int i = 0; i < n; i++)
        for (int j = 0; j <= i; j++) {
            double s = A[n * i + j];
            for (int k = 0; k < j; k++)
                s -= L[n * i + k] * L[n * j + k];
            if (i == j) {
                if (!(s > 0))
                    return 0;
                L[n * i + i] = sqrt(s);
            } else
                L[n * i + j] = s / L[n * j + j];
        }
    return 1;
}

/* solve L L^T x = b in place (b: n values) */
static void chol_solve(const double *L, double *b, int n) {
    for (int i = 0; i < n; i++) {
        double s = b[i];
        for (int k = 0; k < i; k++)
            s -= L[n * i + k] * b[k];
        b[i] = s / L[n * i + i];
    }
    for (int i = n - 1; i >= 0; i--) {
        double s = b[i];
        for (int k = i + 1; k < n; k++)
            s -= L[n * k + i] * b[k];
        b[i] = s / L[n * i + i];
    }
}

/* inverse of an SPD matrix through its Cholesky factor */
static int spd_inverse(const double *A, double *out, int n) {
    double L[36], e[6];
    if (!cholesky(A, L, n))
        return 0;
    for (int j = 0; j < n; j++) {
        for (int i = 0; i < n; i++)
            e[i] = i == j ? 1.0 : 0.0;
        chol_solve(L, e, n);
        for (int i = 0; i < n; i++)
            out[n * i + j] = e[i];
    }
    return 1;
}

static inline double clampd(double x, double lo, double hi) { return x < lo ? lo : (x > hi ? hi : x); }

enum { CL_KIN, CL_REF, CL_CMD, CL_GAINS, CL_STATE, CL_OUT };

/* One cycle of the Cartesian law of one arm: its TCP from the tool frame,
 * the reference pose and speeds of the segment's quintic, the task-space
 * inertia, hybrid position/force control (see hybrid_update). The buffers'
 * layouts are in control/cartesian.py (CartesianLaw). Returns 0, or 1 when
 * the joint-space inertia is not positive definite (nothing written). */
static PyObject *cartesian_law(PyObject *mod, PyObject *arg) {
    PlanObject *pl = plan_arg(arg, "cartesian_law");
    if (pl == NULL)
        return NULL;
    double *kin = F64(pl, CL_KIN), *ref = F64(pl, CL_REF), *cmd = F64(pl, CL_CMD);
    double *gn = F64(pl, CL_GAINS), *st = F64(pl, CL_STATE), *out = F64(pl, CL_OUT);
    const double *J0 = kin, *R = kin + 42, *ft = kin + 51, *Mu = kin + 54, *g = kin + 103;
    const double *q = kin + 110, *qd = kin + 117, *wr = kin + 124;
    double seg_t = kin[130], dt = kin[131], t_s = kin[132];
    int integrate = kin[133] != 0;
    const double *sel = cmd, *goal_w = cmd + 6, *q_null = cmd + 12;
    const double *k = gn, *dgain = gn + 6, *ki = gn + 12, *imax = gn + 18, *k_null = gn + 24;
    const double *d_joint = gn + 31;
    double zeta = gn[38], k_adm = gn[39], k_adm_rot = gn[40], v_max = gn[41], w_max = gn[42];
    double a_max = gn[43], alpha_max = gn[44], contact_n = gn[45], ramp_s = gn[46];
    double tcp_off = gn[47];
    const double *base = gn + 48;
    double *Rt = st, *xi = st + 9, *xi_v = st + 15, *a_st = st + 21, *integral = st + 27;
    int i, j, c;

    /* the TCP: the tool's far end on its z axis; J from the tool frame to the TCP */
    double sensor[3], r[3], p[3], J[42];
    for (i = 0; i < 3; i++) {
        sensor[i] = ft[i] + base[i];
        r[i] = R[3 * i + 2] * tcp_off;
        p[i] = sensor[i] + r[i];
    }
    memcpy(J, J0, sizeof J);
    for (c = 0; c < 7; c++) { /* v_tcp = v_tool + w x r: J_lin -= [r]x J_ang */
        double wx = J0[21 + c], wy = J0[28 + c], wz = J0[35 + c];
        J[c] -= r[1] * wz - r[2] * wy;
        J[7 + c] -= r[2] * wx - r[0] * wz;
        J[14 + c] -= r[0] * wy - r[1] * wx;
    }

    /* the reference: quintic in position, the same blend about one axis in rotation */
    const double *start_p = ref, *goal_p = ref + 3, *start_R = ref + 6, *goal_R = ref + 15;
    const double *axis = ref + 24;
    double move_s = ref[27];
    double s = clampd(seg_t / move_s, 0.0, 1.0), s2 = s * s, s3 = s2 * s;
    double pos = 10 * s3 - 15 * s3 * s + 6 * s3 * s2;
    double vel = (30 * s2 - 60 * s3 + 30 * s2 * s2) / move_s;
    double acc = (60 * s - 180 * s2 + 120 * s3) / (move_s * move_s);
    double p_ref[3], v_ref[6], a_ref[6], R_ref[9], rel[9], rv[3], Rs[9];
    for (i = 0; i < 3; i++) {
        double d = goal_p[i] - start_p[i];
        p_ref[i] = start_p[i] + d * pos;
        v_ref[i] = d * vel;
        a_ref[i] = d * acc;
    }
    m3_mul_bt(goal_R, start_R, rel);
    matrix_to_rotvec(rel, rv);
    for (i = 0; i < 3; i++)
        rv[i] *= pos;
    rotvec_to_matrix(rv, Rs);
    m3_mul(Rs, start_R, R_ref);
    double sd = s < 1.0 ? vel : 0.0, sdd = s < 1.0 ? acc : 0.0;
    for (i = 0; i < 3; i++) {
        v_ref[3 + i] = axis[i] * sd;
        a_ref[3 + i] = axis[i] * sdd;
    }

    /* task-space inertia: Lambda = (J M^-1 J^T)^-1, its translational part,
     * the dynamically consistent null-space projector */
    double M[49], L7[49], MinvJt[42], A[36], lam[36], A3[9], lam_lin[9], N[49];
    for (i = 0; i < 7; i++)
        for (j = 0; j < 7; j++)
            M[7 * i + j] = j >= i ? Mu[7 * i + j] : Mu[7 * j + i];
    if (!cholesky(M, L7, 7))
        return PyLong_FromLong(1);
    for (c = 0; c < 6; c++) {
        double col[7];
        for (i = 0; i < 7; i++)
            col[i] = J[7 * c + i];
        chol_solve(L7, col, 7);
        for (i = 0; i < 7; i++)
            MinvJt[6 * i + c] = col[i];
    }
    for (i = 0; i < 6; i++)
        for (j = 0; j < 6; j++) {
            double v = 0;
            for (c = 0; c < 7; c++)
                v += J[7 * i + c] * MinvJt[6 * c + j];
            A[6 * i + j] = v + (i == j ? 1e-6 : 0.0);
        }
    for (i = 0; i < 6; i++) /* symmetric up to rounding: take the mean */
        for (j = i + 1; j < 6; j++)
            A[6 * i + j] = A[6 * j + i] = 0.5 * (A[6 * i + j] + A[6 * j + i]);
    if (!spd_inverse(A, lam, 6))
        return PyLong_FromLong(1);
    for (i = 0; i < 3; i++)
        for (j = 0; j < 3; j++)
            A3[3 * i + j] = A[6 * i + j];
    if (!spd_inverse(A3, lam_lin, 3))
        return PyLong_FromLong(1);
    {
        double LMt[42]; /* lam @ MinvJt^T: 6 x 7 */
        for (i = 0; i < 6; i++)
            for (c = 0; c < 7; c++) {
                double v = 0;
                for (j = 0; j < 6; j++)
                    v += lam[6 * i + j] * MinvJt[6 * c + j];
                LMt[7 * i + c] = v;
            }
        for (i = 0; i < 7; i++)
            for (c = 0; c < 7; c++) {
                double v = 0;
                for (j = 0; j < 6; j++)
                    v += J[7 * j + i] * LMt[7 * j + c];
                N[7 * i + c] = (i == c ? 1.0 : 0.0) - v;
            }
    }

    /* the wrench the tool applies, task axes, moment about the TCP */
    double f_w[3], m_w[3], applied[6], app_task[6];
    m3_vec(R, wr, f_w);
    m3_vec(R, wr + 3, m_w);
    {
        double rr[3] = {p[0] - sensor[0], p[1] - sensor[1], p[2] - sensor[2]};
        double m_tcp[3] = {m_w[0] - (rr[1] * f_w[2] - rr[2] * f_w[1]),
                           m_w[1] - (rr[2] * f_w[0] - rr[0] * f_w[2]),
                           m_w[2] - (rr[0] * f_w[1] - rr[1] * f_w[0])};
        for (i = 0; i < 3; i++) {
            applied[i] = -f_w[i];
            applied[3 + i] = -m_tcp[i];
        }
    }
    m3t_vec(Rt, applied, app_task);
    m3t_vec(Rt, applied + 3, app_task + 3);

    /* force axes: contact, the goal's ramp, the admittance on the reference */
    int any_force = 0;
    for (i = 0; i < 6; i++)
        any_force |= sel[i] != 0;
    if (any_force) {
        double fx = sel[0] * app_task[0], fy = sel[1] * app_task[1], fz = sel[2] * app_task[2];
        if (st[33] == 0 && sqrt(fx * fx + fy * fy + fz * fz) >= contact_n) {
            /* bumpless handover: the approach's speed stops, and the spring's
             * push along the force axes is handed over to the goal's ramp */
            double pr[3], pt[3];
            m3t_vec(Rt, p_ref, pr);
            m3t_vec(Rt, p, pt);
            st[33] = 1;
            st[34] = t_s;
            for (i = 0; i < 3; i++) {
                st[36 + i] = sel[i] * (pr[i] + xi[i] - pt[i]);
                xi_v[i] = 0.0;
            }
        }
        if (st[33] != 0) {
            double before = st[35], ramp = st[35] + dt / (ramp_s > 1e-9 ? ramp_s : 1e-9);
            st[35] = ramp < 1.0 ? ramp : 1.0;
            for (i = 0; i < 3; i++)
                xi[i] -= st[36 + i] * (st[35] - before);
        }
        for (i = 0; i < 6; i++) {
            double err = goal_w[i] - app_task[i];
            double want = i < 3 ? clampd(k_adm * err, -v_max, v_max)
                                : clampd(k_adm_rot * err, -w_max, w_max);
            double dv = (i < 3 ? a_max : alpha_max) * dt;
            double before = xi_v[i];
            xi_v[i] = sel[i] * (xi_v[i] + clampd(want - xi_v[i], -dv, dv));
            a_st[i] = (xi_v[i] - before) / (dt > 1e-9 ? dt : 1e-9);
            xi[i] += xi_v[i] * dt;
        }
    }

    /* the reference pose: position axes from the trajectory, force axes offset by xi */
    double p_task[3], p_goal[3], R_goal[9], sx[3], rvx[3], Rx[9];
    m3t_vec(Rt, p_ref, p_task);
    for (i = 0; i < 3; i++)
        if (sel[i] > 0)
            p_task[i] += xi[i];
    m3_vec(Rt, p_task, p_goal);
    for (i = 0; i < 3; i++)
        sx[i] = sel[3 + i] * xi[3 + i];
    m3_vec(Rt, sx, rvx);
    rotvec_to_matrix(rvx, Rx);
    m3_mul(Rx, R_ref, R_goal);
    double e[6], Rerr[9];
    for (i = 0; i < 3; i++)
        e[i] = p_goal[i] - p[i];
    m3_mul_bt(R_goal, R, Rerr);
    matrix_to_rotvec(Rerr, e + 3);

    /* speeds: the TCP's, and the reference's on the position axes */
    double v[6], vt[6], v_goal[6], ones[6], pm[6];
    for (i = 0; i < 6; i++) {
        double x = 0;
        for (c = 0; c < 7; c++)
            x += J[7 * i + c] * qd[c];
        v[i] = x;
    }
    m3t_vec(Rt, v_ref, vt);
    m3t_vec(Rt, v_ref + 3, vt + 3);
    for (i = 0; i < 6; i++) {
        vt[i] *= 1.0 - sel[i];
        ones[i] = 1.0 - sel[i];
    }
    m3_vec(Rt, vt, v_goal);
    m3_vec(Rt, vt + 3, v_goal + 3);
    m3_vec(Rt, ones, pm);
    m3_vec(Rt, ones + 3, pm + 3);

    /* integral action on the position-controlled axes only */
    if (integrate)
        for (i = 0; i < 6; i++) {
            double lim = ki[i] > 0 ? imax[i] / ki[i] : 0.0;
            double mask = fabs(pm[i]) > 0.5 ? 1.0 : 0.0;
            integral[i] = clampd(integral[i] + e[i] * dt * mask, -lim, lim);
        }
    double dvv[6], damp[6], F[6];
    for (i = 0; i < 6; i++) {
        dvv[i] = v_goal[i] - v[i];
        damp[i] = dgain[i] * dvv[i];
    }
    if (zeta > 0) {
        double D[9];
        damping3(lam_lin, k, zeta, D);
        m3_vec(D, dvv, damp);
    }
    for (i = 0; i < 6; i++)
        F[i] = k[i] * e[i] + damp[i] + ki[i] * integral[i];
    { /* the goal wrench, ramped in after contact */
        double gw[6], rg[6];
        for (i = 0; i < 6; i++)
            gw[i] = sel[i] * st[35] * goal_w[i];
        m3_vec(Rt, gw, rg);
        m3_vec(Rt, gw + 3, rg + 3);
        for (i = 0; i < 6; i++)
            F[i] += rg[i];
    }
    { /* inertia feedforward of the reference's acceleration */
        double at[6], aw[6];
        m3t_vec(Rt, a_ref, at);
        m3t_vec(Rt, a_ref + 3, at + 3);
        for (i = 0; i < 6; i++)
            at[i] = at[i] * (1.0 - sel[i]) + sel[i] * a_st[i];
        m3_vec(Rt, at, aw);
        m3_vec(Rt, at + 3, aw + 3);
        for (i = 0; i < 6; i++) {
            double x = 0;
            for (j = 0; j < 6; j++)
                x += lam[6 * i + j] * aw[j];
            F[i] += x;
        }
    }
    double post[7];
    for (c = 0; c < 7; c++)
        post[c] = k_null[c] * (q_null[c] - q[c]);
    for (c = 0; c < 7; c++) {
        double x = g[c] - d_joint[c] * qd[c];
        for (i = 0; i < 6; i++)
            x += J[7 * i + c] * F[i];
        for (j = 0; j < 7; j++)
            x += N[7 * c + j] * post[j];
        out[c] = x;
    }
    for (i = 0; i < 6; i++)
        out[7 + i] = app_task[i];
    for (i = 0; i < 3; i++) {
        out[13 + i] = p[i];
        out[19 + i] = p_ref[i];
    }
    matrix_to_rotvec(R, out + 16);
    return PyLong_FromLong(0);
}

/* -- PyBullet's joint states, unpacked -- */

/* states: the list getJointStates returns (position, velocity, reaction,
 * applied torque per joint); into q, qd, applied from index ``at``. */
static PyObject *unpack_states(PyObject *mod, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 5) {
        PyErr_SetString(PyExc_TypeError, "unpack_states(states, q, qd, applied, at)");
        return NULL;
    }
    PyObject *states = args[0];
    Py_ssize_t at = PyLong_AsSsize_t(args[4]);
    if (at < 0 && PyErr_Occurred())
        return NULL;
    Py_buffer v[3];
    int got = 0;
    PyObject *result = NULL;
    for (; got < 3; got++)
        if (PyObject_GetBuffer(args[1 + got], &v[got], PyBUF_WRITABLE | PyBUF_C_CONTIGUOUS) < 0)
            goto done;
    PyObject *seq = PySequence_Fast(states, "states must be a sequence");
    if (seq == NULL)
        goto done;
    Py_ssize_t n = PySequence_Fast_GET_SIZE(seq);
    for (int k = 0; k < 3; k++)
        if (v[k].itemsize != 8 || v[k].len / 8 < at + n) {
            PyErr_SetString(PyExc_ValueError, "unpack_states: arrays of float64, long enough");
            Py_DECREF(seq);
            goto done;
        }
    for (Py_ssize_t j = 0; j < n; j++) {
        PyObject *s = PySequence_Fast_GET_ITEM(seq, j);
        if (!PyTuple_Check(s) || PyTuple_GET_SIZE(s) < 4) {
            PyErr_SetString(PyExc_TypeError, "unpack_states: a joint state is a 4-tuple");
            Py_DECREF(seq);
            goto done;
        }
        ((double *)v[0].buf)[at + j] = PyFloat_AsDouble(PyTuple_GET_ITEM(s, 0));
        ((double *)v[1].buf)[at + j] = PyFloat_AsDouble(PyTuple_GET_ITEM(s, 1));
        ((double *)v[2].buf)[at + j] = PyFloat_AsDouble(PyTuple_GET_ITEM(s, 3));
    }
    Py_DECREF(seq);
    if (!PyErr_Occurred()) {
        Py_INCREF(Py_None);
        result = Py_None;
    }
done:
    for (int k = 0; k < got; k++)
        PyBuffer_Release(&v[k]);
    return result;
}

/* -- the DDM wire record: its checksum and tag -- */

/* A record's crc32 (zlib's) and its HMAC-SHA256 tag (RFC 2104) under the
 * link's key. The key's two padded blocks are hashed once, into a codec
 * (``wire_codec``); sealing or verifying a record then hashes its body and
 * one more block, with no Python call per step. The layout (where the
 * checksum and the tag lie) comes from the caller. */

static uint32_t CRC_TABLE[256];

static void crc_init(void) {
    for (uint32_t i = 0; i < 256; i++) {
        uint32_t c = i;
        for (int k = 0; k < 8; k++)
            c = c & 1 ? 0xEDB88320u ^ (c >> 1) : c >> 1;
        CRC_TABLE[i] = c;
    }
}

/* zlib's own (the one Python's zlib uses) where it loads: faster than the
 * table loop below */
typedef unsigned long (*ZlibCrc32)(unsigned long crc, const uint8_t *buf, unsigned int len);
static ZlibCrc32 ZLIB_CRC32 = NULL;

static uint32_t crc32_update(uint32_t crc, const uint8_t *p, size_t n) {
    if (ZLIB_CRC32 != NULL)
        return (uint32_t)ZLIB_CRC32(crc, p, (unsigned int)n);
    crc = ~crc;
    while (n--)
        crc = CRC_TABLE[(crc ^ *p++) & 0xFF] ^ (crc >> 8);
    return ~crc;
}

typedef struct {
    uint32_t h[8];
    uint64_t len; /* bytes hashed */
    uint8_t buf[64];
    uint32_t n; /* bytes waiting in buf */
} Sha256;

static const uint32_t SHA_K[64] = {
    0x428a2f98, 0x71374491, 0xb5c0fbcf, 0xe9b5dba5, 0x3956c25b, 0x59f111f1, 0x923f82a4,
    0xab1c5ed5, 0xd807aa98, 0x12835b01, 0x243185be, 0x550c7dc3, 0x72be5d74, 0x80deb1fe,
    0x9bdc06a7, 0xc19bf174, 0xe49b69c1, 0xefbe4786, 0x0fc19dc6, 0x240ca1cc, 0x2de92c6f,
    0x4a7484aa, 0x5cb0a9dc, 0x76f988da, 0x983e5152, 0xa831c66d, 0xb00327c8, 0xbf597fc7,
    0xc6e00bf3, 0xd5a79147, 0x06ca6351, 0x14292967, 0x27b70a85, 0x2e1b2138, 0x4d2c6dfc,
    0x53380d13, 0x650a7354, 0x766a0abb, 0x81c2c92e, 0x92722c85, 0xa2bfe8a1, 0xa81a664b,
    0xc24b8b70, 0xc76c51a3, 0xd192e819, 0xd6990624, 0xf40e3585, 0x106aa070, 0x19a4c116,
    0x1e376c08, 0x2748774c, 0x34b0bcb5, 0x391c0cb3, 0x4ed8aa4a, 0x5b9cca4f, 0x682e6ff3,
    0x748f82ee, 0x78a5636f, 0x84c87814, 0x8cc70208, 0x90befffa, 0xa4506ceb, 0xbef9a3f7,
    0xc67178f2,
};

#define ROR(x, n) (((x) >> (n)) | ((x) << (32 - (n))))

static void sha256_block(uint32_t h[8], const uint8_t *p) {
    uint32_t w[64];
    for (int i = 0; i < 16; i++)
        w[i] = (uint32_t)p[4 * i] << 24 | (uint32_t)p[4 * i + 1] << 16 |
               (uint32_t)p[4 * i + 2] << 8 | p[4 * i + 3];
    for (int i = 16; i < 64; i++) {
        uint32_t s0 = ROR(w[i - 15], 7) ^ ROR(w[i - 15], 18) ^ (w[i - 15] >> 3);
        uint32_t s1 = ROR(w[i - 2], 17) ^ ROR(w[i - 2], 19) ^ (w[i - 2] >> 10);
        w[i] = w[i - 16] + s0 + w[i - 7] + s1;
    }
    uint32_t a = h[0], b = h[1], c = h[2], d = h[3], e = h[4], f = h[5], g = h[6], k = h[7];
    for (int i = 0; i < 64; i++) {
        uint32_t t1 = k + (ROR(e, 6) ^ ROR(e, 11) ^ ROR(e, 25)) + ((e & f) ^ (~e & g)) +
                      SHA_K[i] + w[i];
        uint32_t t2 = (ROR(a, 2) ^ ROR(a, 13) ^ ROR(a, 22)) + ((a & b) ^ (a & c) ^ (b & c));
        k = g;
        g = f;
        f = e;
        e = d + t1;
        d = c;
        c = b;
        b = a;
        a = t1 + t2;
    }
    h[0] += a;
    h[1] += b;
    h[2] += c;
    h[3] += d;
    h[4] += e;
    h[5] += f;
    h[6] += g;
    h[7] += k;
}

/* The block function: OpenSSL's (SHA extensions where the CPU has them,
 * found in the libcrypto that Python's hashlib uses) or the portable one
 * above. OpenSSL's SHA256_Transform hashes one block into the state at the
 * start of its context. */
typedef void (*Sha256Transform)(void *ctx, const uint8_t *block);
static Sha256Transform SHA_TRANSFORM = NULL;

static void sha_init_backend(void) {
    if (getenv("REDISTRO_PORTABLE_WIRE") != NULL)
        return;
    void *lib = dlopen("libcrypto.so.3", RTLD_NOW | RTLD_LOCAL);
    if (lib != NULL)
        SHA_TRANSFORM = (Sha256Transform)dlsym(lib, "SHA256_Transform");
    void *z = dlopen("libz.so.1", RTLD_NOW | RTLD_LOCAL);
    if (z != NULL)
        ZLIB_CRC32 = (ZlibCrc32)dlsym(z, "crc32");
}

static inline void sha_block(uint32_t h[8], const uint8_t *p) {
    if (SHA_TRANSFORM != NULL) {
        uint32_t ctx[32]; /* an SHA256_CTX (112 bytes): the state first */
        memcpy(ctx, h, 32);
        SHA_TRANSFORM(ctx, p);
        memcpy(h, ctx, 32);
    } else
        sha256_block(h, p);
}

static void sha256_init(Sha256 *s) {
    static const uint32_t H0[8] = {0x6a09e667, 0xbb67ae85, 0x3c6ef372, 0xa54ff53a,
                                   0x510e527f, 0x9b05688c, 0x1f83d9ab, 0x5be0cd19};
    memcpy(s->h, H0, sizeof H0);
    s->len = 0;
    s->n = 0;
}

static void sha256_update(Sha256 *s, const uint8_t *p, size_t n) {
    s->len += n;
    if (s->n) {
        size_t take = 64 - s->n < n ? 64 - s->n : n;
        memcpy(s->buf + s->n, p, take);
        s->n += (uint32_t)take;
        p += take;
        n -= take;
        if (s->n < 64)
            return;
        sha_block(s->h, s->buf);
        s->n = 0;
    }
    for (; n >= 64; n -= 64, p += 64)
        sha_block(s->h, p);
    memcpy(s->buf, p, n);
    s->n = (uint32_t)n;
}

static void sha256_final(Sha256 *s, uint8_t out[32]) {
    uint64_t bits = s->len * 8;
    uint8_t pad[72] = {0x80};
    size_t padn = (s->n < 56 ? 56 : 120) - s->n;
    for (int i = 0; i < 8; i++)
        pad[padn + i] = (uint8_t)(bits >> (56 - 8 * i));
    sha256_update(s, pad, padn + 8);
    for (int i = 0; i < 8; i++) {
        out[4 * i] = (uint8_t)(s->h[i] >> 24);
        out[4 * i + 1] = (uint8_t)(s->h[i] >> 16);
        out[4 * i + 2] = (uint8_t)(s->h[i] >> 8);
        out[4 * i + 3] = (uint8_t)s->h[i];
    }
}

typedef struct {
    Sha256 inner, outer; /* the key's padded blocks, hashed */
    int64_t body, crc_at; /* the tag covers [0, body); the crc32 (u4) at crc_at */
} Codec;

static void codec_tag(const Codec *c, const uint8_t *body, size_t n, uint8_t out[32]) {
    Sha256 s = c->inner;
    uint8_t inner[32];
    sha256_update(&s, body, n);
    sha256_final(&s, inner);
    s = c->outer;
    sha256_update(&s, inner, 32);
    sha256_final(&s, out);
}

static uint32_t codec_crc(const Codec *c, const uint8_t *rec) {
    uint32_t crc = crc32_update(0, rec, (size_t)c->crc_at);
    return crc32_update(crc, rec + c->crc_at + 4, (size_t)(c->body - c->crc_at - 4));
}

/* wire_codec(key, body, crc_at) -> bytes: a codec for records of ``body``
 * bytes plus a 32-byte tag. */
static PyObject *wire_codec(PyObject *mod, PyObject *args) {
    Py_buffer key;
    long long body, crc_at;
    if (!PyArg_ParseTuple(args, "y*LL", &key, &body, &crc_at))
        return NULL;
    if (crc_at < 0 || crc_at + 4 > body) {
        PyBuffer_Release(&key);
        PyErr_SetString(PyExc_ValueError, "the checksum must lie inside the body");
        return NULL;
    }
    uint8_t block[64] = {0};
    if (key.len > 64) {
        Sha256 s;
        sha256_init(&s);
        sha256_update(&s, key.buf, (size_t)key.len);
        sha256_final(&s, block);
    } else
        memcpy(block, key.buf, (size_t)key.len);
    PyBuffer_Release(&key);
    Codec c;
    memset(&c, 0, sizeof c);
    uint8_t pad[64];
    for (int i = 0; i < 64; i++)
        pad[i] = block[i] ^ 0x36;
    sha256_init(&c.inner);
    sha256_update(&c.inner, pad, 64);
    for (int i = 0; i < 64; i++)
        pad[i] = block[i] ^ 0x5C;
    sha256_init(&c.outer);
    sha256_update(&c.outer, pad, 64);
    c.body = body;
    c.crc_at = crc_at;
    return PyBytes_FromStringAndSize((const char *)&c, sizeof c);
}

static const Codec *codec_arg(PyObject *obj) {
    if (!PyBytes_Check(obj) || PyBytes_GET_SIZE(obj) != (Py_ssize_t)sizeof(Codec)) {
        PyErr_SetString(PyExc_TypeError, "expected a codec from wire_codec()");
        return NULL;
    }
    return (const Codec *)PyBytes_AS_STRING(obj);
}

static PyObject *wire_backend(PyObject *mod, PyObject *unused) {
    return Py_BuildValue("(ss)", SHA_TRANSFORM != NULL ? "libcrypto" : "portable",
                         ZLIB_CRC32 != NULL ? "zlib" : "portable");
}

/* wire_tag(codec, data) -> the 32-byte HMAC-SHA256 of data. */
static PyObject *wire_tag(PyObject *mod, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "wire_tag(codec, data)");
        return NULL;
    }
    const Codec *c = codec_arg(args[0]);
    Py_buffer b;
    if (c == NULL || PyObject_GetBuffer(args[1], &b, PyBUF_SIMPLE) < 0)
        return NULL;
    uint8_t out[32];
    codec_tag(c, b.buf, (size_t)b.len, out);
    PyBuffer_Release(&b);
    return PyBytes_FromStringAndSize((const char *)out, 32);
}

/* wire_seal(codec, record): write the record's crc32 and tag (in place;
 * the record is body + 32 bytes). */
static PyObject *wire_seal(PyObject *mod, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "wire_seal(codec, record)");
        return NULL;
    }
    const Codec *c = codec_arg(args[0]);
    Py_buffer b;
    if (c == NULL || PyObject_GetBuffer(args[1], &b, PyBUF_WRITABLE) < 0)
        return NULL;
    if (b.len != c->body + 32) {
        PyBuffer_Release(&b);
        PyErr_Format(PyExc_ValueError, "a record of %lld bytes, got %zd", (long long)c->body + 32,
                     b.len);
        return NULL;
    }
    uint8_t *p = b.buf;
    st_u32(p + c->crc_at, codec_crc(c, p));
    codec_tag(c, p, (size_t)c->body, p + c->body);
    PyBuffer_Release(&b);
    Py_RETURN_NONE;
}

/* wire_verify(codec, record) -> 0 sound, 1 wrong size, 2 checksum, 3 tag
 * (compared in constant time). */
static PyObject *wire_verify(PyObject *mod, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "wire_verify(codec, record)");
        return NULL;
    }
    const Codec *c = codec_arg(args[0]);
    Py_buffer b;
    if (c == NULL || PyObject_GetBuffer(args[1], &b, PyBUF_SIMPLE) < 0)
        return NULL;
    long why = 0;
    const uint8_t *p = b.buf;
    if (b.len != c->body + 32)
        why = 1;
    else if (ld_u32(p + c->crc_at) != codec_crc(c, p))
        why = 2;
    else {
        uint8_t tag[32], diff = 0;
        codec_tag(c, p, (size_t)c->body, tag);
        for (int i = 0; i < 32; i++)
            diff |= tag[i] ^ p[c->body + i];
        why = diff ? 3 : 0;
    }
    PyBuffer_Release(&b);
    return PyLong_FromLong(why);
}

/* -- the DDM's exchange: a record admitted, a record emitted -- */

/* The common case of a ddm's step in one call each way; anything else (a
 * record to refuse or count, an e-stop, the first record of a link, a torn
 * read) is left untouched for the ddm's Python, which handles every case.
 *
 * ddm_admit(plan, record) -> the local robot whose Local Data block took the
 * record, or -1 (nothing changed: the Python path decides). It takes a
 * record only if it is sound (size, magic, version, crc32, tag), of the
 * kind this ddm receives, for one of its robots, without an e-stop, from
 * the source that robot's row has claimed (the row's last seq and stamp are
 * that source's admission state, shared with the Python path), newer than
 * the last in seq and stamp, and the robot's exchange already fresh. Then:
 * the payload is published into the robot's block (seqlock), the exchange
 * record counts the update, an ESC pays back its starving index (the sent
 * counter copied into the delivered block), and the command latency (now -
 * the payload's stamp) goes into the ring. */
enum {
    DA_MAGIC, DA_VERSION, DA_KIND, DA_PAYLOAD_AT, DA_SIZE, DA_H_MAGIC, DA_H_VERSION, DA_H_KIND,
    DA_H_ROBOT, DA_H_SOURCE, DA_H_SEQ, DA_H_STAMP, DA_H_ESTOP, DA_EX_SIZE, DA_EX_UPDATES,
    DA_EX_LAST, DA_EX_FRESH, DA_SENT_SEQ, DA_SENT_PAY, DA_DELIV_SEQ, DA_DELIV_PAY, DA_NPARAMS
};
enum { DR_GID, DR_SEQ_OFF, DR_PAY_OFF, DR_CLAIMED, DR_LAST_SEQ, DR_LAST_STAMP, DR_ROW = 8 };
enum { DS_LAT_COUNT, DS_FAST, DS_MASK, DS_NSTATE };

static int64_t now_ns(void) {
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return (int64_t)ts.tv_sec * 1000000000 + ts.tv_nsec;
}

static void seqlock_write(uint8_t *seq_at, uint8_t *dst, const uint8_t *src, size_t n) {
    volatile uint64_t *seq = (volatile uint64_t *)seq_at;
    uint64_t s = *seq;
    s += s & 1;
    *seq = s + 1;
    BARRIER();
    memcpy(dst, src, n);
    BARRIER();
    *seq = s + 2;
}

static int seqlock_read(const uint8_t *seq_at, const uint8_t *src, uint8_t *dst, size_t n) {
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

enum { DA_LD, DA_CODEC, DA_PARAMS, DA_ROWS, DA_SRC, DA_EX, DA_LAT, DA_STATE };

static int admit_plan_ok(PlanObject *pl) {
    if (pl->n[DA_PARAMS] < DA_NPARAMS || pl->n[DA_STATE] < DS_NSTATE ||
        pl->n[DA_CODEC] != (Py_ssize_t)sizeof(Codec)) {
        PyErr_SetString(PyExc_ValueError, "ddm_admit: a plan of the wrong sizes");
        return 0;
    }
    return 1;
}

/* The common case of one record (see above): the local robot, or -1. */
static long admit_record(PlanObject *pl, const uint8_t *r, Py_ssize_t len) {
    const int64_t *P = I64(pl, DA_PARAMS);
    const Codec *c = (const Codec *)U8(pl, DA_CODEC);
    Py_ssize_t nrows = pl->n[DA_ROWS] / DR_ROW;
    int64_t *row = NULL;
    Py_ssize_t i = 0;
    if (len != c->body + 32 || ld_u32(r + P[DA_H_MAGIC]) != (uint32_t)P[DA_MAGIC] ||
        (r[P[DA_H_VERSION]] | r[P[DA_H_VERSION] + 1] << 8) != P[DA_VERSION] ||
        r[P[DA_H_KIND]] != P[DA_KIND] || r[P[DA_H_ESTOP]] != 0)
        return -1;
    for (i = 0; i < nrows; i++)
        if (I64(pl, DA_ROWS)[i * DR_ROW + DR_GID] == r[P[DA_H_ROBOT]]) {
            row = I64(pl, DA_ROWS) + i * DR_ROW;
            break;
        }
    if (row == NULL || !row[DR_CLAIMED] ||
        memcmp(r + P[DA_H_SOURCE], U8(pl, DA_SRC) + 16 * i, 16) != 0)
        return -1;
    uint8_t *ex = U8(pl, DA_EX) + i * P[DA_EX_SIZE];
    if (!ex[P[DA_EX_FRESH]])
        return -1;
    uint64_t seq = ld_u64(r + P[DA_H_SEQ]);
    int64_t stamp = (int64_t)ld_u64(r + P[DA_H_STAMP]);
    if (seq <= (uint64_t)row[DR_LAST_SEQ] || stamp <= row[DR_LAST_STAMP])
        return -1; /* a drop to count: the Python path */
    if (ld_u32(r + c->crc_at) != codec_crc(c, r))
        return -1;
    uint8_t tag[32], diff = 0;
    codec_tag(c, r, (size_t)c->body, tag);
    for (int k = 0; k < 32; k++)
        diff |= tag[k] ^ r[c->body + k];
    if (diff)
        return -1;
    /* admitted */
    row[DR_LAST_SEQ] = (int64_t)seq;
    row[DR_LAST_STAMP] = stamp;
    uint8_t *ld = U8(pl, DA_LD);
    int64_t now = now_ns();
    seqlock_write(ld + row[DR_SEQ_OFF], ld + row[DR_PAY_OFF], r + P[DA_PAYLOAD_AT],
                  (size_t)P[DA_SIZE]);
    st_u64(ex + P[DA_EX_UPDATES], ld_u64(ex + P[DA_EX_UPDATES]) + 1);
    st_u64(ex + P[DA_EX_LAST], (uint64_t)now);
    int64_t *state = I64(pl, DA_STATE);
    if (P[DA_DELIV_SEQ] >= 0) {
        uint8_t counter[16];
        if (seqlock_read(ld + P[DA_SENT_SEQ], ld + P[DA_SENT_PAY], counter, 8)) {
            st_u64(counter + 8, (uint64_t)now);
            seqlock_write(ld + P[DA_DELIV_SEQ], ld + P[DA_DELIV_PAY], counter, 16);
        }
        int64_t pstamp = (int64_t)ld_u64(r + P[DA_PAYLOAD_AT]);
        Py_ssize_t ring = pl->n[DA_LAT];
        if (ring > 0 && 0 < pstamp && pstamp <= now) {
            I64(pl, DA_LAT)[state[DS_LAT_COUNT] % ring] = now - pstamp;
            state[DS_LAT_COUNT] += 1;
        }
    }
    state[DS_FAST] += 1;
    return (long)i;
}

static PyObject *ddm_admit(PyObject *mod, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 2) {
        PyErr_SetString(PyExc_TypeError, "ddm_admit(plan, record)");
        return NULL;
    }
    PlanObject *pl = plan_arg(args[0], "ddm_admit");
    if (pl == NULL || !admit_plan_ok(pl))
        return NULL;
    Py_buffer b;
    if (PyObject_GetBuffer(args[1], &b, PyBUF_SIMPLE) < 0)
        return NULL;
    long result = admit_record(pl, b.buf, b.len);
    PyBuffer_Release(&b);
    return PyLong_FromLong(result);
}

/* ddm_recv(plan, rx, fd) -> int: one non-blocking recv(2) from the stream
 * socket fd into the writable buffer rx, and its records admitted: the
 * bytes received (0: the peer closed) or -errno (nothing received:
 * -EAGAIN). When the bytes are whole records (a multiple of the record
 * size, rx not filled to the brim, at most 64), each is offered to
 * ddm_admit's common case; the plan's state DS_MASK has bit k set for each
 * record k admitted, the others are the caller's (they stay in rx). The
 * socket's system call and the records' admission without the
 * interpreter in between: the receiving half of a ddm's step. */
static PyObject *ddm_recv(PyObject *mod, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 3) {
        PyErr_SetString(PyExc_TypeError, "ddm_recv(plan, rx, fd)");
        return NULL;
    }
    PlanObject *pl = plan_arg(args[0], "ddm_admit"); /* ddm_admit's plan */
    if (pl == NULL || !admit_plan_ok(pl))
        return NULL;
    int fd = (int)PyLong_AsLong(args[2]);
    if (fd == -1 && PyErr_Occurred())
        return NULL;
    Py_buffer b;
    if (PyObject_GetBuffer(args[1], &b, PyBUF_WRITABLE) < 0)
        return NULL;
    const Codec *c = (const Codec *)U8(pl, DA_CODEC);
    Py_ssize_t size = c->body + 32;
    int64_t *state = I64(pl, DA_STATE);
    state[DS_MASK] = 0;
    ssize_t got = recv(fd, b.buf, (size_t)b.len, MSG_DONTWAIT);
    long result = got < 0 ? -errno : (long)got;
    if (got > 0 && got % size == 0 && got < b.len && got / size <= 64) {
        uint64_t mask = 0;
        for (Py_ssize_t k = 0; k < got / size; k++)
            if (admit_record(pl, (const uint8_t *)b.buf + k * size, size) >= 0)
                mask |= (uint64_t)1 << k;
        state[DS_MASK] = (int64_t)mask;
    }
    PyBuffer_Release(&b);
    return PyLong_FromLong(result);
}

/* ddm_send(plan, mask, reverse) -> int: the records ddm_emit encoded (bits
 * of mask; wire holds one record per row of fds) sent, each with one
 * non-blocking send(2) to its row's stream socket (fds; -1: none), rows in
 * order or in reverse order. status[i]
 * gets the bytes sent or -errno. Returns the bits of the records not sent
 * whole (no socket, a full buffer, an error, a short send): the caller's
 * transport counts or raises what each means. */
enum { DSD_WIRE, DSD_FDS, DSD_STATUS };

/* The send plan's sizes: its rows (robots), or 0 (an error is set). */
static Py_ssize_t send_rows_ok(PlanObject *pl) {
    Py_ssize_t n = pl->n[DSD_FDS];
    Py_ssize_t size = n > 0 ? pl->n[DSD_WIRE] / n : 0;
    if (n < 1 || n > 62 || pl->n[DSD_STATUS] < n || size <= 0 || pl->n[DSD_WIRE] != n * size) {
        PyErr_SetString(PyExc_ValueError, "ddm_send: a plan of the wrong sizes");
        return 0;
    }
    return n;
}

/* ddm_send's loop over a valid plan of n rows: the trouble bits. */
static long send_rows(PlanObject *pl, Py_ssize_t n, long mask, long reverse) {
    Py_ssize_t size = pl->n[DSD_WIRE] / n;
    long trouble = 0;
    for (Py_ssize_t k = 0; k < n; k++) {
        Py_ssize_t i = reverse ? n - 1 - k : k;
        if (!(mask >> i & 1))
            continue;
        int fd = (int)I64(pl, DSD_FDS)[i];
        int64_t *status = I64(pl, DSD_STATUS) + i;
        if (fd < 0) {
            *status = 0;
            trouble |= 1L << i;
            continue;
        }
        ssize_t sent = send(fd, U8(pl, DSD_WIRE) + i * size, (size_t)size,
                            MSG_DONTWAIT | MSG_NOSIGNAL);
        *status = sent < 0 ? -errno : (int64_t)sent;
        if (sent != size)
            trouble |= 1L << i;
    }
    return trouble;
}

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
    if (n == 0)
        return NULL;
    return PyLong_FromLong(send_rows(pl, n, mask, reverse));
}

/* ddm_emit(plan) -> a bit mask of the robots whose wire buffer holds a new
 * record to send, or -1 (a torn read: the Python path reads again). For
 * each robot, the out block (its node's command or feedback) is read into
 * the local record; a newly produced one (seq_src not 0 and not the last
 * sent) is encoded behind the row's next seq, now, no e-stop, and sealed;
 * the exchange record counts it sent. */
enum {
    DE_PAYLOAD_AT, DE_SIZE, DE_SEQSRC_AT, DE_H_SEQ, DE_H_STAMP, DE_H_ESTOP, DE_EX_SIZE, DE_EX_SENT,
    DE_NPARAMS
};
enum { DE_SEQ_OFF, DE_PAY_OFF, DE_LAST_OUT, DE_SEQ, DE_ROW = 8 };
enum { DE_LD, DE_CODEC, DE_PARAMS, DE_ROWS, DE_OUT, DE_WIRE, DE_EX };

/* The emit plan's sizes are sound (else an error is set, 0). */
static int emit_plan_ok(PlanObject *pl) {
    if (pl->n[DE_PARAMS] < DE_NPARAMS || pl->n[DE_CODEC] != (Py_ssize_t)sizeof(Codec)) {
        PyErr_SetString(PyExc_ValueError, "ddm_emit: a plan of the wrong sizes");
        return 0;
    }
    const int64_t *P = I64(pl, DE_PARAMS);
    const Codec *c = (const Codec *)U8(pl, DE_CODEC);
    Py_ssize_t nrows = pl->n[DE_ROWS] / DE_ROW, size = P[DE_SIZE], wsize = c->body + 32;
    if (nrows > 62 || pl->n[DE_OUT] < nrows * size || pl->n[DE_WIRE] < nrows * wsize) {
        PyErr_SetString(PyExc_ValueError, "ddm_emit: a plan of the wrong sizes");
        return 0;
    }
    return 1;
}

/* ddm_emit's work over a valid plan: the mask, or -1 (a torn read). */
static long emit_rows(PlanObject *pl) {
    const int64_t *P = I64(pl, DE_PARAMS);
    const Codec *c = (const Codec *)U8(pl, DE_CODEC);
    Py_ssize_t nrows = pl->n[DE_ROWS] / DE_ROW, size = P[DE_SIZE], wsize = c->body + 32;
    uint8_t *ld = U8(pl, DE_LD);
    long mask = 0;
    for (Py_ssize_t i = 0; i < nrows; i++) {
        int64_t *row = I64(pl, DE_ROWS) + i * DE_ROW;
        uint8_t *out = U8(pl, DE_OUT) + i * size;
        if (!seqlock_read(ld + row[DE_SEQ_OFF], ld + row[DE_PAY_OFF], out, (size_t)size))
            return -1;
        int64_t produced = (int64_t)ld_u64(out + P[DE_SEQSRC_AT]);
        if (produced == 0 || produced == row[DE_LAST_OUT])
            continue;
        row[DE_LAST_OUT] = produced;
        row[DE_SEQ] += 1;
        uint8_t *w = U8(pl, DE_WIRE) + i * wsize;
        st_u64(w + P[DE_H_SEQ], (uint64_t)row[DE_SEQ]);
        st_u64(w + P[DE_H_STAMP], (uint64_t)now_ns());
        w[P[DE_H_ESTOP]] = 0;
        memcpy(w + P[DE_PAYLOAD_AT], out, (size_t)size);
        st_u32(w + c->crc_at, codec_crc(c, w));
        codec_tag(c, w, (size_t)c->body, w + c->body);
        uint8_t *ex = U8(pl, DE_EX) + i * P[DE_EX_SIZE];
        st_u64(ex + P[DE_EX_SENT], ld_u64(ex + P[DE_EX_SENT]) + 1);
        mask |= 1L << i;
    }
    return mask;
}

static PyObject *ddm_emit(PyObject *mod, PyObject *arg) {
    PlanObject *pl = plan_arg(arg, "ddm_emit");
    if (pl == NULL || !emit_plan_ok(pl))
        return NULL;
    return PyLong_FromLong(emit_rows(pl));
}

/* ddm_reply(admit_plan, emit_plan, send_plan, rx, fd) -> int: an ESC ddm's
 * usual step over a stream socket in one call, the paper's receive and
 * reply: ddm_recv (one non-blocking recv(2) from fd into rx, its whole
 * records offered to ddm_admit's common case; the admit plan's DS_MASK
 * says which were taken), and when every record received was admitted,
 * ddm_emit and ddm_send (the node's new feedback sealed and sent back, row
 * 0 of the send plan). Returns what recv returned (bytes, 0 closed,
 * -errno); the send plan's status holds, after its n rows, the emit's
 * mask (-2: not run; -1: a torn read) and the send's trouble bits. The
 * usual step done whole (every record admitted, the reply sent or none
 * new) returns DDM_REPLIED instead (not a byte count: 2^40). A return the
 * caller does not take whole (a part record, a record refused, the end)
 * is the general path's, with the bytes left in rx. */
enum { DRP_EMIT = 0, DRP_TROUBLE = 1, DRP_EXTRA = 2 };
#define DDM_REPLIED ((int64_t)1 << 40)

static PyObject *ddm_reply(PyObject *mod, PyObject *const *args, Py_ssize_t nargs) {
    if (nargs != 5) {
        PyErr_SetString(PyExc_TypeError, "ddm_reply(admit_plan, emit_plan, send_plan, rx, fd)");
        return NULL;
    }
    PlanObject *ap = plan_arg(args[0], "ddm_admit");
    PlanObject *ep = ap == NULL ? NULL : plan_arg(args[1], "ddm_emit");
    PlanObject *sp = ep == NULL ? NULL : plan_arg(args[2], "ddm_send");
    if (sp == NULL || !admit_plan_ok(ap) || !emit_plan_ok(ep))
        return NULL;
    Py_ssize_t n = send_rows_ok(sp);
    if (n == 0)
        return NULL;
    if (sp->n[DSD_STATUS] < n + DRP_EXTRA) {
        PyErr_SetString(PyExc_ValueError, "ddm_reply: the send plan's status has no room");
        return NULL;
    }
    int fd = (int)PyLong_AsLong(args[4]);
    if (fd == -1 && PyErr_Occurred())
        return NULL;
    Py_buffer b;
    if (PyObject_GetBuffer(args[3], &b, PyBUF_WRITABLE) < 0)
        return NULL;
    const Codec *c = (const Codec *)U8(ap, DA_CODEC);
    Py_ssize_t size = c->body + 32;
    int64_t *state = I64(ap, DA_STATE), *status = I64(sp, DSD_STATUS) + n;
    state[DS_MASK] = 0;
    status[DRP_EMIT] = -2;
    status[DRP_TROUBLE] = 0;
    ssize_t got = recv(fd, b.buf, (size_t)b.len, MSG_DONTWAIT);
    long result = got < 0 ? -errno : (long)got;
    if (got > 0 && got % size == 0 && got < b.len && got / size <= 64) {
        Py_ssize_t records = got / size;
        uint64_t mask = 0;
        for (Py_ssize_t k = 0; k < records; k++)
            if (admit_record(ap, (const uint8_t *)b.buf + k * size, size) >= 0)
                mask |= (uint64_t)1 << k;
        state[DS_MASK] = (int64_t)mask;
        if (mask == ((uint64_t)1 << records) - 1) {
            long emitted = emit_rows(ep);
            status[DRP_EMIT] = emitted;
            if (emitted > 0)
                status[DRP_TROUBLE] = send_rows(sp, n, emitted, 0);
            if (emitted >= 0 && status[DRP_TROUBLE] == 0) {
                PyBuffer_Release(&b);
                return PyLong_FromLongLong(DDM_REPLIED);
            }
        }
    }
    PyBuffer_Release(&b);
    return PyLong_FromLong(result);
}

/* -- a ddm's answer, whole, in the transport's thread -- */

/* Answerer(admit_plan, emit_plan, publish_plan, gate, estop_at, lock, put,
 * inbox, fallback, wake, before): the callable a transport that delivers
 * records on a thread of its own (zenoh's) hands each record to, in that
 * thread, instead of the ddm's Python answer (Ddm._answer, which it does
 * the same as, and which stays the reference). Called with a record (a
 * bytes-like object) or a sample (its ``payload.to_bytes()``), it makes a
 * ddm's usual step for it whole. An ESC's: the command admitted (ddm_admit's
 * common case), the node's newest feedback emitted (ddm_emit) and handed to
 * ``put`` as the reply, and every 64th answer the exchange records
 * published (publish_plan, seq_write's). The SSC's (``put`` None): the
 * feedback admitted and the exchange published (its manager watches every
 * robot's updates). It takes a record only when gate[AG_OPEN]
 * says the ddm answers, the manager's e-stop byte (ld byte estop_at of the
 * admit plan) is clear, ``inbox`` is empty (records queued before it go
 * first), and ``lock`` (the ddm's step lock) is free; anything else goes to
 * ``fallback(raw)`` untouched (the transport's Python path: the ddm's own
 * step). A torn read of the feedback, or a put that raised, leaves the
 * reply to the ddm: gate[AG_OWED] set and ``wake()`` called. gate[AG_ANSWERED]
 * counts the records taken. ``before`` (None, or a callable run first on
 * every call: a bench's stand-in for the acquisition). The first call in
 * each thread keeps that thread's Python thread state (one PyGILState_Ensure
 * never released), as zenoh's threads otherwise make and free one around
 * every record. */
enum { AG_OPEN, AG_ANSWERED, AG_OWED, AG_NGATE };
#define KEPT_THREADS 8

typedef struct {
    PyObject_HEAD
    PyObject *admit, *emit, *publish, *gate_obj, *acquire, *release, *put, *inbox, *fallback,
        *wake, *before;
    Py_buffer gate;
    Py_ssize_t estop_at;
    int closed;
    int nkept;
    unsigned long kept[KEPT_THREADS];
} AnswererObject;

static PyObject *STR_PAYLOAD, *STR_TO_BYTES;

static int Answerer_traverse(AnswererObject *self, visitproc visit, void *arg) {
    Py_VISIT(self->admit);
    Py_VISIT(self->emit);
    Py_VISIT(self->publish);
    Py_VISIT(self->gate_obj);
    Py_VISIT(self->acquire);
    Py_VISIT(self->release);
    Py_VISIT(self->put);
    Py_VISIT(self->inbox);
    Py_VISIT(self->fallback);
    Py_VISIT(self->wake);
    Py_VISIT(self->before);
    return 0;
}

static int Answerer_clear(AnswererObject *self) {
    if (self->gate_obj != NULL && self->gate.obj != NULL)
        PyBuffer_Release(&self->gate);
    Py_CLEAR(self->admit);
    Py_CLEAR(self->emit);
    Py_CLEAR(self->publish);
    Py_CLEAR(self->gate_obj);
    Py_CLEAR(self->acquire);
    Py_CLEAR(self->release);
    Py_CLEAR(self->put);
    Py_CLEAR(self->inbox);
    Py_CLEAR(self->fallback);
    Py_CLEAR(self->wake);
    Py_CLEAR(self->before);
    return 0;
}

static void Answerer_dealloc(AnswererObject *self) {
    PyObject_GC_UnTrack(self);
    Answerer_clear(self);
    Py_TYPE(self)->tp_free((PyObject *)self);
}

static int Answerer_init(AnswererObject *self, PyObject *args, PyObject *kwds) {
    PyObject *admit, *emit, *publish, *gate, *lock, *put, *inbox, *fallback, *wake, *before;
    Py_ssize_t estop_at;
    if (!PyArg_ParseTuple(args, "O!O!O!OnOOOOOO", &PlanType, &admit, &PlanType, &emit, &PlanType,
                          &publish, &gate, &estop_at, &lock, &put, &inbox, &fallback, &wake,
                          &before))
        return -1;
    PlanObject *ap = (PlanObject *)admit, *ep = (PlanObject *)emit, *pp = (PlanObject *)publish;
    if (strcmp(SIGNATURES[ap->kernel].name, "ddm_admit") != 0 ||
        strcmp(SIGNATURES[ep->kernel].name, "ddm_emit") != 0 ||
        strcmp(SIGNATURES[pp->kernel].name, "seq_write") != 0) {
        PyErr_SetString(PyExc_ValueError, "Answerer: plans of ddm_admit, ddm_emit, seq_write");
        return -1;
    }
    if (!admit_plan_ok(ap) || !emit_plan_ok(ep))
        return -1;
    if (estop_at < 0 || estop_at >= ap->n[DA_LD]) {
        PyErr_SetString(PyExc_ValueError, "Answerer: the e-stop byte is outside Local Data");
        return -1;
    }
    Answerer_clear(self);
    if (PyObject_GetBuffer(gate, &self->gate, PyBUF_WRITABLE | PyBUF_C_CONTIGUOUS) < 0)
        return -1;
    if (self->gate.len < AG_NGATE * 8 || (uintptr_t)self->gate.buf % 8) {
        PyBuffer_Release(&self->gate);
        PyErr_SetString(PyExc_ValueError, "Answerer: the gate is 3 aligned int64");
        return -1;
    }
    self->gate_obj = Py_NewRef(gate);
    self->acquire = PyObject_GetAttrString(lock, "acquire");
    self->release = PyObject_GetAttrString(lock, "release");
    if (self->acquire == NULL || self->release == NULL) {
        Answerer_clear(self);
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
static int answer_try_lock(AnswererObject *self) {
    PyObject *r = PyObject_CallOneArg(self->acquire, Py_False);
    if (r == NULL)
        return -1;
    int taken = r == Py_True;
    Py_DECREF(r);
    return taken;
}

/* The usual record taken whole (1), or left to the fallback (0), -1 an error. */
static int answer_record(AnswererObject *self, const uint8_t *raw, Py_ssize_t len) {
    int64_t *gate = (int64_t *)self->gate.buf;
    PlanObject *ap = (PlanObject *)self->admit, *ep = (PlanObject *)self->emit;
    if (self->closed || !gate[AG_OPEN] || U8(ap, DA_LD)[self->estop_at] ||
        PyObject_Size(self->inbox) != 0)
        return 0;
    int taken = answer_try_lock(self);
    if (taken <= 0)
        return taken;
    int done = 0, owed = 0;
    /* (under the lock: the ddm may have closed the gate meanwhile) */
    if (gate[AG_OPEN] && !U8(ap, DA_LD)[self->estop_at] && admit_record(ap, raw, len) >= 0) {
        done = 1;
        gate[AG_ANSWERED] += 1;
        long mask = self->put == NULL ? 0 : emit_rows(ep);
        if (mask > 0) {
            Py_ssize_t wsize = ((const Codec *)U8(ep, DE_CODEC))->body + 32;
            PyObject *out = PyBytes_FromStringAndSize((const char *)U8(ep, DE_WIRE), wsize);
            PyObject *r = out == NULL ? NULL : PyObject_CallOneArg(self->put, out);
            Py_XDECREF(out);
            if (r == NULL) {
                PyErr_Clear(); /* (a closing session): the ddm's step sends, or learns why */
                owed = 1;
            }
            Py_XDECREF(r);
        } else if (mask < 0)
            owed = 1; /* a torn read of the feedback: the ddm reads it again */
        if (self->put == NULL || !(gate[AG_ANSWERED] & 63)) {
            PyObject *r = seq_write(NULL, self->publish);
            Py_XDECREF(r);
        }
        if (owed)
            gate[AG_OWED] = 1;
    }
    PyObject *r = PyObject_CallNoArgs(self->release);
    if (r == NULL)
        return -1;
    Py_DECREF(r);
    if (owed) {
        r = PyObject_CallNoArgs(self->wake);
        if (r == NULL)
            return -1;
        Py_DECREF(r);
    }
    return done;
}

static PyObject *Answerer_call(AnswererObject *self, PyObject *args, PyObject *kwds) {
    PyObject *arg;
    if (!PyArg_UnpackTuple(args, "Answerer", 1, 1, &arg))
        return NULL;
    if (self->admit == NULL) {
        PyErr_SetString(PyExc_ValueError, "Answerer: not initialized");
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

static PyObject *Answerer_close(AnswererObject *self, PyObject *unused) {
    self->closed = 1;
    Py_RETURN_NONE;
}

static PyMethodDef ANSWERER_METHODS[] = {
    {"close", (PyCFunction)Answerer_close, METH_NOARGS,
     "Take no more records (each goes to the fallback)."},
    {NULL, NULL, 0, NULL},
};

static PyTypeObject AnswererType = {
    PyVarObject_HEAD_INIT(NULL, 0).tp_name = "redistro._kernels.Answerer",
    .tp_basicsize = sizeof(AnswererObject),
    .tp_flags = Py_TPFLAGS_DEFAULT | Py_TPFLAGS_HAVE_GC,
    .tp_new = PyType_GenericNew,
    .tp_init = (initproc)Answerer_init,
    .tp_dealloc = (destructor)Answerer_dealloc,
    .tp_traverse = (traverseproc)Answerer_traverse,
    .tp_clear = (inquiry)Answerer_clear,
    .tp_call = (ternaryfunc)Answerer_call,
    .tp_methods = ANSWERER_METHODS,
    .tp_doc = "An ESC ddm's answer in the transport's thread (see the C source).",
};

/* -- introspection -- */

static PyObject *signature(PyObject *mod, PyObject *arg) {
    const char *name = PyUnicode_AsUTF8(arg);
    if (name == NULL)
        return NULL;
    int k = find_signature(name);
    if (k < 0) {
        PyErr_Format(PyExc_ValueError, "no kernel %s", name);
        return NULL;
    }
    const Signature *sig = &SIGNATURES[k];
    PyObject *out = PyTuple_New(sig->nargs);
    if (out == NULL)
        return NULL;
    for (int i = 0; i < sig->nargs; i++) {
        char t[2] = {sig->args[i].type, 0};
        PyObject *pair = Py_BuildValue("(ss)", sig->args[i].name, t);
        if (pair == NULL) {
            Py_DECREF(out);
            return NULL;
        }
        PyTuple_SET_ITEM(out, i, pair);
    }
    return out;
}

static PyMethodDef METHODS[] = {
    {"copy", copy, METH_O, "Copy many byte ranges from one buffer to another."},
    {"seq_read", seq_read, METH_O, "Consistent copies of many seqlocked blocks."},
    {"seq_write", seq_write, METH_O, "Publish many seqlocked blocks."},
    {"chassis_apply", chassis_apply, METH_O, "The chassis: outputs -> joints."},
    {"chassis_sample", chassis_sample, METH_O, "The chassis: joints -> boards."},
    {"driver_decode", driver_decode, METH_O, "The driver: boards -> robot units."},
    {"driver_dac", driver_dac, METH_O, "The driver: torques -> DAC codes."},
    {"joint_pid", joint_pid, METH_O, "A joint PID with gravity compensation, one cycle."},
    {"quintic", quintic, METH_O, "A quintic's reference at one time."},
    {"cartesian_law", cartesian_law, METH_O, "The SSC: one arm's Cartesian law, one cycle."},
    {"guard_prepare", guard_prepare, METH_O, "The sender: a command prepared and screened."},
    {"unpack_states", (PyCFunction)(void (*)(void))unpack_states, METH_FASTCALL,
     "PyBullet joint states -> q, qd, applied torque."},
    {"wire_codec", wire_codec, METH_VARARGS, "A DDM record codec: the key's HMAC states, the layout."},
    {"wire_tag", (PyCFunction)(void (*)(void))wire_tag, METH_FASTCALL, "HMAC-SHA256 of data."},
    {"wire_seal", (PyCFunction)(void (*)(void))wire_seal, METH_FASTCALL,
     "Write a record's crc32 and tag."},
    {"wire_verify", (PyCFunction)(void (*)(void))wire_verify, METH_FASTCALL,
     "Check a record's size, crc32 and tag: 0 sound, 1 size, 2 checksum, 3 tag."},
    {"ddm_admit", (PyCFunction)(void (*)(void))ddm_admit, METH_FASTCALL,
     "The DDM: a sound, fresh record of the usual kind admitted into Local Data, or -1."},
    {"ddm_emit", ddm_emit, METH_O, "The DDM: new records encoded for sending (a bit mask)."},
    {"ddm_recv", (PyCFunction)(void (*)(void))ddm_recv, METH_FASTCALL,
     "The DDM: one recv from a socket, its whole records admitted (see the source)."},
    {"ddm_send", (PyCFunction)(void (*)(void))ddm_send, METH_FASTCALL,
     "The DDM: encoded records sent to their sockets; the bits of those not sent whole."},
    {"ddm_reply", (PyCFunction)(void (*)(void))ddm_reply, METH_FASTCALL,
     "The DDM: an ESC's receive and reply on a stream socket in one call (see the source)."},
    {"wire_backend", wire_backend, METH_NOARGS, "Which SHA-256 block and crc32 functions run."},
    {"signature", signature, METH_O, "A kernel's arguments: ((name, type), ...)."},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef MODULE = {
    PyModuleDef_HEAD_INIT, "redistro._kernels",
    "The per-cycle arithmetic of the I/O paths, fused (see the C source).", -1, METHODS,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__kernels(void) {
    crc_init();
    sha_init_backend();
    if (PyType_Ready(&PlanType) < 0 || PyType_Ready(&AnswererType) < 0)
        return NULL;
    STR_PAYLOAD = PyUnicode_InternFromString("payload");
    STR_TO_BYTES = PyUnicode_InternFromString("to_bytes");
    if (STR_PAYLOAD == NULL || STR_TO_BYTES == NULL)
        return NULL;
    PyObject *m = PyModule_Create(&MODULE);
    if (m == NULL)
        return NULL;
    Py_INCREF(&PlanType);
    if (PyModule_AddObject(m, "Plan", (PyObject *)&PlanType) < 0) {
        Py_DECREF(&PlanType);
        Py_DECREF(m);
        return NULL;
    }
    Py_INCREF(&AnswererType);
    if (PyModule_AddObject(m, "Answerer", (PyObject *)&AnswererType) < 0) {
        Py_DECREF(&AnswererType);
        Py_DECREF(m);
        return NULL;
    }
    return m;
}
