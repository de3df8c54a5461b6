/*
 * Joint control's kernels (their references: control/pid.py, pid_update;
 * control/trajectory.py, the quintic).
 */
#include "../kernels.h"

enum { JP_Q, JP_QD, JP_QREF, JP_QDREF, JP_G, JP_ON, JP_TAU, JP_INTEGRAL, JP_GAINS, JP_DT };
enum { QU_Q0, QU_D, QU_Q, QU_QD, QU_QDD, QU_TIME };

/* -- joint control -- */

/* Joint PID with gravity compensation (see control/pid.py: pid_update):
 * gains: PID_GAINS (control/joint_layout.py); the integral (state) clamped
 * to +-i_max and zeroed on joints off; tau = (g + kp e + kd (qd_ref - qd)
 * + ki integral) on joints on, 0 off. */
static PyObject *joint_pid(PyObject *mod, PyObject *arg) {
    PlanObject *pl = plan_arg(arg, "joint_pid");
    if (pl == NULL)
        return NULL;
    const double *q = F64(pl, JP_Q), *qd = F64(pl, JP_QD), *qr = F64(pl, JP_QREF);
    const double *qdr = F64(pl, JP_QDREF), *g = F64(pl, JP_G), *gn = F64(pl, JP_GAINS);
    const uint8_t *on = U8(pl, JP_ON);
    double *tau = F64(pl, JP_TAU), *I = F64(pl, JP_INTEGRAL);
    double dt = F64(pl, JP_DT)[JOINT_PID_DT_DT];
    Py_ssize_t n = pl->n[JP_TAU];
    const double *kp = gn + JOINT_PID_GAINS_KP, *ki = gn + JOINT_PID_GAINS_KI;
    const double *kd = gn + JOINT_PID_GAINS_KD, *lim = gn + JOINT_PID_GAINS_I_MAX;
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
    double T = tm[QUINTIC_TIME_DURATION], s = clampd(tm[QUINTIC_TIME_T] / T, 0.0, 1.0);
    double s2 = s * s, s3 = s2 * s;
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

/* the PID's joints: as many as the gains' layout has per field ('j': the quintic's) */
#define PID_JOINTS JOINT_PID_GAINS_KP__LEN
static const Signature JOINT_SIGNATURES[] = {
    {"joint_pid",
     ARGS(REC("q", 'd', PID_JOINTS), REC("qd", 'd', PID_JOINTS), REC("q_ref", 'd', PID_JOINTS),
          REC("qd_ref", 'd', PID_JOINTS), REC("g", 'd', PID_JOINTS), REC("on", 'B', PID_JOINTS),
          REC("tau", 'd', PID_JOINTS), REC("integral", 'd', PID_JOINTS),
          REC("gains", 'd', JOINT_PID_GAINS__N), REC("dt", 'd', JOINT_PID_DT__N))},
    {"quintic",
     ARGS(DIM("q0", 'd', 'j', 1), DIM("d", 'd', 'j', 1), DIM("q", 'd', 'j', 1),
          DIM("qd", 'd', 'j', 1), DIM("qdd", 'd', 'j', 1), REC("time", 'd', QUINTIC_TIME__N))},
};

static PyMethodDef JOINT_METHODS[] = {
    {"joint_pid", joint_pid, METH_O, "A joint PID with gravity compensation, one cycle."},
    {"quintic", quintic, METH_O, "A quintic's reference at one time."},
    {NULL, NULL, 0, NULL},
};

const KernelSet JOINT_KERNELS = {JOINT_SIGNATURES, 2, JOINT_METHODS};
