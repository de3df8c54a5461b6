/*
 * The sender's safety guard kernel (its reference: esc/sender.py,
 * Sender._prepare_numpy; what it flags, check() judges).
 */
#include "../kernels.h"

#include <math.h>

enum {
    GP_FB, GP_FB_OFF, GP_SRC, GP_SRC_OFF, GP_HOME, GP_HOME_OFF, GP_LIMITS, GP_ON,
    GP_RELEASED, GP_TAU, GP_TRACE, GP_TRACE_AT
};

/* -- the sender's safety guard -- */

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

static const Signature GUARD_SIGNATURES[] = {
    {"guard_prepare",
     ARGS({"fb", 'B'}, {"fb_off", 'q'}, {"src", 'B'}, {"src_off", 'q'}, {"home", 'B'},
          {"home_off", 'q'}, {"limits", 'd'}, {"on", 'B'}, {"released", 'B'}, {"tau", 'd'},
          {"trace", 'd'}, {"trace_at", 'q'})},
};

static PyMethodDef GUARD_METHODS[] = {
    {"guard_prepare", guard_prepare, METH_O, "The sender: a command prepared and screened."},
    {NULL, NULL, 0, NULL},
};

const KernelSet GUARD_KERNELS = {GUARD_SIGNATURES, 1, GUARD_METHODS};
