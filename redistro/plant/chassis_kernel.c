/*
 * The simulated chassis's kernels (its reference: plant/chassis.py): the
 * controller's outputs applied to the joints, the joints sampled into the
 * boards' in banks, and PyBullet's joint states unpacked.
 */
#include "../kernels.h"

#include <math.h>

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
    for (Py_ssize_t r = 0; r < pl->n[CA_COPY] / CHASSIS_APPLY_COPY__N;
         r++, c += CHASSIS_APPLY_COPY__N) {
        int64_t src = c[CHASSIS_APPLY_COPY_SRC], dst = c[CHASSIS_APPLY_COPY_DST];
        if (c[CHASSIS_APPLY_COPY_MASK])
            st_u32(img + dst, ld_u32(img + src) & (uint32_t)c[CHASSIS_APPLY_COPY_MASK]);
        else
            memcpy(img + dst, img + src, (size_t)c[CHASSIS_APPLY_COPY_SIZE]);
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
        if (src[i] < 0 || src[i] >= 2 * n) {
            PyErr_SetString(PyExc_IndexError, "chassis_sample: an ADC source past the joints");
            return NULL;
        }
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
        int64_t *at = I64(pl, CS_NOISE_AT) + CHASSIS_SAMPLE_NOISE_AT_ROW;
        Py_ssize_t rows = pl->n[CS_NOISE] / (6 * wrists);
        if (*at < 0 || *at >= rows) {
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
    uint64_t step = (uint64_t)I64(pl, CS_STEP)[CHASSIS_SAMPLE_STEP_STEP];
    for (Py_ssize_t b = 0; b < pl->n[CS_STEP_OFF]; b++)
        st_u64(img + stoff[b], step);
    return PyLong_FromLong(flags);
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

/* 'j': the joints; 'e': encoder boards; 'a': ADC channels; 'w': wrists */
static const Signature CHASSIS_SIGNATURES[] = {
    {"chassis_apply",
     ARGS(FREE("image", 'B'), DIM("brake_off", 'q', 'j', 1), DIM("brake_bit", 'q', 'j', 1),
          DIM("dac_off", 'q', 'j', 1), DIM("cut", 'B', 'j', 1),
          DIM("amps_per_code", 'd', 'j', 1), DIM("max_current", 'd', 'j', 1),
          DIM("nm_per_amp", 'd', 'j', 1), DIM("motor_tau", 'd', 'j', 1),
          DIM("brake", 'B', 'j', 1), DIM("braked", 'B', 'j', 1),
          ROWS("copy", 'q', CHASSIS_APPLY_COPY__N), DIM("req_off", 'q', 'e', 1),
          DIM("req_seen", 'B', 'e', 32))},
    {"chassis_sample",
     ARGS(FREE("image", 'B'), DIM("q", 'd', 'j', 1), DIM("qd", 'd', 'j', 1),
          DIM("tau", 'd', 'j', 1), DIM("applied", 'd', 'j', 1), DIM("motor_tau", 'd', 'j', 1),
          DIM("braked", 'B', 'j', 1), DIM("held", 'B', 'j', 1), DIM("stopped", 'B', 'j', 1),
          DIM("counts_per_rad", 'd', 'j', 1), DIM("enc_offset", 'q', 'j', 1),
          DIM("counts", 'q', 'j', 1), DIM("counter_off", 'q', 'j', 1),
          DIM("home_center", 'd', 'j', 1), DIM("home_on", 'd', 'j', 1),
          DIM("home_off", 'd', 'j', 1), DIM("switch", 'B', 'j', 1), DIM("force", 'B', 'j', 1),
          DIM("home", 'B', 'j', 1), DIM("last_home", 'B', 'j', 1), DIM("edges", 'B', 'j', 1),
          DIM("home_reg_off", 'q', 'j', 1), FREE("dio_clear", 'q'),
          DIM("home_word", 'q', 'j', 1), DIM("home_bit", 'q', 'j', 1),
          DIM("adc_src", 'q', 'a', 1), DIM("adc_scale", 'd', 'a', 1),
          DIM("adc_off", 'q', 'a', 1), DIM("wrench", 'd', 'w', 6), DIM("inverse", 'd', 'w', 36),
          FREE("noise", 'd'), REC("noise_at", 'q', CHASSIS_SAMPLE_NOISE_AT__N),
          DIM("strain_off", 'q', 'w', 1), DIM("sample_off", 'q', 'w', 1),
          FREE("step_off", 'q'), REC("step", 'q', CHASSIS_SAMPLE_STEP__N))},
};

static PyMethodDef CHASSIS_METHODS[] = {
    {"chassis_apply", chassis_apply, METH_O, "The chassis: outputs -> joints."},
    {"chassis_sample", chassis_sample, METH_O, "The chassis: joints -> boards."},
    {"unpack_states", (PyCFunction)(void (*)(void))unpack_states, METH_FASTCALL,
     "PyBullet joint states -> q, qd, applied torque."},
    {NULL, NULL, 0, NULL},
};

const KernelSet CHASSIS_KERNELS = {CHASSIS_SIGNATURES, 2, CHASSIS_METHODS};
