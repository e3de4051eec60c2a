/* mcsm's device kernel: the passes whose cost grows with the map (a loop closure's frame pass,
 * the transform of a join and a re-root) on a CUDA GPU, with the arithmetic of
 * kernel_common.h, the same functions the CPU kernel (_kernel.c) runs, in the same order.
 *
 * Compiled at run time by NVRTC (mcsm.core.device) with --fmad=false: no multiply-add is
 * fused, so every value is bit-identical to the CPU kernel's (docs/kernel.md, "The device
 * kernel"). The tests compile this same file as host C++ (_kernel_emulation.cpp) and run
 * every launch thread by thread on the CPU. No shared memory, no barrier, no floating-point
 * atomic: a thread's result never depends on another thread of the same launch, which is
 * what makes the emulation exact.
 *
 * Device layout of a component ("frame-minor"): one buffer (7, N, cap) of float64, the value
 * of row d (x y z qw qx qy qz), sample i, frame f at (d N + i) cap + f. Consecutive threads
 * take consecutive frames, so every warp reads and writes 32 consecutive doubles (256 bytes)
 * at each step of its loops: the sums, the apply step and the transform are coalesced.
 *
 * Sums over samples keep the CPU's four lanes: one thread per (frame, row, lane) runs lane
 * l's chain (samples l, l + 4, ... below 4 floor(N / 4)), a per-frame thread combines the
 * lanes as (l0 + l1) + (l2 + l3) and adds the tail in order.
 */
#include "kernel_common.h"

typedef long long mk_i64;

#define MK_KERNEL extern "C" __global__ void
#define AT(buf, cap, n, f, d, i) (buf)[((mk_i64)(d) * (n) + (i)) * (cap) + (f)]

static __device__ __forceinline__ mk_i64 mk_tid(void) {
    return (mk_i64)blockIdx.x * (mk_i64)blockDim.x + (mk_i64)threadIdx.x;
}

/* ------------------------------------------------------------------ the joint update */

/* One lane of one row's moments against mm rows r (mm known at compile time). */
template <int MM>
static __device__ __forceinline__ void lane_moments(const double *buf, mk_i64 cap, mk_i64 n,
                                                    mk_i64 f, int d, int lane, const double *r,
                                                    double *out, mk_i64 m) {
    double s = AT(buf, cap, n, f, d, 0);
    double a1 = 0.0, a2 = 0.0, ac[MM > 0 ? MM : 1];
    for (int j = 0; j < MM; j++) ac[j] = 0.0;
    mk_i64 n4 = n - n % 4;
    for (mk_i64 i = lane; i < n4; i += 4) {
        double e;
        MK_MOMENT_STEP(e, AT(buf, cap, n, f, d, i), s, a1, a2);
        for (int j = 0; j < MM; j++) MK_CROSS_STEP(ac[j], e, r[j * n + i]);
    }
    out[0 * m] = a1;
    out[1 * m] = a2;
    for (int j = 0; j < MM; j++) out[(2 + j) * m] = ac[j];
}

#define LANE_CASE(M) case M: lane_moments<M>(buf, cap, n, f, task, lane, r, o, m); return;

/* part (ntask, 4 lanes, nacc, m): thread (task, lane, frame), frames fastest. Tasks 0..6: the
 * moments of row `task` (nacc = 2 + p or 2 + k accumulators); tasks 7..16 (endpoint gain):
 * the shifted product sums of the quaternion pairs. Frame 0 (the root) is skipped. */
MK_KERNEL mk_d_joint_sums(const mk_joint_args *A, const double *buf, mk_i64 cap, mk_i64 m,
                          int ntask, int nacc, double *part) {
    mk_i64 t = mk_tid();
    if (t >= (mk_i64)ntask * 4 * m) return;
    mk_i64 f = t % m, rest = t / m;
    int lane = (int)(rest % 4), task = (int)(rest / 4);
    if (f == 0) return;
    mk_i64 n = A->n;
    double *o = part + ((mk_i64)(task * 4 + lane) * nacc) * m + f;
    if (task < 7) {
        int mm = A->gain == 0 ? A->p : A->k;
        const double *r = A->gain == 0 ? A->yc : A->pcs;
        switch (mm) {
            LANE_CASE(0) LANE_CASE(1) LANE_CASE(2) LANE_CASE(3) LANE_CASE(4) LANE_CASE(5)
            LANE_CASE(6) LANE_CASE(7) LANE_CASE(8) LANE_CASE(9) LANE_CASE(10) LANE_CASE(11)
            LANE_CASE(12)
            default: return;
        }
    }
    int a = 3 + mk_pair_a(task - 7), b = 3 + mk_pair_b(task - 7);
    double sa = AT(buf, cap, n, f, a, 0), sb = AT(buf, cap, n, f, b, 0), acc = 0.0;
    mk_i64 n4 = n - n % 4;
    for (mk_i64 i = lane; i < n4; i += 4)
        MK_COV_STEP(acc, AT(buf, cap, n, f, a, i), sa, AT(buf, cap, n, f, b, i), sb);
    o[0] = acc;
}

/* one accumulator q of task `task`, its four lanes combined */
static __device__ __forceinline__ double lanes_of(const double *part, int task, int nacc,
                                                  int q, mk_i64 m, mk_i64 f) {
    double l[4];
    for (int lane = 0; lane < 4; lane++) l[lane] = part[((mk_i64)(task * 4 + lane) * nacc + q) * m + f];
    return mk_lanes(l[0], l[1], l[2], l[3]);
}

/* One thread per frame: the lanes combined, the tail samples added in order, then the
 * per-frame algebra (mk_joint_gain). Writes cxy (p * 7, m), nmean (7, m), rc (m). */
MK_KERNEL mk_d_joint_gain(const mk_joint_args *A, const double *buf, mk_i64 cap, mk_i64 m,
                          int nacc, const double *part, double *cxy, double *nmean, int *rc) {
    mk_i64 f = mk_tid();
    if (f >= m) return;
    if (f == 0) {
        rc[0] = MK_OK;
        return;
    }
    mk_i64 n = A->n, n4 = n - n % 4;
    int mm = A->gain == 0 ? A->p : A->k;
    const double *r = A->gain == 0 ? A->yc : A->pcs;
    double x0[7], s1[7], s2[7], c[7 * MAXK], covq[MK_NPAIRS];
    for (int d = 0; d < 7; d++) {
        x0[d] = AT(buf, cap, n, f, d, 0);
        s1[d] = lanes_of(part, d, nacc, 0, m, f);
        s2[d] = lanes_of(part, d, nacc, 1, m, f);
        for (int j = 0; j < mm; j++) c[d * MAXK + j] = lanes_of(part, d, nacc, 2 + j, m, f);
        for (mk_i64 i = n4; i < n; i++) {
            double e;
            MK_MOMENT_STEP(e, AT(buf, cap, n, f, d, i), x0[d], s1[d], s2[d]);
            for (int j = 0; j < mm; j++) MK_CROSS_STEP(c[d * MAXK + j], e, r[j * n + i]);
        }
    }
    if (A->gain == 1)
        for (int t = 0; t < MK_NPAIRS; t++) {
            int a = 3 + mk_pair_a(t), b = 3 + mk_pair_b(t);
            double sa = AT(buf, cap, n, f, a, 0), sb = AT(buf, cap, n, f, b, 0);
            double acc = lanes_of(part, 7 + t, nacc, 0, m, f);
            for (mk_i64 i = n4; i < n; i++)
                MK_COV_STEP(acc, AT(buf, cap, n, f, a, i), sa, AT(buf, cap, n, f, b, i), sb);
            covq[t] = acc;
        }
    double cx[MAXP * 7], nm[7];
    int code = mk_joint_gain(A, x0, s1, s2, c, covq, cx, nm);
    rc[f] = code;
    if (code != MK_OK) return;
    for (int k = 0; k < A->p * 7; k++) cxy[(mk_i64)k * m + f] = cx[k];
    for (int d = 0; d < 7; d++) nmean[(mk_i64)d * m + f] = nm[d];
}

/* Samples [i0, i1) of frame f: move, inflate, renormalise (mk_joint_apply, one sample per
 * call: MK_LANES is 1 here), pin a point frame's quaternions; the OR of the samples' flags. */
template <int P>
static __device__ __forceinline__ int apply_span(const mk_joint_args *A, const double *buf,
                                                 mk_i64 cap, double *out, mk_i64 m, mk_i64 f,
                                                 mk_i64 i0, mk_i64 i1, int point,
                                                 const double *cxy, const double *nmean) {
    mk_i64 n = A->n;
    double cx[P * 7], nm[7];
    for (int k = 0; k < P * 7; k++) cx[k] = cxy[(mk_i64)k * m + f];
    for (int d = 0; d < 7; d++) nm[d] = nmean[(mk_i64)d * m + f];
    int inflate = A->inflation != 1.0, flags = 0;
    double lam = A->inflation;
    for (mk_i64 i = i0; i < i1; i++) {
        double os[7];
        flags |= mk_joint_apply(cx, nm, inflate, lam, P, &AT(buf, cap, n, f, 0, i), n * cap,
                                A->w + i, n, os, 1);
        if (point) mk_pin_sample(os + 3);
        for (int d = 0; d < 7; d++) AT(out, cap, n, f, d, i) = os[d];
    }
    return flags;
}

#define APPLY_CASE(P) case P: \
    flags = apply_span<P>(A, buf, cap, out, m, f, i0, i1, point[f], cxy, nmean); break;

/* Thread (chunk, frame), frames fastest; each thread does `spt` consecutive samples of one
 * frame. Frame 0 becomes the identity; frames whose gain failed are left alone (the update is
 * refused). flags[f] |= the samples' MK_FLAG_* (an integer OR: order-free). */
MK_KERNEL mk_d_joint_apply(const mk_joint_args *A, const double *buf, mk_i64 cap, double *out,
                           mk_i64 m, const unsigned char *point, const double *cxy,
                           const double *nmean, const int *rc, int spt, int *flags_out) {
    mk_i64 t = mk_tid(), n = A->n;
    mk_i64 chunks = (n + spt - 1) / spt;
    if (t >= m * chunks) return;
    mk_i64 f = t % m, i0 = (t / m) * spt, i1 = i0 + spt < n ? i0 + spt : n;
    if (f == 0) {
        for (mk_i64 i = i0; i < i1; i++)
            for (int d = 0; d < 7; d++) AT(out, cap, n, f, d, i) = d == 3 ? 1.0 : 0.0;
        return;
    }
    if (rc[f] != MK_OK) return;
    int flags = 0;
    switch (A->p) {
        APPLY_CASE(1) APPLY_CASE(2) APPLY_CASE(3) APPLY_CASE(4) APPLY_CASE(5) APPLY_CASE(6)
        APPLY_CASE(7)
        default: flags = MK_FLAG_NONFINITE;
    }
    if (flags) atomicOr(flags_out + f, flags);
}

/* ------------------------------------------------------------------ joins and re-roots */

/* Thread (sample, frame), frames fastest: out frame perm[f] = pre (+) in frame f, its
 * quaternion renormalised (a point frame's pinned). pre: one AT as rows (7, N). */
MK_KERNEL mk_d_transform(const double *pre, const double *in, mk_i64 cap_in, double *out,
                         mk_i64 cap_out, mk_i64 m, mk_i64 n, const unsigned char *point,
                         const mk_i64 *perm) {
    mk_i64 t = mk_tid();
    if (t >= m * n) return;
    mk_i64 f = t % m, i = t / m, g = perm[f];
    double as[7], bs[7], os[7];
    for (int d = 0; d < 7; d++) {
        as[d] = pre[d * n + i];
        bs[d] = AT(in, cap_in, n, f, d, i);
    }
    mk_compound_sample(as, bs, os);
    if (point[f]) mk_pin_sample(os + 3);
    else mk_normalize_sample(os + 3);
    for (int d = 0; d < 7; d++) AT(out, cap_out, n, g, d, i) = os[d];
}

/* Thread (lane, frame): lane `lane` of the mean rotation's four sums of each full frame (the
 * samples on the hemisphere of the frame's first sample). part (4 lanes, 4, m). */
MK_KERNEL mk_d_meanrot_lanes(const double *buf, mk_i64 cap, mk_i64 m, mk_i64 n,
                             const unsigned char *point, double *part) {
    mk_i64 t = mk_tid();
    if (t >= 4 * m) return;
    mk_i64 f = t % m;
    int lane = (int)(t / m);
    if (point[f]) return;
    double r[4], sum[4] = {0.0, 0.0, 0.0, 0.0};
    for (int k = 0; k < 4; k++) r[k] = AT(buf, cap, n, f, 3 + k, 0);
    mk_i64 n4 = n - n % 4;
    for (mk_i64 i = lane; i < n4; i += 4)
        mk_meanrot_add(sum, AT(buf, cap, n, f, 3, i), AT(buf, cap, n, f, 4, i),
                       AT(buf, cap, n, f, 5, i), AT(buf, cap, n, f, 6, i), r);
    for (int k = 0; k < 4; k++) part[((mk_i64)lane * 4 + k) * m + f] = sum[k];
}

/* Thread per frame: the lanes combined, the tail added, the mean rotation (4, m). */
MK_KERNEL mk_d_meanrot_finish(const double *buf, mk_i64 cap, mk_i64 m, mk_i64 n,
                              const unsigned char *point, const double *part, double *mrot) {
    mk_i64 f = mk_tid();
    if (f >= m || point[f]) return;
    double r[4], sum[4], mr[4];
    for (int k = 0; k < 4; k++) {
        r[k] = AT(buf, cap, n, f, 3 + k, 0);
        sum[k] = mk_lanes(part[(0 * 4 + k) * m + f], part[(1 * 4 + k) * m + f],
                          part[(2 * 4 + k) * m + f], part[(3 * 4 + k) * m + f]);
    }
    for (mk_i64 i = n - n % 4; i < n; i++)
        mk_meanrot_add(sum, AT(buf, cap, n, f, 3, i), AT(buf, cap, n, f, 4, i),
                       AT(buf, cap, n, f, 5, i), AT(buf, cap, n, f, 6, i), r);
    mk_meanrot_finish(sum, n, mr);
    for (int k = 0; k < 4; k++) mrot[(mk_i64)k * m + f] = mr[k];
}

/* Thread (sample, frame): a full frame's quaternion put on its mean rotation's hemisphere;
 * flags[f] |= 1 if any value of the sample is not finite. */
MK_KERNEL mk_d_canon_check(double *buf, mk_i64 cap, mk_i64 m, mk_i64 n,
                           const unsigned char *point, const double *mrot, int *flags) {
    mk_i64 t = mk_tid();
    if (t >= m * n) return;
    mk_i64 f = t % m, i = t / m;
    double v[7];
    for (int d = 0; d < 7; d++) v[d] = AT(buf, cap, n, f, d, i);
    if (!point[f]) {
        double mr[4];
        for (int k = 0; k < 4; k++) mr[k] = mrot[(mk_i64)k * m + f];
        mk_flip_sample(v + 3, mr);
        for (int k = 0; k < 4; k++) AT(buf, cap, n, f, 3 + k, i) = v[3 + k];
    }
    int ok = 1;
    for (int d = 0; d < 7; d++) ok &= mk_finite(v[d]);
    if (!ok) atomicOr(flags + f, 1);
}
