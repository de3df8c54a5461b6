/*
 * Small dense linear algebra for the Cartesian law (row-major): 3x3
 * products, rotation vectors, the symmetric 3x3 eigen-decomposition
 * (cyclic Jacobi), the damping of a 3x3 inertia, and Cholesky factors,
 * solves and inverses of small SPD matrices. The kernels ``eig3`` and
 * ``cholesky`` expose the two decompositions, for their own tests
 * (tests/unit/test_kernels.py, against numpy.linalg).
 */
#include "linalg.h"

#include <math.h>
#include <string.h>

/* row-major 3x3 helpers */
void m3_mul(const double *a, const double *b, double *out) {
    double t[9];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            t[3 * i + j] = a[3 * i] * b[j] + a[3 * i + 1] * b[3 + j] + a[3 * i + 2] * b[6 + j];
    memcpy(out, t, sizeof t);
}
void m3_mul_bt(const double *a, const double *b, double *out) { /* a @ b.T */
    double t[9];
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            t[3 * i + j] = a[3 * i] * b[3 * j] + a[3 * i + 1] * b[3 * j + 1] + a[3 * i + 2] * b[3 * j + 2];
    memcpy(out, t, sizeof t);
}
void m3_vec(const double *a, const double *v, double *out) {
    double t[3];
    for (int i = 0; i < 3; i++)
        t[i] = a[3 * i] * v[0] + a[3 * i + 1] * v[1] + a[3 * i + 2] * v[2];
    memcpy(out, t, sizeof t);
}
void m3t_vec(const double *a, const double *v, double *out) { /* a.T @ v */
    double t[3];
    for (int i = 0; i < 3; i++)
        t[i] = a[i] * v[0] + a[3 + i] * v[1] + a[6 + i] * v[2];
    memcpy(out, t, sizeof t);
}

void rotvec_to_matrix(const double *r, double *R) {
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

void matrix_to_rotvec(const double *R, double *r) {
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
void eig3(const double *A, double *w, double *V) {
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
void from_eig3(const double *V, const double *f, double *out) {
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++)
            out[3 * i + j] = V[3 * i] * f[0] * V[3 * j] + V[3 * i + 1] * f[1] * V[3 * j + 1] +
                             V[3 * i + 2] * f[2] * V[3 * j + 2];
}

/* D = 2 zeta L^1/2 (L^-1/2 K L^-1/2)^1/2 L^1/2 (see damping_matrix) */
void damping3(const double *lam, const double *k, double zeta, double *D) {
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
int cholesky(const double *A, double *L, int n) {
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
void chol_solve(const double *L, double *b, int n) {
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
int spd_inverse(const double *A, double *out, int n) {
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


/* -- the decompositions as kernels, for their tests -- */

enum { EG_A, EG_W, EG_V };

static PyObject *eig3_kernel(PyObject *mod, PyObject *arg) {
    PlanObject *pl = plan_arg(arg, "eig3");
    if (pl == NULL)
        return NULL;
    eig3(F64(pl, EG_A), F64(pl, EG_W), F64(pl, EG_V));
    Py_RETURN_NONE;
}

enum { CH_A, CH_L, CH_B };

/* cholesky: L of the n x n SPD a (n*n = len(a), n <= 7), and b solved in
 * place (L L^T x = b); 1, or 0 when a is not positive definite. */
static PyObject *cholesky_kernel(PyObject *mod, PyObject *arg) {
    PlanObject *pl = plan_arg(arg, "cholesky");
    if (pl == NULL)
        return NULL;
    int n = (int)lround(sqrt((double)pl->n[CH_A]));
    if (n < 1 || n > 7 || n * n != pl->n[CH_A] || pl->n[CH_L] != n * n || pl->n[CH_B] != n) {
        PyErr_SetString(PyExc_ValueError, "cholesky: a[n*n], l[n*n], b[n], n <= 7");
        return NULL;
    }
    if (!cholesky(F64(pl, CH_A), F64(pl, CH_L), n))
        return PyLong_FromLong(0);
    chol_solve(F64(pl, CH_L), F64(pl, CH_B), n);
    return PyLong_FromLong(1);
}

static const Signature LINALG_SIGNATURES[] = {
    {"eig3", ARGS(REC("a", 'd', 9), REC("w", 'd', 3), REC("v", 'd', 9))},
    {"cholesky", ARGS(FREE("a", 'd'), FREE("l", 'd'), FREE("b", 'd'))},
};

static PyMethodDef LINALG_METHODS[] = {
    {"eig3", eig3_kernel, METH_O, "Symmetric 3x3 eigen-decomposition: a = v diag(w) v^T."},
    {"cholesky", cholesky_kernel, METH_O, "Cholesky factor of an SPD matrix, and a solve."},
    {NULL, NULL, 0, NULL},
};

const KernelSet LINALG_KERNELS = {LINALG_SIGNATURES, 2, LINALG_METHODS};
