/* mcsm's shared arithmetic: the per-sample and per-frame functions of every pass whose cost
 * grows with the map (loop closure, join, re-root, import, points), written once for the CPU
 * kernel (_kernel.c, C11) and the device kernel (_kernel_cuda.cu, CUDA C++ compiled by NVRTC
 * with --fmad=false, and the same file compiled as host C++ by the tests' launch emulation).
 *
 * The subset both languages accept: no VLAs, no compound literals, no designated
 * initialisers, no memcpy, no libm beyond sqrt and fabs (both IEEE exact on every target),
 * no INFINITY macro (the CPU-only lane helpers under MK_LANE_VECTOR excepted). MK_FN marks a
 * function for both host and device.
 *
 * Rules (docs/design.md "Portable arithmetic"): only +, -, *, / and sqrt, in the order the
 * source gives, never contracted into fused multiply-adds. A sum over the samples of one row
 * runs in four lanes: lane l takes samples i = l, l + 4, ... below 4 floor(n / 4), each lane
 * one sequential chain from 0.0 through the step macros below; the lanes combine as
 * mk_lanes(l0, l1, l2, l3) = (l0 + l1) + (l2 + l3); the tail samples follow in order through
 * the same step. The CPU runs the four chains as one 4-wide vector (each step macro applies to
 * a vector as to a scalar); the device runs each chain in one thread. Checks over samples are
 * per-sample predicates OR-ed per frame (order-free).
 */
#ifndef MCSM_KERNEL_COMMON_H
#define MCSM_KERNEL_COMMON_H

#if defined(__CUDACC__)
#define MK_FN static __host__ __device__ __forceinline__
#else
#include <math.h>
#define MK_FN static inline
#endif

/* The lane type of the per-sample apply step (mk_joint_apply): MK_LANES consecutive samples
 * of one row, each on its own, never mixed with another. The device (and its host
 * emulation) runs one sample per thread: a double. The CPU kernel defines MK_LANE_VECTOR
 * before including this file: four samples in one 4-wide vector (GCC's vector extension;
 * one AVX2 register, or two SSE2 ones in the baseline build), so that the step runs on four
 * samples per instruction whatever the compiler's auto-vectoriser does. Only +, -, *, / act
 * on lanes (a scalar operand is broadcast); these helpers do the rest. */
#if defined(MK_LANE_VECTOR)
#include <string.h>
#define MK_LANES 4
typedef double mk_lane __attribute__((vector_size(32)));
typedef long long mk_lane_mask __attribute__((vector_size(32)));  /* -1 true, 0 false */
MK_FN mk_lane mk_lane_splat(double x) {
    mk_lane v = {x, x, x, x};
    return v;
}
MK_FN mk_lane mk_lane_load(const double *p) { mk_lane v; memcpy(&v, p, sizeof v); return v; }
MK_FN void mk_lane_store(double *p, mk_lane v) { memcpy(p, &v, sizeof v); }
MK_FN mk_lane mk_lane_sqrt(mk_lane v) {
    mk_lane r;
    for (int l = 0; l < MK_LANES; l++) r[l] = sqrt(v[l]);
    return r;
}
MK_FN int mk_lane_all(mk_lane_mask m) { return (m[0] & m[1] & m[2] & m[3]) != 0; }
MK_FN double mk_lane_get(mk_lane v, int l) { return v[l]; }
#else
#define MK_LANES 1
typedef double mk_lane;
typedef int mk_lane_mask;
MK_FN mk_lane mk_lane_splat(double x) { return x; }
MK_FN mk_lane mk_lane_load(const double *p) { return *p; }
MK_FN void mk_lane_store(double *p, mk_lane v) { *p = v; }
MK_FN mk_lane mk_lane_sqrt(mk_lane v) { return sqrt(v); }
MK_FN int mk_lane_all(mk_lane_mask m) { return m != 0; }
MK_FN double mk_lane_get(mk_lane v, int l) { (void)l; return v; }
#endif

#define MK_OK 0
#define MK_NONFINITE_GAIN 1
#define MK_BAD_QUATERNION 2
#define MK_NONFINITE 3
#define MK_BAD_ARGS 4

#define MAXP 7   /* largest observation dimension (quaternion space) */
#define MAXK 12  /* largest number of endpoint components */
#define MAXD 13  /* largest small matrix */

#define ZERO_VARIANCE 1e-20
#define RTOL 1e-9
#define MK_DBL_MAX 1.7976931348623157e308

/* per-sample flags of the joint update's apply step, OR-ed per frame */
#define MK_FLAG_BAD_QUATERNION 1
#define MK_FLAG_NONFINITE 2

/* ------------------------------------------------------------------ lane steps
 * Each takes scalars or the CPU's 4-wide vectors alike (plain + - * only). */

/* one sample of a row's shifted moments: d = x - s; s1 += d; s2 += d d */
#define MK_MOMENT_STEP(d, x, s, a1, a2) ((d) = (x) - (s), (a1) += (d), (a2) += (d) * (d))
/* one sample of a cross sum: acc += d r */
#define MK_CROSS_STEP(acc, d, r) ((acc) += (d) * (r))
/* one sample of a shifted product sum: acc += (xa - sa)(xb - sb) */
#define MK_COV_STEP(acc, xa, sa, xb, sb) ((acc) += ((xa) - (sa)) * ((xb) - (sb)))
/* a quaternion dot product, in this order */
#define MK_QDOT(a, b, c, d, r0, r1, r2, r3) ((a) * (r0) + (b) * (r1) + (c) * (r2) + (d) * (r3))

MK_FN double mk_lanes(double l0, double l1, double l2, double l3) { return (l0 + l1) + (l2 + l3); }

/* the hemisphere sign of a dot product: -1 below zero, else 1 (NaN gives 1) */
MK_FN double mk_sign(double dot) { return dot < 0.0 ? -1.0 : 1.0; }

/* 1 if x is finite (x * 0 is NaN for an infinity or a NaN) */
MK_FN int mk_finite(double x) { return x * 0.0 == 0.0; }

/* ------------------------------------------------------------------ per-sample algebra */

MK_FN void mk_qmul(double pw, double px, double py, double pz, double qw, double qx, double qy,
                   double qz, double *o) {
    o[0] = pw * qw - px * qx - py * qy - pz * qz;
    o[1] = pw * qx + px * qw + py * qz - pz * qy;
    o[2] = pw * qy - px * qz + py * qw + pz * qx;
    o[3] = pw * qz + px * qy - py * qx + pz * qw;
}

/* R(q) v with t = 2 u x v, v + w t + u x t */
MK_FN void mk_qrot(double w, double ux, double uy, double uz, double vx, double vy, double vz,
                   double *o) {
    double tx = 2.0 * (uy * vz - uz * vy);
    double ty = 2.0 * (uz * vx - ux * vz);
    double tz = 2.0 * (ux * vy - uy * vx);
    o[0] = vx + w * tx + (uy * tz - uz * ty);
    o[1] = vy + w * ty + (uz * tx - ux * tz);
    o[2] = vz + w * tz + (ux * ty - uy * tx);
}

/* o = a (+) b for one sample (7 values each: x y z qw qx qy qz); o may not alias a or b */
MK_FN void mk_compound_sample(const double *a, const double *b, double *o) {
    double t[3], q[4];
    mk_qrot(a[3], a[4], a[5], a[6], b[0], b[1], b[2], t);
    o[0] = a[0] + t[0];
    o[1] = a[1] + t[1];
    o[2] = a[2] + t[2];
    mk_qmul(a[3], a[4], a[5], a[6], b[3], b[4], b[5], b[6], q);
    o[3] = q[0];
    o[4] = q[1];
    o[5] = q[2];
    o[6] = q[3];
}

/* one quaternion (4 values) scaled to unit norm */
MK_FN void mk_normalize_sample(double *q) {
    double s = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    q[0] = q[0] / s;
    q[1] = q[1] / s;
    q[2] = q[2] / s;
    q[3] = q[3] / s;
}

/* identity quaternion of a point frame's edge */
MK_FN void mk_pin_sample(double *q) {
    q[0] = 1.0;
    q[1] = 0.0;
    q[2] = 0.0;
    q[3] = 0.0;
}

/* one sample of the chordal mean rotation's sums: the sample on the reference's hemisphere */
MK_FN void mk_meanrot_add(double *sum, double q0, double q1, double q2, double q3,
                          const double *r) {
    double s = mk_sign(MK_QDOT(q0, q1, q2, q3, r[0], r[1], r[2], r[3]));
    sum[0] += q0 * s;
    sum[1] += q1 * s;
    sum[2] += q2 * s;
    sum[3] += q3 * s;
}

/* the mean rotation from its four sums over n samples: divided by n, normalised */
MK_FN void mk_meanrot_finish(const double *sum, long n, double *m) {
    for (int k = 0; k < 4; k++) m[k] = sum[k] / (double)n;
    double norm = sqrt(m[0] * m[0] + m[1] * m[1] + m[2] * m[2] + m[3] * m[3]);
    for (int k = 0; k < 4; k++) m[k] = m[k] / norm;
}

/* one quaternion put on the hemisphere of m */
MK_FN void mk_flip_sample(double *q, const double *m) {
    if (MK_QDOT(q[0], q[1], q[2], q[3], m[0], m[1], m[2], m[3]) < 0.0) {
        q[0] = -q[0];
        q[1] = -q[1];
        q[2] = -q[2];
        q[3] = -q[3];
    }
}

/* ------------------------------------------------------------------ the joint update */

typedef struct {
    long n;          /* samples */
    int p;           /* observation dimension */
    int space;       /* 0 tangent, 1 quaternion */
    int gain;        /* 0 direct, 1 endpoints */
    double shrink;   /* < 0: off */
    double inflation;
    double wmax;
    const double *yc;     /* p rows */
    const double *w;      /* p rows */
    const double *var_y;  /* p */
    const double *sum_yc; /* p */
    const double *wbar;   /* p */
    /* endpoints */
    int k;
    const double *pcs;    /* k rows */
    const double *lam;    /* k */
    const double *cpy;    /* k x p, shrunk */
    const double *sum_pc; /* k */
} mk_joint_args;

MK_FN double mk_clip01(double f) {
    if (f != f) return 0.0;
    return f < 0.0 ? 0.0 : (f > 1.0 ? 1.0 : f);
}

/* the quaternion pairs (a <= b) of the endpoint gain's 4 x 4 covariance, in this order */
#define MK_NPAIRS 10
MK_FN int mk_pair_a(int t) { return t < 4 ? 0 : (t < 7 ? 1 : (t < 9 ? 2 : 3)); }
MK_FN int mk_pair_b(int t) { return t < 4 ? t : (t < 7 ? t - 3 : (t < 9 ? t - 5 : 3)); }

/* The per-frame algebra of the joint update, from the frame's sums: each row d's shift x0[d]
 * (its first sample), s1[d] = sum(x - x0), s2[d] = sum((x - x0)^2), c[d * MAXK + j] =
 * sum((x - x0) r_j) with r the centred prediction (gain 0, p rows) or the endpoint
 * components (gain 1, k rows), and (gain 1) covq[t] = sum((x_a - x0_a)(x_b - x0_b)) over the
 * quaternion pairs t. Writes the cross-covariance cxy[k * 7 + d] (p x 7) and the frame's
 * inflation centre nmean (7). Returns MK_OK or MK_NONFINITE_GAIN (unbounded gain). */
MK_FN int mk_joint_gain(const mk_joint_args *A, const double *x0, const double *s1,
                        const double *s2, const double *c, const double *covq, double *cxy,
                        double *nmean) {
    long n = A->n;
    int p = A->p;
    double nm1 = (double)(n - 1), dn = (double)n;
    double mean[7], var[7];
    if (A->gain == 0) {
        for (int d = 0; d < 7; d++) {
            double dm = s1[d] / dn;
            mean[d] = x0[d] + dm;
            double v = (s2[d] - s1[d] * dm) / nm1;
            var[d] = v > 0.0 ? v : 0.0;
            for (int k = 0; k < p; k++)
                cxy[k * 7 + d] = (c[d * MAXK + k] - dm * A->sum_yc[k]) / nm1;
        }
        if (A->space == 0) {
            double qn = sqrt(mean[3] * mean[3] + mean[4] * mean[4] + mean[5] * mean[5] +
                             mean[6] * mean[6]);
            double qb[4];
            for (int j = 0; j < 4; j++) qb[j] = mean[3 + j] / qn;
            for (int k = 0; k < p; k++) {
                double rad = cxy[k * 7 + 3] * qb[0] + cxy[k * 7 + 4] * qb[1] +
                             cxy[k * 7 + 5] * qb[2] + cxy[k * 7 + 6] * qb[3];
                for (int j = 0; j < 4; j++) cxy[k * 7 + 3 + j] -= rad * qb[j];
            }
        }
        if (A->shrink >= 0.0) {
            for (int k = 0; k < p; k++)
                for (int d = 0; d < 7; d++) {
                    double cv = cxy[k * 7 + d];
                    double denom = A->var_y[k] * var[d];
                    double r2 = denom > 0.0 ? cv * cv / denom : 0.0;
                    double f = r2 > 0.0 ? 1.0 - A->shrink * ((1.0 - r2) * (1.0 - r2)) / (dn * r2)
                                        : 0.0;
                    cxy[k * 7 + d] = cv * mk_clip01(f);
                }
        }
    } else {
        int K = A->k;
        double cxp[MAXK * 7];  /* cxp[j * 7 + d] */
        double dev0[7];
        for (int d = 0; d < 7; d++) {
            double dm = s1[d] / dn;
            dev0[d] = dm;
            mean[d] = x0[d] + dm;
            double v = (s2[d] - s1[d] * dm) / nm1;
            var[d] = v > 0.0 ? v : 0.0;
            for (int j = 0; j < K; j++) cxp[j * 7 + d] = (c[d * MAXK + j] - dm * A->sum_pc[j]) / nm1;
        }
        /* quaternion covariance 4 x 4 from shifted cross sums */
        double cq[16];
        for (int t = 0; t < MK_NPAIRS; t++) {
            int a = mk_pair_a(t), b = mk_pair_b(t);
            double cv = (covq[t] - dn * dev0[3 + a] * dev0[3 + b]) / nm1;
            cq[a * 4 + b] = cv;
            cq[b * 4 + a] = cv;
        }
        double qn = sqrt(mean[3] * mean[3] + mean[4] * mean[4] + mean[5] * mean[5] +
                         mean[6] * mean[6]);
        double qb[4];
        for (int j = 0; j < 4; j++) qb[j] = mean[3 + j] / qn;
        /* B = columns 1..3 of L(qb) (4 x 3) */
        double B[12];
        B[0] = -qb[1]; B[1] = -qb[2]; B[2] = -qb[3];
        B[3] = qb[0];  B[4] = -qb[3]; B[5] = qb[2];
        B[6] = qb[3];  B[7] = qb[0];  B[8] = -qb[1];
        B[9] = -qb[2]; B[10] = qb[1]; B[11] = qb[0];
        double varx[6];
        for (int d = 0; d < 3; d++) varx[d] = var[d];
        for (int i = 0; i < 3; i++) {
            double acc = 0.0;
            for (int k = 0; k < 4; k++)
                for (int l = 0; l < 4; l++) acc += B[k * 3 + i] * cq[k * 4 + l] * B[l * 3 + i];
            acc = 4.0 * acc;
            varx[3 + i] = acc > 0.0 ? acc : 0.0;
        }
        double beta[MAXK * 6];
        for (int j = 0; j < K; j++) {
            for (int d = 0; d < 3; d++) beta[j * 6 + d] = cxp[j * 7 + d];
            for (int i = 0; i < 3; i++) {
                double acc = 0.0;
                for (int k = 0; k < 4; k++) acc += B[k * 3 + i] * cxp[j * 7 + 3 + k];
                beta[j * 6 + 3 + i] = 2.0 * acc;
            }
        }
        /* beta = c_xp / lam, then shrunk by the t-statistic */
        double chart[MAXK * 6];
        for (int i = 0; i < K * 6; i++) chart[i] = beta[i];
        for (int j = 0; j < K; j++)
            for (int d = 0; d < 6; d++) beta[j * 6 + d] = chart[j * 6 + d] / A->lam[j];
        if (A->shrink >= 0.0) {
            double dof = (double)((n - K - 1) > 1 ? (n - K - 1) : 1);
            for (int d = 0; d < 6; d++) {
                double expl = 0.0;
                for (int j = 0; j < K; j++) expl += chart[j * 6 + d] * beta[j * 6 + d];
                double ve = varx[d] - expl;
                ve = ve > 0.0 ? ve : 0.0;
                for (int j = 0; j < K; j++) {
                    double b = beta[j * 6 + d];
                    double t2 = b * b * (A->lam[j] * dof) / ve;
                    double f;
                    if (t2 != t2) f = 0.0;            /* 0 / 0 */
                    else if (t2 > 0.0) f = 1.0 - 2.0 * A->shrink / t2;  /* inf gives 1 */
                    else f = 0.0;
                    beta[j * 6 + d] = b * mk_clip01(f);
                }
            }
        }
        double c6[MAXP * 6];
        for (int k = 0; k < p; k++)
            for (int d = 0; d < 6; d++) {
                double acc = 0.0;
                for (int j = 0; j < K; j++) acc += beta[j * 6 + d] * A->cpy[j * p + k];
                c6[k * 6 + d] = acc;
            }
        for (int k = 0; k < p; k++) {
            for (int d = 0; d < 3; d++) cxy[k * 7 + d] = c6[k * 6 + d];
            for (int q = 0; q < 4; q++) {
                double acc = 0.0;
                for (int i = 0; i < 3; i++) acc += B[q * 3 + i] * c6[k * 6 + 3 + i];
                cxy[k * 7 + 3 + q] = 0.5 * acc;
            }
        }
    }
    /* finite, bounded gain */
    double cmax = 0.0;
    for (int i = 0; i < p * 7; i++) {
        double a = fabs(cxy[i]);
        if (!(a == a) || a > MK_DBL_MAX) return MK_NONFINITE_GAIN;
        cmax = a > cmax ? a : cmax;
    }
    if (!(cmax * A->wmax * (double)p < 1e100)) return MK_NONFINITE_GAIN;
    if (A->inflation != 1.0)
        for (int d = 0; d < 7; d++) {
            double acc = 0.0;
            for (int k = 0; k < p; k++) acc += A->wbar[k] * cxy[k * 7 + d];
            nmean[d] = mean[d] + acc;
        }
    else
        for (int d = 0; d < 7; d++) nmean[d] = mean[d];
    return MK_OK;
}

/* The joint update's apply step on MK_LANES consecutive samples of one frame (one lane
 * each): row d's lane at x + d * xs, weight k's at w + k * ws; the output's row d to
 * o + d * os (o may alias x). Each sample is moved by the gain cxy (p x 7), inflated about
 * nmean when `inflate`, and its quaternion renormalised. Returns the OR of
 * MK_FLAG_BAD_QUATERNION if a quaternion's norm was not in (0.1, 1e10) (or NaN) and
 * MK_FLAG_NONFINITE if a translation is not finite. p and inflate are constants where the
 * caller specialises on them. */
MK_FN int mk_joint_rescue(const double *cxy, const double *nmean, int p, const double *x,
                          long xs, const double *w, long ws, double *o, long os);

MK_FN int mk_joint_apply(const double *cxy, const double *nmean, int inflate, double lam,
                         int p, const double *x, long xs, const double *w, long ws, double *o,
                         long os) {
    mk_lane v[7], wk[MAXP];
    for (int k = 0; k < p; k++) wk[k] = mk_lane_load(w + k * ws);
    for (int d = 0; d < 7; d++) {
        mk_lane acc = mk_lane_splat(0.0);
        for (int k = 0; k < p; k++) acc += wk[k] * cxy[k * 7 + d];
        v[d] = mk_lane_load(x + d * xs) + acc;
    }
    if (inflate)
        for (int d = 0; d < 7; d++) v[d] = (v[d] - nmean[d]) * lam + nmean[d];
    mk_lane sq = mk_lane_sqrt(v[3] * v[3] + v[4] * v[4] + v[5] * v[5] + v[6] * v[6]);
    for (int d = 0; d < 3; d++) mk_lane_store(o + d * os, v[d]);
    for (int d = 3; d < 7; d++) mk_lane_store(o + d * os, v[d] / sq);
    /* NaN fails both comparisons; x * 0 is NaN for an infinity or a NaN */
    int flags = 0;
    if (!mk_lane_all((sq > 0.1) & (sq < 1e10))) {
        /* rare: a sample far from the frame's centre; each collapsed one is rescued */
        for (int l = 0; l < MK_LANES; l++) {
            double s = mk_lane_get(sq, l);
            if (s > 0.1 && s < 1e10) continue;
            if (!(s <= 0.1) || mk_joint_rescue(cxy, nmean, p, x + l, xs, w + l, ws, o + l, os))
                flags |= MK_FLAG_BAD_QUATERNION;
        }
    }
    if (!mk_lane_all((v[0] * 0.0 == 0.0) & (v[1] * 0.0 == 0.0) & (v[2] * 0.0 == 0.0)))
        flags |= MK_FLAG_NONFINITE;
    return flags;
}

/* One sample whose moved quaternion collapsed (norm at most 0.1: the linear move in the
 * quaternion's coordinates, exact to first order near the frame's centre, crossed zero for a
 * sample nearly opposite it): its rotation move, read in the tangent at the centre nmean
 * (where the gain's quaternion rows live: 0.5 qc (0, d) for the chart step d), applied on the
 * manifold instead, q (+) d = q (sqrt(1 - |d/2|^2), d/2), without inflation; o's quaternion
 * (the sample's translation is the linear one, already written). Row d's value at
 * x + d * xs, weight k's at w + k * ws. Returns 1 if it cannot (a centre or a sample that is
 * not finite), else 0. */
MK_FN int mk_joint_rescue(const double *cxy, const double *nmean, int p, const double *x,
                          long xs, const double *w, long ws, double *o, long os) {
    double acc[4];
    for (int d = 0; d < 4; d++) {
        double a = 0.0;
        for (int k = 0; k < p; k++) a += w[k * ws] * cxy[k * 7 + 3 + d];
        acc[d] = a;
    }
    double cn = sqrt(nmean[3] * nmean[3] + nmean[4] * nmean[4] + nmean[5] * nmean[5] +
                     nmean[6] * nmean[6]);
    if (!(cn > 0.0 && cn < 1e10)) return 1;
    double c[4] = {nmean[3] / cn, nmean[4] / cn, nmean[5] / cn, nmean[6] / cn};
    double h[4];
    mk_qmul(c[0], -c[1], -c[2], -c[3], acc[0], acc[1], acc[2], acc[3], h);
    double hh = h[1] * h[1] + h[2] * h[2] + h[3] * h[3];
    double hw = hh < 1.0 ? sqrt(1.0 - hh) : 0.0;
    double q[4];
    mk_qmul(x[3 * xs], x[4 * xs], x[5 * xs], x[6 * xs], hw, h[1], h[2], h[3], q);
    double s = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
    if (!(s > 0.1 && s < 1e10)) return 1;
    for (int d = 0; d < 4; d++) o[(3 + d) * os] = q[d] / s;
    return 0;
}

/* the frame's code from its per-sample flags: a bad quaternion first, then a non-finite
 * translation */
MK_FN int mk_flags_code(int flags) {
    if (flags & MK_FLAG_BAD_QUATERNION) return MK_BAD_QUATERNION;
    if (flags & MK_FLAG_NONFINITE) return MK_NONFINITE;
    return MK_OK;
}

#endif
