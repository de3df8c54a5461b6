/*
 * The SSC's Cartesian law of one arm, one cycle (its reference:
 * control/cartesian.py, CartesianLaw and hybrid_update; its buffers'
 * layouts: control/cartesian_layout.py): its TCP from the tool frame, the
 * reference pose and speeds of the segment's quintic, the task-space
 * inertia, hybrid position/force control with an admittance on the force
 * axes, and the joint torques.
 */
#include "linalg.h"

#include <math.h>

#define KIN(f) (kin + CARTESIAN_LAW_KIN_##f)
#define REF(f) (ref + CARTESIAN_LAW_REF_##f)
#define CMD(f) (cmd + CARTESIAN_LAW_CMD_##f)
#define GAIN(f) (gn + CARTESIAN_LAW_GAINS_##f)
#define ST(f) (st + CARTESIAN_LAW_STATE_##f)
#define OUT(f) (out + CARTESIAN_LAW_OUT_##f)

enum { CL_KIN, CL_REF, CL_CMD, CL_GAINS, CL_STATE, CL_OUT };

/* What one cycle works out, step by step. */
typedef struct {
    double sensor[3], p[3], J[42];                /* the TCP and its Jacobian */
    double p_ref[3], v_ref[6], a_ref[6], R_ref[9]; /* the reference */
    double lam[36], lam_lin[9], N[49];            /* task-space inertia, null space */
    double app_task[6];                           /* the wrench applied, task axes */
    double e[6], v[6], v_goal[6], pm[6];          /* errors, speeds, position axes */
} Cycle;

static double positive(double x) { return x > 1e-9 ? x : 1e-9; }

/* The TCP: the tool's far end on its z axis; J from the tool frame to it. */
static void tcp(const double *kin, const double *gn, Cycle *c) {
    const double *R = KIN(R), *J0 = KIN(J);
    double r[3];
    for (int i = 0; i < 3; i++) {
        c->sensor[i] = KIN(T)[i] + GAIN(BASE)[i];
        r[i] = R[3 * i + 2] * *GAIN(TCP_OFFSET);
        c->p[i] = c->sensor[i] + r[i];
    }
    memcpy(c->J, J0, sizeof c->J);
    for (int k = 0; k < 7; k++) { /* v_tcp = v_tool + w x r: J_lin -= [r]x J_ang */
        double wx = J0[21 + k], wy = J0[28 + k], wz = J0[35 + k];
        c->J[k] -= r[1] * wz - r[2] * wy;
        c->J[7 + k] -= r[2] * wx - r[0] * wz;
        c->J[14 + k] -= r[0] * wy - r[1] * wx;
    }
}

/* The reference: a quintic in position, the same blend about one axis in rotation. */
static void reference(const double *ref, double seg_t, Cycle *c) {
    double move_s = *REF(MOVE_S);
    double s = clampd(seg_t / move_s, 0.0, 1.0), s2 = s * s, s3 = s2 * s;
    double pos = 10 * s3 - 15 * s3 * s + 6 * s3 * s2;
    double vel = (30 * s2 - 60 * s3 + 30 * s2 * s2) / move_s;
    double acc = (60 * s - 180 * s2 + 120 * s3) / (move_s * move_s);
    double rel[9], rv[3], Rs[9];
    for (int i = 0; i < 3; i++) {
        double d = REF(GOAL_P)[i] - REF(START_P)[i];
        c->p_ref[i] = REF(START_P)[i] + d * pos;
        c->v_ref[i] = d * vel;
        c->a_ref[i] = d * acc;
    }
    m3_mul_bt(REF(GOAL_R), REF(START_R), rel);
    matrix_to_rotvec(rel, rv);
    for (int i = 0; i < 3; i++)
        rv[i] *= pos;
    rotvec_to_matrix(rv, Rs);
    m3_mul(Rs, REF(START_R), c->R_ref);
    double sd = s < 1.0 ? vel : 0.0, sdd = s < 1.0 ? acc : 0.0;
    for (int i = 0; i < 3; i++) {
        c->v_ref[3 + i] = REF(AXIS)[i] * sd;
        c->a_ref[3 + i] = REF(AXIS)[i] * sdd;
    }
}

/* M^-1 J^T (7 x 6) from M's upper triangle; 0 when M is not positive definite. */
static int minv_jt(const double *Mu, const double *J, double *MinvJt) {
    double M[49], L7[49];
    for (int i = 0; i < 7; i++)
        for (int j = 0; j < 7; j++)
            M[7 * i + j] = j >= i ? Mu[7 * i + j] : Mu[7 * j + i];
    if (!cholesky(M, L7, 7))
        return 0;
    for (int k = 0; k < 6; k++) {
        double col[7];
        for (int i = 0; i < 7; i++)
            col[i] = J[7 * k + i];
        chol_solve(L7, col, 7);
        for (int i = 0; i < 7; i++)
            MinvJt[6 * i + k] = col[i];
    }
    return 1;
}

/* Task-space inertia Lambda = (J M^-1 J^T)^-1, its translational part, and
 * the dynamically consistent null-space projector N = I - J^T Lambda J M^-1.
 * 0 when an inertia is not positive definite. */
static int task_inertia(const double *Mu, Cycle *c) {
    double MinvJt[42], A[36], A3[9], LMt[42];
    const double *J = c->J;
    if (!minv_jt(Mu, J, MinvJt))
        return 0;
    for (int i = 0; i < 6; i++)
        for (int j = 0; j < 6; j++) {
            double v = 0;
            for (int k = 0; k < 7; k++)
                v += J[7 * i + k] * MinvJt[6 * k + j];
            A[6 * i + j] = v + (i == j ? 1e-6 : 0.0);
        }
    for (int i = 0; i < 6; i++) /* symmetric up to rounding: take the mean */
        for (int j = i + 1; j < 6; j++)
            A[6 * i + j] = A[6 * j + i] = 0.5 * (A[6 * i + j] + A[6 * j + i]);
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            A3[3 * i + j] = A[6 * i + j];
    if (!spd_inverse(A, c->lam, 6) || !spd_inverse(A3, c->lam_lin, 3))
        return 0;
    for (int i = 0; i < 6; i++) /* lam @ MinvJt^T: 6 x 7 */
        for (int k = 0; k < 7; k++) {
            double v = 0;
            for (int j = 0; j < 6; j++)
                v += c->lam[6 * i + j] * MinvJt[6 * k + j];
            LMt[7 * i + k] = v;
        }
    for (int i = 0; i < 7; i++)
        for (int k = 0; k < 7; k++) {
            double v = 0;
            for (int j = 0; j < 6; j++)
                v += J[7 * j + i] * LMt[7 * j + k];
            c->N[7 * i + k] = (i == k ? 1.0 : 0.0) - v;
        }
    return 1;
}

/* The wrench the tool applies, on the task axes, its moment about the TCP. */
static void applied_wrench(const double *kin, const double *Rt, Cycle *c) {
    double f_w[3], m_w[3], applied[6];
    m3_vec(KIN(R), KIN(WRENCH), f_w);
    m3_vec(KIN(R), KIN(WRENCH) + 3, m_w);
    double rr[3] = {c->p[0] - c->sensor[0], c->p[1] - c->sensor[1], c->p[2] - c->sensor[2]};
    double m_tcp[3] = {m_w[0] - (rr[1] * f_w[2] - rr[2] * f_w[1]),
                       m_w[1] - (rr[2] * f_w[0] - rr[0] * f_w[2]),
                       m_w[2] - (rr[0] * f_w[1] - rr[1] * f_w[0])};
    for (int i = 0; i < 3; i++) {
        applied[i] = -f_w[i];
        applied[3 + i] = -m_tcp[i];
    }
    m3t_vec(Rt, applied, c->app_task);
    m3t_vec(Rt, applied + 3, c->app_task + 3);
}

/* On contact (the force along the force axes reaches contact_n): the
 * approach's speed stops, and the spring's push along the force axes is
 * handed over to the goal's ramp (a bumpless handover). After it the ramp
 * grows to 1 over ramp_s. */
static void contact(const double *kin, const double *cmd, const double *gn, double *st,
                    const Cycle *c) {
    const double *sel = CMD(SELECTION), *Rt = ST(R_TASK), *a = c->app_task;
    double fx = sel[0] * a[0], fy = sel[1] * a[1], fz = sel[2] * a[2];
    if (*ST(CONTACT) == 0 && sqrt(fx * fx + fy * fy + fz * fz) >= *GAIN(CONTACT_N)) {
        double pr[3], pt[3];
        m3t_vec(Rt, c->p_ref, pr);
        m3t_vec(Rt, c->p, pt);
        *ST(CONTACT) = 1;
        *ST(CONTACT_T) = *KIN(T_TASK);
        for (int i = 0; i < 3; i++) {
            ST(SPRING0)[i] = sel[i] * (pr[i] + ST(XI)[i] - pt[i]);
            ST(XI_V)[i] = 0.0;
        }
    }
    if (*ST(CONTACT) != 0) {
        double before = *ST(RAMP), ramp = before + *KIN(DT) / positive(*GAIN(RAMP_S));
        *ST(RAMP) = ramp < 1.0 ? ramp : 1.0;
        for (int i = 0; i < 3; i++)
            ST(XI)[i] -= ST(SPRING0)[i] * (*ST(RAMP) - before);
    }
}

/* The admittance on the force axes: the reference offset xi moves at a
 * speed that follows the wrench error, within speed and acceleration limits. */
static void admittance(const double *kin, const double *cmd, const double *gn, double *st,
                       const Cycle *c) {
    const double *sel = CMD(SELECTION), *goal_w = CMD(GOAL_WRENCH);
    double dt = *KIN(DT);
    double *xi = ST(XI), *xi_v = ST(XI_V), *a_st = ST(A_REF);
    for (int i = 0; i < 6; i++) {
        double err = goal_w[i] - c->app_task[i];
        double want = i < 3 ? clampd(*GAIN(K_ADM) * err, -*GAIN(V_MAX), *GAIN(V_MAX))
                            : clampd(*GAIN(K_ADM_ROT) * err, -*GAIN(W_MAX), *GAIN(W_MAX));
        double dv = (i < 3 ? *GAIN(A_MAX) : *GAIN(ALPHA_MAX)) * dt;
        double before = xi_v[i];
        xi_v[i] = sel[i] * (xi_v[i] + clampd(want - xi_v[i], -dv, dv));
        a_st[i] = (xi_v[i] - before) / positive(dt);
        xi[i] += xi_v[i] * dt;
    }
}

/* The pose error: position axes from the trajectory, force axes offset by xi. */
static void pose_error(const double *kin, const double *cmd, const double *st, Cycle *c) {
    const double *sel = CMD(SELECTION), *Rt = ST(R_TASK), *xi = ST(XI);
    double p_task[3], p_goal[3], R_goal[9], sx[3], rvx[3], Rx[9], Rerr[9];
    m3t_vec(Rt, c->p_ref, p_task);
    for (int i = 0; i < 3; i++)
        if (sel[i] > 0)
            p_task[i] += xi[i];
    m3_vec(Rt, p_task, p_goal);
    for (int i = 0; i < 3; i++)
        sx[i] = sel[3 + i] * xi[3 + i];
    m3_vec(Rt, sx, rvx);
    rotvec_to_matrix(rvx, Rx);
    m3_mul(Rx, c->R_ref, R_goal);
    for (int i = 0; i < 3; i++)
        c->e[i] = p_goal[i] - c->p[i];
    m3_mul_bt(R_goal, KIN(R), Rerr);
    matrix_to_rotvec(Rerr, c->e + 3);
}

/* Speeds: the TCP's, the reference's on the position axes, and those axes. */
static void speeds(const double *kin, const double *cmd, const double *st, Cycle *c) {
    const double *sel = CMD(SELECTION), *Rt = ST(R_TASK), *qd = KIN(QD);
    double vt[6], ones[6];
    for (int i = 0; i < 6; i++) {
        double x = 0;
        for (int k = 0; k < 7; k++)
            x += c->J[7 * i + k] * qd[k];
        c->v[i] = x;
    }
    m3t_vec(Rt, c->v_ref, vt);
    m3t_vec(Rt, c->v_ref + 3, vt + 3);
    for (int i = 0; i < 6; i++) {
        vt[i] *= 1.0 - sel[i];
        ones[i] = 1.0 - sel[i];
    }
    m3_vec(Rt, vt, c->v_goal);
    m3_vec(Rt, vt + 3, c->v_goal + 3);
    m3_vec(Rt, ones, c->pm);
    m3_vec(Rt, ones + 3, c->pm + 3);
}

/* Rt applied to both halves of a 6-vector (task axes -> world). */
static void rotate6(const double *Rt, const double *x, double *out) {
    m3_vec(Rt, x, out);
    m3_vec(Rt, x + 3, out + 3);
}

/* The task-space wrench: spring, damper (critically damped on the
 * translational inertia when zeta > 0), integral on the position axes, the
 * goal wrench ramped in after contact, and the inertia feedforward. */
static void task_wrench(const double *kin, const double *cmd, const double *gn, double *st,
                        const Cycle *c, double *F) {
    const double *sel = CMD(SELECTION), *Rt = ST(R_TASK), *k = GAIN(K), *ki = GAIN(KI);
    double *integral = ST(INTEGRAL), dt = *KIN(DT);
    double dvv[6], damp[6], gw[6], rg[6], at[6], aw[6];
    if (*KIN(INTEGRATE) != 0)
        for (int i = 0; i < 6; i++) {
            double lim = ki[i] > 0 ? GAIN(I_MAX)[i] / ki[i] : 0.0;
            double mask = fabs(c->pm[i]) > 0.5 ? 1.0 : 0.0;
            integral[i] = clampd(integral[i] + c->e[i] * dt * mask, -lim, lim);
        }
    for (int i = 0; i < 6; i++) {
        dvv[i] = c->v_goal[i] - c->v[i];
        damp[i] = GAIN(D)[i] * dvv[i];
    }
    if (*GAIN(ZETA) > 0) {
        double D[9];
        damping3(c->lam_lin, k, *GAIN(ZETA), D);
        m3_vec(D, dvv, damp);
    }
    for (int i = 0; i < 6; i++)
        gw[i] = sel[i] * *ST(RAMP) * CMD(GOAL_WRENCH)[i];
    rotate6(Rt, gw, rg);
    m3t_vec(Rt, c->a_ref, at);
    m3t_vec(Rt, c->a_ref + 3, at + 3);
    for (int i = 0; i < 6; i++)
        at[i] = at[i] * (1.0 - sel[i]) + sel[i] * ST(A_REF)[i];
    rotate6(Rt, at, aw);
    for (int i = 0; i < 6; i++) {
        double x = 0;
        for (int j = 0; j < 6; j++)
            x += c->lam[6 * i + j] * aw[j];
        F[i] = k[i] * c->e[i] + damp[i] + ki[i] * integral[i] + rg[i] + x;
    }
}

/* tau = g - d_joint qd + J^T F + N k_null (q_null - q), and what the law reports. */
static void torques(const double *kin, const double *cmd, const double *gn, const Cycle *c,
                    const double *F, double *out) {
    double post[7];
    for (int k = 0; k < 7; k++)
        post[k] = GAIN(K_NULL)[k] * (CMD(Q_NULL)[k] - KIN(Q)[k]);
    for (int k = 0; k < 7; k++) {
        double x = KIN(G)[k] - GAIN(D_JOINT)[k] * KIN(QD)[k];
        for (int i = 0; i < 6; i++)
            x += c->J[7 * i + k] * F[i];
        for (int j = 0; j < 7; j++)
            x += c->N[7 * k + j] * post[j];
        OUT(TAU)[k] = x;
    }
    memcpy(OUT(APPLIED), c->app_task, sizeof c->app_task);
    memcpy(OUT(TCP_P), c->p, sizeof c->p);
    memcpy(OUT(REF_P), c->p_ref, sizeof c->p_ref);
    matrix_to_rotvec(KIN(R), OUT(TCP_ROT));
}

/* cartesian_law(plan) -> 0, or 1 when an inertia is not positive definite
 * (nothing written). */
static PyObject *cartesian_law(PyObject *mod, PyObject *arg) {
    PlanObject *pl = plan_arg(arg, "cartesian_law");
    if (pl == NULL)
        return NULL;
    const double *kin = F64(pl, CL_KIN), *ref = F64(pl, CL_REF), *cmd = F64(pl, CL_CMD);
    const double *gn = F64(pl, CL_GAINS);
    double *st = F64(pl, CL_STATE), *out = F64(pl, CL_OUT);
    Cycle c;
    double F[6];
    tcp(kin, gn, &c);
    reference(ref, *KIN(SEG_T), &c);
    if (!task_inertia(KIN(M), &c))
        return PyLong_FromLong(1);
    applied_wrench(kin, ST(R_TASK), &c);
    int any_force = 0;
    for (int i = 0; i < 6; i++)
        any_force |= CMD(SELECTION)[i] != 0;
    if (any_force) {
        contact(kin, cmd, gn, st, &c);
        admittance(kin, cmd, gn, st, &c);
    }
    pose_error(kin, cmd, st, &c);
    speeds(kin, cmd, st, &c);
    task_wrench(kin, cmd, gn, st, &c, F);
    torques(kin, cmd, gn, &c, F, out);
    return PyLong_FromLong(0);
}

static const Signature CARTESIAN_SIGNATURES[] = {
    {"cartesian_law",
     ARGS(REC("kin", 'd', CARTESIAN_LAW_KIN__N), REC("ref", 'd', CARTESIAN_LAW_REF__N),
          REC("cmd", 'd', CARTESIAN_LAW_CMD__N), REC("gains", 'd', CARTESIAN_LAW_GAINS__N),
          REC("state", 'd', CARTESIAN_LAW_STATE__N), REC("out", 'd', CARTESIAN_LAW_OUT__N))},
};

static PyMethodDef CARTESIAN_METHODS[] = {
    {"cartesian_law", cartesian_law, METH_O, "The SSC's Cartesian law of one arm, one cycle."},
    {NULL, NULL, 0, NULL},
};

const KernelSet CARTESIAN_KERNELS = {CARTESIAN_SIGNATURES, 1, CARTESIAN_METHODS};
