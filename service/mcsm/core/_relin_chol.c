/* mcsm's relinearisation: the numeric block Cholesky factorisation (right-looking, in the
 * elimination order of _relin_order.c) and the triangular solves. Blocks are a variable's
 * active dimensions (at most 6). A pivot below 1e-10 of H's diagonal marks a dimension without
 * information: its column of L is zero, its solution 0. Portability: _relin.h.
 */
#include <math.h>
#include <string.h>

#include "_relin.h"

#define PIVOT_TOL 1e-10


/* T (dw x D) -= Lw (dw x D) Lu^T (Lu: D x D), given lut = Lu transposed (k-major): the update
 * loop of mr_factorise for D-dimensional blocks on both sides (6-dof poses, planar poses),
 * its bounds known so that the compiler unrolls it and runs the b loop along lut's rows.
 * Each element's sum is still 0.0 + the products k = 0, 1, ... in that order, the plain
 * loop's order: the same bits. Only independent elements are computed side by side. */
#define MR_OUTER(NAME, D)                                                                   \
    static void NAME(const double *Lw, const double *lut, int dw, double *T) {              \
        for (int a = 0; a < dw; a++) {                                                      \
            double t[D];                                                                    \
            for (int b = 0; b < D; b++) t[b] = 0.0;                                         \
            for (int k = 0; k < D; k++) {                                                   \
                double l = Lw[a * D + k];                                                   \
                for (int b = 0; b < D; b++) t[b] += l * lut[k * D + b];                     \
            }                                                                               \
            for (int b = 0; b < D; b++) T[a * D + b] -= t[b];                               \
        }                                                                                   \
    }
MR_OUTER(outer3, 3)

/* The same for D = 6 in pairs of lanes (GCC / clang vector extensions: SSE2 on baseline
 * x86-64, NEON on arm64): lane j of t0, t1, t2 is element 2 i + j's sum, added in the same
 * order; a lane's multiply and add are IEEE operations on that lane alone (no contraction:
 * -ffp-contract=off), so the bits are the scalar loop's. */
typedef double mr_v2 __attribute__((vector_size(16)));

static void outer6(const double *Lw, const double *lut, int dw, double *T) {
    mr_v2 L[18];
    memcpy(L, lut, sizeof L);
    for (int a = 0; a < dw; a++) {
        mr_v2 t0 = {0.0, 0.0}, t1 = {0.0, 0.0}, t2 = {0.0, 0.0};
        for (int k = 0; k < 6; k++) {
            double l = Lw[a * 6 + k];
            mr_v2 lv = {l, l};
            t0 += lv * L[k * 3];
            t1 += lv * L[k * 3 + 1];
            t2 += lv * L[k * 3 + 2];
        }
        mr_v2 r[3];
        memcpy(r, T + a * 6, sizeof r);
        r[0] -= t0;
        r[1] -= t1;
        r[2] -= t2;
        memcpy(T + a * 6, r, sizeof r);
    }
}

/* val = L of (H + lambda diag H); marks dimensions without information. */
void mr_factorise(mr_state *S, double lambda, int *slot) {
    memcpy(S->val, S->hval, sizeof(double) * S->nval);
    memset(S->dead, 0, S->nscal);
    for (long p = 0; p < S->ns; p++) {
        int dp = S->dim[p];
        double *D = S->val + S->doff[p];
        if (lambda > 0.0)
            for (int a = 0; a < dp; a++) D[a * dp + a] += lambda * D[a * dp + a];
        uint8_t *dead = S->dead + S->soff[p];
        const double *hd = S->hdiag + S->soff[p];
        for (int j = 0; j < dp; j++) {
            double s = D[j * dp + j];
            for (int k = 0; k < j; k++) s -= D[j * dp + k] * D[j * dp + k];
            if (!(s > PIVOT_TOL * hd[j])) {
                dead[j] = 1;
                D[j * dp + j] = 1.0;
                for (int i = j + 1; i < dp; i++) D[i * dp + j] = 0.0;
                continue;
            }
            double l = sqrt(s);
            D[j * dp + j] = l;
            for (int i = j + 1; i < dp; i++) {
                double t = D[i * dp + j];
                for (int k = 0; k < j; k++) t -= D[i * dp + k] * D[j * dp + k];
                D[i * dp + j] = t / l;
            }
        }
        for (int i = 0; i < dp; i++)
            for (int j = i + 1; j < dp; j++) D[i * dp + j] = 0.0;
        long c0 = S->cptr[p], c1 = S->cptr[p + 1];
        for (long q = c0; q < c1; q++) {
            int du = S->dim[S->crow[q]];
            double *B = S->val + S->boff[q];
            for (int a = 0; a < du; a++)
                for (int j = 0; j < dp; j++) {
                    if (dead[j]) {
                        B[a * dp + j] = 0.0;
                        continue;
                    }
                    double t = B[a * dp + j];
                    for (int k = 0; k < j; k++) t -= B[a * dp + k] * D[j * dp + k];
                    B[a * dp + j] = t / D[j * dp + j];
                }
        }
        for (long qa = c0; qa < c1; qa++) {
            int u = S->crow[qa], du = S->dim[u];
            const double *Lu = S->val + S->boff[qa];
#ifdef MR_PLAIN_FACTOR /* the plain loop alone: tests/core/test_portability.py builds it */
            int fast = 0;
#else
            int fast = du == dp && (dp == 6 || dp == 3);
#endif
            double lut[36];
            if (fast)
                for (int b = 0; b < du; b++)
                    for (int k = 0; k < dp; k++) lut[k * du + b] = Lu[b * dp + k];
            for (long q = S->cptr[u]; q < S->cptr[u + 1]; q++) slot[S->crow[q]] = (int)(q - S->cptr[u]);
            double *Du = S->val + S->doff[u];
            for (int a = 0; a < du; a++)
                for (int b = 0; b <= a; b++) {
                    double t = 0.0;
                    for (int k = 0; k < dp; k++) t += Lu[a * dp + k] * Lu[b * dp + k];
                    Du[a * du + b] -= t;
                }
            for (long qb = qa + 1; qb < c1; qb++) {
                int w = S->crow[qb], dw = S->dim[w];
                const double *Lw = S->val + S->boff[qb];
                double *T = S->val + S->boff[S->cptr[u] + slot[w]];
                if (fast) {
                    if (dp == 6) outer6(Lw, lut, dw, T);
                    else outer3(Lw, lut, dw, T);
                    continue;
                }
                for (int a = 0; a < dw; a++)
                    for (int b = 0; b < du; b++) {
                        double t = 0.0;
                        for (int k = 0; k < dp; k++) t += Lw[a * dp + k] * Lu[b * dp + k];
                        T[a * du + b] -= t;
                    }
            }
            for (long q = S->cptr[u]; q < S->cptr[u + 1]; q++) slot[S->crow[q]] = -1;
        }
    }
}

/* y = L^-1 b (dead dimensions 0). */
void mr_forward(const mr_state *S, const double *b, double *y) {
    memcpy(y, b, sizeof(double) * S->nscal);
    for (long p = 0; p < S->ns; p++) {
        int dp = S->dim[p];
        const double *D = S->val + S->doff[p];
        double *yp = y + S->soff[p];
        const uint8_t *dead = S->dead + S->soff[p];
        for (int j = 0; j < dp; j++) {
            if (dead[j]) {
                yp[j] = 0.0;
                continue;
            }
            double t = yp[j];
            for (int k = 0; k < j; k++) t -= D[j * dp + k] * yp[k];
            yp[j] = t / D[j * dp + j];
        }
        for (long q = S->cptr[p]; q < S->cptr[p + 1]; q++) {
            int u = S->crow[q], du = S->dim[u];
            const double *L = S->val + S->boff[q];
            double *yu = y + S->soff[u];
            for (int a = 0; a < du; a++) {
                double t = 0.0;
                for (int j = 0; j < dp; j++) t += L[a * dp + j] * yp[j];
                yu[a] -= t;
            }
        }
    }
}

/* x = L^-T x in place, over positions [p0, ns) (dead dimensions 0). */
void mr_backward(const mr_state *S, double *x, long p0, long stride, long nrhs) {
    for (long p = S->ns - 1; p >= p0; p--) {
        int dp = S->dim[p];
        const double *D = S->val + S->doff[p];
        double *xp = x + (S->soff[p] - S->soff[p0]) * stride;
        const uint8_t *dead = S->dead + S->soff[p];
        for (long q = S->cptr[p]; q < S->cptr[p + 1]; q++) {
            int u = S->crow[q], du = S->dim[u];
            const double *L = S->val + S->boff[q];
            const double *xu = x + (S->soff[u] - S->soff[p0]) * stride;
            for (int j = 0; j < dp; j++)
                for (int a = 0; a < du; a++) {
                    double l = L[a * dp + j];
                    for (long c = 0; c < nrhs; c++) xp[j * stride + c] -= l * xu[a * stride + c];
                }
        }
        for (int j = dp - 1; j >= 0; j--) {
            if (dead[j]) {
                for (long c = 0; c < nrhs; c++) xp[j * stride + c] = 0.0;
                continue;
            }
            for (int i = j + 1; i < dp; i++) {
                double l = D[i * dp + j];
                for (long c = 0; c < nrhs; c++) xp[j * stride + c] -= l * xp[i * stride + c];
            }
            double l = D[j * dp + j];
            for (long c = 0; c < nrhs; c++) xp[j * stride + c] = xp[j * stride + c] / l;
        }
    }
}

