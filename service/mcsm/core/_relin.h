/* Shared declarations of mcsm's relinearisation kernel (_relin.c: the factor graph's
 * Gauss-Newton / Levenberg-Marquardt solve with a backtracking line search; _relin_order.c:
 * the elimination order and the factor's structure; _relin_chol.c: the sparse block Cholesky
 * factorisation and solves; _relin_draw.c: input moments, pose transforms, the
 * counter-based normal generator and the redraw).
 *
 * The same portability rules as _kernel.c (README "Portable arithmetic"): only IEEE +, -, *,
 * / and sqrt, every sum in a fixed order, no libm transcendental function, built with the same
 * flags (-ffp-contract=off, no fast-math) into the same libraries. The ordering is computed with
 * integer arithmetic only. Everything here is single-threaded.
 */
#ifndef MCSM_RELIN_H
#define MCSM_RELIN_H

/* GCC's straight-line (SLP) vectorizer turns the alternating sums of a quaternion product into
 * vfmsubadd instructions on FMA targets even under -ffp-contract=off (seen with GCC 12 and
 * -march=native): fused, so other bits. It is off for these files; loops over samples are
 * still vectorised (elementwise, same bits). */
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC optimize("no-tree-slp-vectorize")
#endif

#include <math.h>
#include <stdint.h>

#define MR_OK 0
#define MR_NONFINITE 3
#define MR_BAD_ARGS 4
#define MR_NO_MEMORY 5

/* One solve (bindings: mcsm.core.relin.Problem; every field is 8 bytes wide). Variables are
 * poses (x y z qw qx qy qz, 6-D tangent: translation in the root's frame, rotation
 * 2 vec(q^-1 q') in the body frame) or points (x y z, 3-D). Factors: a pose factor a->b with
 * mean z (t, q) and the lower-triangular square-root information W (packed, 21 values) of the
 * input's covariance in the chart [t, 2 vec(z_q^-1 q)]; a point factor a->p with mean z (t)
 * and W (6 values); a prior: an anchor pose and k variables, error R c + d with c the charts
 * of (anchor^-1 x_j) around zhat_j. Coordinates outside pose_active / point_active are held
 * at their estimates (the map's samples do not vary in them: a planar map's z, qx, qy). */
typedef struct {
    int64_t nv;
    const int32_t *vkind;   /* 0 pose, 1 point */
    const uint8_t *vfixed;  /* 1: the component's root (the gauge): not solved for */
    const uint8_t *vkept;   /* 1: eliminated last (the trailing block is their joint) */
    double *x;              /* nv x 7, in the root's frame; the solve updates it */
    int64_t nf;
    const int32_t *fkind;   /* 0 pose, 1 point */
    const int32_t *fvars;   /* nf x 2 */
    const double *fz;       /* nf x 7 */
    const double *fw;       /* nf x 21 */
    const double *ftrim;    /* nf: a loop closure's chi-square threshold for trimming; 0: never */
    int64_t np;
    const int64_t *pvoff;   /* np + 1 offsets into pvars */
    const int32_t *pvars;   /* per prior: anchor, then its k variables */
    const int64_t *pdoff;   /* np + 1 offsets into pdata */
    const int64_t *prows;   /* rows of each prior */
    const double *pdata;    /* per prior: zhat (k x 7), R (rows x cols), d (rows) */
    int64_t pose_active;    /* bit k: pose coordinate k (x y z rx ry rz) is solved for */
    int64_t point_active;   /* bit k: point coordinate k is solved for */
    int64_t max_iter;       /* 0: factorise at x only (marginalisation) */
    double tol;             /* stop when an accepted step lowers the cost by less than tol * cost */
    int64_t keep_factor;    /* 1: factorise at the result and keep it (redraw, marginals); 0: the
                             * solution and its costs only (a re-centring), the same x */
    double stats[11];       /* out: see mr_solve */
    void *state;            /* the last factorisation (mr_free) */
} mr_problem;

/* Quaternion helpers (scalar first). */
static inline void mr_qmul(const double *p, const double *q, double *o) {
    o[0] = p[0] * q[0] - p[1] * q[1] - p[2] * q[2] - p[3] * q[3];
    o[1] = p[0] * q[1] + p[1] * q[0] + p[2] * q[3] - p[3] * q[2];
    o[2] = p[0] * q[2] - p[1] * q[3] + p[2] * q[0] + p[3] * q[1];
    o[3] = p[0] * q[3] + p[1] * q[2] - p[2] * q[1] + p[3] * q[0];
}

/* Rotation matrix R(q), row-major. */
static inline void mr_rotmat(const double *q, double *r) {
    double w = q[0], x = q[1], y = q[2], z = q[3];
    r[0] = 1.0 - 2.0 * (y * y + z * z);
    r[1] = 2.0 * (x * y - w * z);
    r[2] = 2.0 * (x * z + w * y);
    r[3] = 2.0 * (x * y + w * z);
    r[4] = 1.0 - 2.0 * (x * x + z * z);
    r[5] = 2.0 * (y * z - w * x);
    r[6] = 2.0 * (x * z - w * y);
    r[7] = 2.0 * (y * z + w * x);
    r[8] = 1.0 - 2.0 * (x * x + y * y);
}

/* q <- q (x) (sqrt(1 - |h|^2), h) with h = v / 2, renormalised (the chart's retraction). */
static inline void mr_qretract(double *q, const double *v) {
    double h[4] = {0.0, 0.5 * v[0], 0.5 * v[1], 0.5 * v[2]};
    double hh = h[1] * h[1] + h[2] * h[2] + h[3] * h[3];
    h[0] = hh < 1.0 ? sqrt(1.0 - hh) : 0.0;
    double o[4];
    mr_qmul(q, h, o);
    double s = sqrt(o[0] * o[0] + o[1] * o[1] + o[2] * o[2] + o[3] * o[3]);
    for (int k = 0; k < 4; k++) q[k] = o[k] / s;
}

/* Internal: the factorisation of one solve, read by the redraw (_relin_draw.c). */
typedef struct {
    long ns;          /* variables in the system (not fixed), = positions */
    long kept_pos;    /* first position of a kept variable */
    int *var_at;      /* position -> variable */
    int *pos_of;      /* variable -> position, -1 if fixed */
    int *dim;         /* position -> active dimensions */
    int *act;         /* position -> active coordinates (6 per position) */
    long *soff;       /* position -> first scalar (ns + 1) */
    long *cptr;       /* column structure: rows of column p are crow[cptr[p]..cptr[p+1]) */
    int *crow;        /* row positions, ascending */
    long *boff;       /* value offset of each crow entry's block (d_row x d_col, row-major) */
    long *doff;       /* value offset of each diagonal block */
    double *val;      /* L (factorised) */
    double *hval;     /* H at the current estimate (before damping) */
    double *g;        /* gradient J^T r, by scalar */
    double *y;        /* work: L^-1 g */
    double *dx;       /* work: the step */
    double *hdiag;    /* diagonal of H (pivot tolerance) */
    uint8_t *dead;    /* scalar with no information (pivot below tolerance): held fixed */
    uint8_t *off;     /* factor left out (trimmed) */
    long nval, nscal;
    int factored;     /* 1: val holds the factorisation at the solution (keep_factor) */
} mr_state;

/* _relin_order.c, _relin_chol.c */
int mr_build_structure(const mr_problem *P, mr_state *S);
void mr_factorise(mr_state *S, double lambda, int *slot);
void mr_forward(const mr_state *S, const double *b, double *y);
void mr_backward(const mr_state *S, double *x, long p0, long stride, long nrhs);

#endif
