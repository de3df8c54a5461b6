/*
 * The sender's safety guard kernel (its reference: esc/sender.py,
 * Sender._prepare_numpy; what it flags, check() judges).
 */
#include "../kernels.h"

#include <math.h>

#define DOF GUARD_PREPARE_LIMITS_QD_MAX__LEN /* joints of an arm */
#define FINISHED 2 /* the session status that ends control (SessionStatus.FINISHED) */

enum {
    GP_FB, GP_FB_OFF, GP_SRC, GP_SRC_OFF, GP_HOME, GP_HOME_OFF, GP_LIMITS, GP_ON,
    GP_RELEASED, GP_TAU, GP_TRACE, GP_TRACE_AT
};

#define LIM(f) (lim + GUARD_PREPARE_LIMITS_##f)
#define ROW(f) (row + GUARD_PREPARE_TRACE_##f)
#define AT(f) at[GUARD_PREPARE_TRACE_AT_##f]

/* One joint screened: bit 1 when a figure is not finite or over its limit,
 * or it could not stop inside its position limits. */
static long screen_joint(const double *lim, int j, double q, double qd, double t, double c) {
    double stop = q + qd * fabs(qd) * LIM(STOP_K)[j];
    if (!isfinite(q) || !isfinite(qd) || !isfinite(t) || !isfinite(c))
        return 1;
    if (fabs(qd) > LIM(QD_MAX)[j] || fabs(t) > LIM(TAU_MAX)[j] || fabs(c) > LIM(TAU_MAX)[j])
        return 1;
    return q < LIM(Q_LO)[j] || q > LIM(Q_HI)[j] || stop < LIM(Q_LO)[j] || stop > LIM(Q_HI)[j];
}

/* The wrist's wrench screened: bit 1 when not finite or over its limits. */
static long screen_wrench(const double *lim, const uint8_t *w_at) {
    double w[6];
    long flags = 0;
    for (int i = 0; i < 6; i++) {
        w[i] = ld_f64(w_at + 8 * i);
        if (!isfinite(w[i]))
            flags = 1;
    }
    if (sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]) > *LIM(FORCE_MAX) ||
        sqrt(w[3] * w[3] + w[4] * w[4] + w[5] * w[5]) > *LIM(MOMENT_MAX))
        flags = 1;
    return flags;
}

/* guard_prepare(plan): one command, prepared and screened (see
 * esc/sender.py; the layouts: esc/guard_layout.py). on[j]: the joint is
 * under control (its joint_on, none once the session status says
 * finished); tau[j]: its commanded torque (0 for a joint off); a trace row
 * (the cycle, the boards' step, q, qd, tau, tau commanded) written at row
 * rows % n, rows += 1. Returns bit 1: a figure is not finite or over its
 * limit, or a joint could not stop inside its position limits (the guard's
 * check decides what); bit 2: the joints on differ from ``released``. */
static PyObject *guard_prepare(PyObject *mod, PyObject *arg) {
    PlanObject *pl = plan_arg(arg, "guard_prepare");
    if (pl == NULL)
        return NULL;
    const uint8_t *fb = U8(pl, GP_FB), *src = U8(pl, GP_SRC), *home = U8(pl, GP_HOME);
    const int64_t *fo = I64(pl, GP_FB_OFF), *so = I64(pl, GP_SRC_OFF);
    int64_t *at = I64(pl, GP_TRACE_AT);
    const double *lim = F64(pl, GP_LIMITS);
    double *tau = F64(pl, GP_TAU), *trace = F64(pl, GP_TRACE);
    uint8_t *on = U8(pl, GP_ON), *released = U8(pl, GP_RELEASED);
    Py_ssize_t rows = pl->n[GP_TRACE] / GUARD_PREPARE_TRACE__N;
    int64_t status_at = so[GUARD_PREPARE_SRC_OFF_SESSION_STATUS];
    int finished = status_at >= 0 && src[status_at] == FINISHED;
    double *row = trace + GUARD_PREPARE_TRACE__N * (AT(ROWS) % rows);
    AT(ROWS) += 1;
    *ROW(CYCLE) = (double)AT(CYCLE);
    *ROW(STEP) = (double)ld_u64(home + I64(pl, GP_HOME_OFF)[GUARD_PREPARE_HOME_OFF_STEP]);
    long flags = 0;
    for (int j = 0; j < DOF; j++) {
        double q = ld_f64(fb + fo[GUARD_PREPARE_FB_OFF_Q] + 8 * j);
        double qd = ld_f64(fb + fo[GUARD_PREPARE_FB_OFF_QD] + 8 * j);
        double t = ld_f64(fb + fo[GUARD_PREPARE_FB_OFF_TAU] + 8 * j);
        on[j] = !finished && src[so[GUARD_PREPARE_SRC_OFF_JOINT_ON] + j] != 0;
        double c = on[j] ? ld_f64(src + so[GUARD_PREPARE_SRC_OFF_TAU] + 8 * j) : 0.0;
        tau[j] = c;
        ROW(Q)[j] = q;
        ROW(QD)[j] = qd;
        ROW(TAU)[j] = t;
        ROW(TAU_CMD)[j] = c;
        flags |= screen_joint(lim, j, q, qd, t, c);
        if (on[j] != released[j])
            flags |= 2;
    }
    flags |= screen_wrench(lim, fb + fo[GUARD_PREPARE_FB_OFF_WRENCH]);
    return PyLong_FromLong(flags);
}

static const Signature GUARD_SIGNATURES[] = {
    {"guard_prepare",
     ARGS(FREE("fb", 'B'), REC("fb_off", 'q', GUARD_PREPARE_FB_OFF__N), FREE("src", 'B'),
          REC("src_off", 'q', GUARD_PREPARE_SRC_OFF__N), FREE("home", 'B'),
          REC("home_off", 'q', GUARD_PREPARE_HOME_OFF__N),
          REC("limits", 'd', GUARD_PREPARE_LIMITS__N), REC("on", 'B', DOF),
          REC("released", 'B', DOF), REC("tau", 'd', DOF),
          ROWS("trace", 'd', GUARD_PREPARE_TRACE__N),
          REC("trace_at", 'q', GUARD_PREPARE_TRACE_AT__N))},
};

static PyMethodDef GUARD_METHODS[] = {
    {"guard_prepare", guard_prepare, METH_O, "The sender: a command prepared and screened."},
    {NULL, NULL, 0, NULL},
};

const KernelSet GUARD_KERNELS = {GUARD_SIGNATURES, 1, GUARD_METHODS};
