/* Small dense linear algebra (control/linalg.c). */
#ifndef REDISTRO_LINALG_H
#define REDISTRO_LINALG_H

#include "../kernels.h"

void m3_mul(const double *a, const double *b, double *out);    /* a @ b */
void m3_mul_bt(const double *a, const double *b, double *out); /* a @ b.T */
void m3_vec(const double *a, const double *v, double *out);    /* a @ v */
void m3t_vec(const double *a, const double *v, double *out);   /* a.T @ v */
void rotvec_to_matrix(const double *r, double *R);
void matrix_to_rotvec(const double *R, double *r);
void eig3(const double *A, double *w, double *V); /* A = V diag(w) V^T */
void from_eig3(const double *V, const double *f, double *out); /* V diag(f) V^T */
void damping3(const double *lam, const double *k, double zeta, double *D);
int cholesky(const double *A, double *L, int n); /* 0: not positive definite */
void chol_solve(const double *L, double *b, int n);
int spd_inverse(const double *A, double *out, int n); /* n <= 6 */

#endif
