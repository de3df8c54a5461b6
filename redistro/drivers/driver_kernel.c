/*
 * The robot-level driver's kernels (their reference: drivers/robot.py,
 * RobotDriver._decode_numpy and _dac_numpy): the boards' snapshot decoded
 * into robot units, and torques into DAC codes. The state, parameter and
 * jump buffers are declared in drivers/driver_layout.py.
 */
#include "../kernels.h"

#include <math.h>

enum {
    DD_IMAGE, DD_STEP_OFF, DD_COUNTER_OFF, DD_LATCH_OFF, DD_LCOUNT_OFF, DD_LEDGE_OFF,
    DD_TACH_OFF, DD_TORQUE_OFF, DD_READBACK_OFF, DD_HOME_WORD, DD_HOME_BIT, DD_BRAKE_WORD,
    DD_BRAKE_BIT, DD_STRAIN_OFF, DD_CAL_OFF, DD_CPR, DD_TACH_SCALE, DD_TORQUE_SCALE,
    DD_DAC_SCALE, DD_RAW, DD_ACC, DD_QREF, DD_PREV_Q, DD_STATE, DD_PARAMS, DD_Q, DD_QD,
    DD_TAU, DD_WRENCH, DD_HOME, DD_BRAKES, DD_LCOUNT, DD_LEDGE, DD_LATCH_Q, DD_OUT
};

enum { DT_IMAGE, DT_TAU, DT_VOLTS_PER_NM, DT_CODE_OFF, DT_RESIDUAL, DT_CARRY };

#define MAX_JOINTS 64
#define STATE(pl, f) I64(pl, DD_STATE)[DRIVER_DECODE_STATE_##f]
#define PARAM(pl, f) F64(pl, DD_PARAMS)[DRIVER_DECODE_PARAMS_##f]

static inline int64_t wrap24(int64_t d) { return ((d + (1 << 23)) & 0xFFFFFF) - (1 << 23); }

/* The counters' change since the last sample, judged and accumulated: 0,
 * or 1 + the joint whose counter moved more than any motion could (its
 * change, the limit and the steps in ``out``; nothing updated then). */
static long decode_counters(PlanObject *pl, const int64_t *now_raw, Py_ssize_t n, int64_t step) {
    int64_t *raw = I64(pl, DD_RAW), *acc = I64(pl, DD_ACC);
    double *cpr = F64(pl, DD_CPR), *qref = F64(pl, DD_QREF), *q = F64(pl, DD_Q);
    if (!STATE(pl, HAVE_REF)) {
        for (Py_ssize_t j = 0; j < n; j++) {
            int64_t s = now_raw[j] >= (1 << 23) ? now_raw[j] - (1 << 24) : now_raw[j];
            qref[j] = (double)s / cpr[j];
            acc[j] = 0;
        }
        STATE(pl, HAVE_REF) = 1;
    } else {
        int64_t deltas[MAX_JOINTS];
        for (Py_ssize_t j = 0; j < n; j++)
            deltas[j] = wrap24(now_raw[j] - raw[j]);
        int64_t prev = STATE(pl, PREV_STEP);
        if (PARAM(pl, JUMP_LIMIT_RAD_S) > 0 && prev >= 0) {
            int64_t steps = step - prev < 1 ? 1 : step - prev;
            for (Py_ssize_t j = 0; j < n; j++) {
                double limit = PARAM(pl, JUMP_LIMIT_RAD_S) * cpr[j] * (double)steps /
                                   PARAM(pl, PHYSICS_HZ) + 2.0;
                if (fabs((double)deltas[j]) > limit) {
                    double *out = F64(pl, DD_OUT);
                    out[DRIVER_DECODE_OUT_DELTA] = (double)deltas[j];
                    out[DRIVER_DECODE_OUT_LIMIT] = limit;
                    out[DRIVER_DECODE_OUT_STEPS] = (double)steps;
                    return (long)j + 1;
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
    return 0;
}

/* Latches (where each joint was at its last home edge) and speeds
 * (tachometers, or the counters differentiated on the boards' clock). */
static void decode_latches_speeds(PlanObject *pl, const uint8_t *img, const int64_t *now_raw,
                                  Py_ssize_t n, int64_t step) {
    int64_t *loff = I64(pl, DD_LATCH_OFF), *lcoff = I64(pl, DD_LCOUNT_OFF);
    int64_t *leoff = I64(pl, DD_LEDGE_OFF);
    uint8_t *lcount = U8(pl, DD_LCOUNT); /* uint32 each */
    uint8_t *ledge = U8(pl, DD_LEDGE);
    double *lq = F64(pl, DD_LATCH_Q), *q = F64(pl, DD_Q), *cpr = F64(pl, DD_CPR);
    for (Py_ssize_t j = 0; j < n; j++) {
        int64_t back = wrap24((int64_t)ld_u32(img + loff[j]) - now_raw[j]);
        lq[j] = q[j] + (double)back / cpr[j];
        st_u32(lcount + 4 * j, ld_u32(img + lcoff[j]));
        ledge[j] = img[leoff[j]];
    }
    double *qd = F64(pl, DD_QD), *prev_q = F64(pl, DD_PREV_Q);
    int64_t prev = STATE(pl, PREV_STEP);
    if (PARAM(pl, HAS_TACH) != 0) {
        int64_t *toff = I64(pl, DD_TACH_OFF);
        double *ts = F64(pl, DD_TACH_SCALE);
        for (Py_ssize_t j = 0; j < n; j++)
            qd[j] = (double)ld_i16(img + toff[j]) * ts[j];
    } else if (prev >= 0 && step > prev) {
        double dt = (double)(step - prev) / PARAM(pl, PHYSICS_HZ);
        for (Py_ssize_t j = 0; j < n; j++)
            qd[j] = (q[j] - prev_q[j]) / dt;
    }
    STATE(pl, PREV_STEP) = step;
    for (Py_ssize_t j = 0; j < n; j++)
        prev_q[j] = q[j];
}

/* Torques (torque sensors, or the DAC readback through the motor model),
 * home switches, brakes, and the wrist's wrench (gauges through the
 * calibration matrix; zero without a wrist). */
static void decode_rest(PlanObject *pl, const uint8_t *img, Py_ssize_t n) {
    double *tau = F64(pl, DD_TAU);
    int torque = PARAM(pl, HAS_TORQUE) != 0;
    int64_t *toff = I64(pl, torque ? DD_TORQUE_OFF : DD_READBACK_OFF);
    double *ts = F64(pl, torque ? DD_TORQUE_SCALE : DD_DAC_SCALE);
    for (Py_ssize_t j = 0; j < n; j++)
        tau[j] = (double)ld_i16(img + toff[j]) * ts[j];
    int64_t *hw = I64(pl, DD_HOME_WORD), *hb = I64(pl, DD_HOME_BIT);
    int64_t *bw = I64(pl, DD_BRAKE_WORD), *bb = I64(pl, DD_BRAKE_BIT);
    uint8_t *home = U8(pl, DD_HOME), *brakes = U8(pl, DD_BRAKES);
    for (Py_ssize_t j = 0; j < n; j++) {
        home[j] = (ld_u32(img + hw[j]) >> hb[j]) & 1u;
        brakes[j] = ((ld_u32(img + bw[j]) >> bb[j]) & 1u) == 0;
    }
    double *w = F64(pl, DD_WRENCH);
    int64_t soff = I64(pl, DD_STRAIN_OFF)[DRIVER_DECODE_STRAIN_OFF_AT];
    int64_t caloff = I64(pl, DD_CAL_OFF)[DRIVER_DECODE_CAL_OFF_AT];
    for (int i = 0; i < 6; i++) {
        double v = 0.0;
        for (int k = 0; soff >= 0 && k < 6; k++)
            v += (double)ld_f32(img + caloff + 4 * (6 * i + k)) * (double)ld_i32(img + soff + 4 * k);
        w[i] = v;
    }
}

/* The boards' snapshot -> robot units (see RobotDriver.read_feedback). With
 * the ``retry`` parameter set, a snapshot whose encoder boards come from
 * different plant steps returns -1 at once (nothing decoded: take it
 * again). Returns 0, or 1 + the joint whose counter jumped (nothing
 * updated then; ``out`` holds the jump). */
static PyObject *driver_decode(PyObject *mod, PyObject *arg) {
    PlanObject *pl = plan_arg(arg, "driver_decode");
    if (pl == NULL)
        return NULL;
    uint8_t *img = U8(pl, DD_IMAGE);
    Py_ssize_t n = pl->n[DD_Q];
    if (n > MAX_JOINTS) {
        PyErr_SetString(PyExc_ValueError, "driver_decode: at most 64 joints");
        return NULL;
    }
    int64_t *stoff = I64(pl, DD_STEP_OFF);
    uint64_t lo = UINT64_MAX, hi = 0;
    for (Py_ssize_t b = 0; b < pl->n[DD_STEP_OFF]; b++) {
        uint64_t s = ld_u64(img + stoff[b]);
        lo = s < lo ? s : lo;
        hi = s > hi ? s : hi;
    }
    int64_t step = (int64_t)lo;
    STATE(pl, STEP) = step;
    STATE(pl, COHERENT) = lo == hi;
    if (lo != hi && PARAM(pl, RETRY) != 0)
        return PyLong_FromLong(-1); /* boards of two plant steps: read again first */
    int64_t now_raw[MAX_JOINTS], *coff = I64(pl, DD_COUNTER_OFF);
    for (Py_ssize_t j = 0; j < n; j++)
        now_raw[j] = (int64_t)ld_u32(img + coff[j]);
    long jumped = decode_counters(pl, now_raw, n, step);
    if (jumped)
        return PyLong_FromLong(jumped);
    decode_latches_speeds(pl, img, now_raw, n, step);
    decode_rest(pl, img, n);
    return PyLong_FromLong(0);
}

/* Joint torques -> DAC codes (rounded, saturated) in the DAC boards' out
 * banks; on a joint whose carry is 1, each rounding's error is carried into
 * the next cycle's code (error feedback: over cycles the codes average the
 * torque asked for; a saturated code carries nothing). Returns 0, or 1 +
 * the first joint whose torque is not finite (nothing is written, nothing
 * carried then). */
static PyObject *driver_dac(PyObject *mod, PyObject *arg) {
    PlanObject *pl = plan_arg(arg, "driver_dac");
    if (pl == NULL)
        return NULL;
    uint8_t *img = U8(pl, DT_IMAGE);
    double *tau = F64(pl, DT_TAU), *vpn = F64(pl, DT_VOLTS_PER_NM);
    double *res = F64(pl, DT_RESIDUAL), *carry = F64(pl, DT_CARRY);
    int64_t *off = I64(pl, DT_CODE_OFF);
    Py_ssize_t n = pl->n[DT_TAU];
    for (Py_ssize_t j = 0; j < n; j++)
        if (!isfinite(tau[j]))
            return PyLong_FromLong((long)j + 1);
    for (Py_ssize_t j = 0; j < n; j++) {
        double x = tau[j] * vpn[j] * 204.8 + res[j]; /* 2048 codes per 10 V */
        double v = nearbyint(x);
        if (v > 2047.0) {
            v = 2047.0;
            res[j] = 0.0;
        } else if (v < -2048.0) {
            v = -2048.0;
            res[j] = 0.0;
        } else {
            res[j] = carry[j] * (x - v);
        }
        st_i16(img + off[j], (int16_t)v);
    }
    return PyLong_FromLong(0);
}

/* 'j': the joints; 'b': the boards stamped with a step */
static const Signature DRIVER_SIGNATURES[] = {
    {"driver_decode",
     ARGS(FREE("image", 'B'), FREE("step_off", 'q'), DIM("counter_off", 'q', 'j', 1),
          DIM("latch_off", 'q', 'j', 1), DIM("latch_count_off", 'q', 'j', 1),
          DIM("latch_edge_off", 'q', 'j', 1), DIM("tach_off", 'q', 'j', 1),
          DIM("torque_off", 'q', 'j', 1), DIM("readback_off", 'q', 'j', 1),
          DIM("home_word", 'q', 'j', 1), DIM("home_bit", 'q', 'j', 1),
          DIM("brake_word", 'q', 'j', 1), DIM("brake_bit", 'q', 'j', 1),
          REC("strain_off", 'q', DRIVER_DECODE_STRAIN_OFF__N),
          REC("cal_off", 'q', DRIVER_DECODE_CAL_OFF__N), DIM("counts_per_rad", 'd', 'j', 1),
          DIM("tach_scale", 'd', 'j', 1), DIM("torque_scale", 'd', 'j', 1),
          DIM("dac_scale", 'd', 'j', 1), DIM("raw", 'q', 'j', 1), DIM("acc", 'q', 'j', 1),
          DIM("q_ref", 'd', 'j', 1), DIM("prev_q", 'd', 'j', 1),
          REC("state", 'q', DRIVER_DECODE_STATE__N), REC("params", 'd', DRIVER_DECODE_PARAMS__N),
          DIM("q", 'd', 'j', 1), DIM("qd", 'd', 'j', 1), DIM("tau", 'd', 'j', 1),
          REC("wrench", 'd', 6), DIM("home", 'B', 'j', 1), DIM("brakes", 'B', 'j', 1),
          DIM("latch_count", 'B', 'j', 4), DIM("latch_edge", 'B', 'j', 1),
          DIM("latch_q", 'd', 'j', 1), REC("out", 'd', DRIVER_DECODE_OUT__N))},
    {"driver_dac",
     ARGS(FREE("image", 'B'), DIM("tau", 'd', 'j', 1), DIM("volts_per_nm", 'd', 'j', 1),
          DIM("code_off", 'q', 'j', 1), DIM("residual", 'd', 'j', 1),
          DIM("carry", 'd', 'j', 1))},
};

static PyMethodDef DRIVER_METHODS[] = {
    {"driver_decode", driver_decode, METH_O, "The driver: boards -> robot units."},
    {"driver_dac", driver_dac, METH_O, "The driver: torques -> DAC codes."},
    {NULL, NULL, 0, NULL},
};

const KernelSet DRIVER_KERNELS = {DRIVER_SIGNATURES, 2, DRIVER_METHODS};
