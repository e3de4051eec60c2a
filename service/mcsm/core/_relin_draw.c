/* mcsm's relinearisation, the parts around the solve (_relin.c): the moments of an input in
 * the project's chart, pose transforms of estimates, the marginal prior of a factorisation,
 * and the redraw of a component's edges from the posterior with a counter-based normal
 * generator.
 *
 * The generator: a uniform from a 64-bit integer hash (splitmix64's finaliser) of a key and a
 * counter, a normal by Marsaglia's polar method with our own logarithm (exponent from the bits,
 * mantissa by the atanh series with a fixed number of terms): only +, -, *, / and sqrt, so
 * every CPU draws the same numbers. Each normal has its own counter (variable, coordinate,
 * sample), so nothing depends on the order in which they are drawn.
 *
 * Portability: _relin.h.
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "_relin.h"
#include "kernel_common.h"

#define ZERO_VARIANCE 1e-20
#define RTOL 1e-9
#define CHUNK 64
#define FULL_MAX (1L << 23)  /* normals held at once (64 MiB); beyond, drawn twice in chunks */
#define LN2 0.69314718055994530942


/* ------------------------------------------------------------------ moments of an input */

/* Chordal mean of quaternion rows q (4 x n), aligned to the first sample, normalised. */
static void chordal_mean(const double *q, long n, double *m) {
    double s[4] = {0.0, 0.0, 0.0, 0.0};
    for (long i = 0; i < n; i++) {
        double dot = q[i] * q[0] + q[n + i] * q[n] + q[2 * n + i] * q[2 * n] +
                     q[3 * n + i] * q[3 * n];
        double sg = dot < 0.0 ? -1.0 : 1.0;
        for (int k = 0; k < 4; k++) s[k] += sg * q[k * n + i];
    }
    double norm = sqrt(s[0] * s[0] + s[1] * s[1] + s[2] * s[2] + s[3] * s[3]);
    for (int k = 0; k < 4; k++) m[k] = s[k] / norm;
}

/* The chart vector [t, 2 s vec(qm^-1 q)] of sample i (rows x), m = 6. */
static void chart_of(const double *x, long n, long i, const double *qm, double *v) {
    for (int k = 0; k < 3; k++) v[k] = x[k * n + i];
    double qc[4] = {qm[0], -qm[1], -qm[2], -qm[3]};
    double q[4] = {x[3 * n + i], x[4 * n + i], x[5 * n + i], x[6 * n + i]}, r[4];
    mr_qmul(qc, q, r);
    double sg = r[0] < 0.0 ? -1.0 : 1.0;
    for (int k = 0; k < 3; k++) v[3 + k] = 2.0 * (sg * r[1 + k]);
}

/* The lower-triangular square-root information W (packed) of covariance c (m x m): every
 * dimension scaled to unit variance, dimensions with variance below 1e-20 dropped, a Cholesky
 * factorisation whose pivots below 1e-9 drop their dimension (nearly dependent on earlier
 * ones), inverted. Dropped dimensions get zero rows and columns. */
static void sqrt_information(const double *c, int m, double *w) {
    double dsc[6], l[36], inv[36];
    int live[6];
    memset(l, 0, sizeof l);
    memset(inv, 0, sizeof inv);
    for (int i = 0; i < m; i++) {
        live[i] = c[i * m + i] > ZERO_VARIANCE;
        dsc[i] = live[i] ? sqrt(c[i * m + i]) : 0.0;
    }
    for (int j = 0; j < m; j++) {
        if (!live[j]) continue;
        double s = c[j * m + j] / (dsc[j] * dsc[j]);
        for (int k = 0; k < j; k++) s -= l[j * m + k] * l[j * m + k];
        if (!(s > RTOL)) {
            live[j] = 0;
            continue;
        }
        double ljj = sqrt(s);
        l[j * m + j] = ljj;
        for (int i = j + 1; i < m; i++) {
            if (!live[i]) continue;
            double t = c[i * m + j] / (dsc[i] * dsc[j]);
            for (int k = 0; k < j; k++) t -= l[i * m + k] * l[j * m + k];
            l[i * m + j] = t / ljj;
        }
    }
    /* inv = L^-1 over the live dimensions (forward substitution, column by column) */
    for (int j = 0; j < m; j++) {
        if (!live[j]) continue;
        inv[j * m + j] = 1.0 / l[j * m + j];
        for (int i = j + 1; i < m; i++) {
            if (!live[i]) continue;
            double t = 0.0;
            for (int k = j; k < i; k++) t += l[i * m + k] * inv[k * m + j];
            inv[i * m + j] = -t / l[i * m + i];
        }
    }
    for (int i = 0; i < m; i++)
        for (int j = 0; j <= i; j++)
            w[i * (i + 1) / 2 + j] = live[i] && live[j] ? inv[i * m + j] / dsc[j] : 0.0;
}

/* An input's mean z (t, q; a point: t, then the identity) and the square-root information W of
 * its covariance in the chart around z (21 values, or 6 for a point), from its samples x
 * (rows: 7 x n, or 3 x n for a point). */
int mr_moments(const double *x, long n, int point, double *z, double *w) {
    if (n < 2) return MR_BAD_ARGS;
    int m = point ? 3 : 6;
    for (int k = 0; k < 3; k++) {
        double s = 0.0;
        for (long i = 0; i < n; i++) s += x[k * n + i];
        z[k] = s / (double)n;
    }
    if (point) {
        z[3] = 1.0;
        z[4] = z[5] = z[6] = 0.0;
    } else {
        chordal_mean(x + 3 * n, n, z + 3);
    }
    double mean[6] = {0, 0, 0, 0, 0, 0}, v[6], cov[36];
    for (long i = 0; i < n; i++) {
        if (point) for (int k = 0; k < 3; k++) v[k] = x[k * n + i];
        else chart_of(x, n, i, z + 3, v);
        for (int k = 0; k < m; k++) mean[k] += v[k];
    }
    for (int k = 0; k < m; k++) mean[k] = mean[k] / (double)n;
    memset(cov, 0, sizeof cov);
    for (long i = 0; i < n; i++) {
        if (point) for (int k = 0; k < 3; k++) v[k] = x[k * n + i];
        else chart_of(x, n, i, z + 3, v);
        for (int k = 0; k < m; k++) v[k] -= mean[k];
        for (int a = 0; a < m; a++)
            for (int b = 0; b <= a; b++) cov[a * m + b] += v[a] * v[b];
    }
    for (int a = 0; a < m; a++)
        for (int b = 0; b <= a; b++) {
            cov[a * m + b] = cov[a * m + b] / (double)(n - 1);
            cov[b * m + a] = cov[a * m + b];
        }
    sqrt_information(cov, m, w);
    for (int k = 0; k < (point ? 6 : 21); k++)
        if (!(w[k] - w[k] == 0.0)) return MR_NONFINITE;
    for (int k = 0; k < 7; k++)
        if (!(z[k] - z[k] == 0.0)) return MR_NONFINITE;
    return MR_OK;
}

/* The mean pose of one frame x (7 x n): each translation row summed in sample order, divided by
 * n; the rotation chordal_mean's, or the identity for a point. One loop carries every sum (each
 * in its own order, so the values are those of separate loops) so that their chains of
 * additions overlap instead of running one after another. */
static void frame_mean(const double *x, long n, int point, double *o) {
    const double *x0 = x, *x1 = x + n, *x2 = x + 2 * n;
    double t0 = 0.0, t1 = 0.0, t2 = 0.0;
    if (point) {
        for (long i = 0; i < n; i++) {
            t0 += x0[i];
            t1 += x1[i];
            t2 += x2[i];
        }
        o[3] = 1.0;
        o[4] = o[5] = o[6] = 0.0;
    } else {
        const double *qw = x + 3 * n, *qx = x + 4 * n, *qy = x + 5 * n, *qz = x + 6 * n;
        const double rw = qw[0], rx = qx[0], ry = qy[0], rz = qz[0];
        double s0 = 0.0, s1 = 0.0, s2 = 0.0, s3 = 0.0;
        for (long i = 0; i < n; i++) {
            t0 += x0[i];
            t1 += x1[i];
            t2 += x2[i];
            double dot = qw[i] * rw + qx[i] * rx + qy[i] * ry + qz[i] * rz;
            double sg = dot < 0.0 ? -1.0 : 1.0;
            s0 += sg * qw[i];
            s1 += sg * qx[i];
            s2 += sg * qy[i];
            s3 += sg * qz[i];
        }
        double norm = sqrt(s0 * s0 + s1 * s1 + s2 * s2 + s3 * s3);
        o[3] = s0 / norm;
        o[4] = s1 / norm;
        o[5] = s2 / norm;
        o[6] = s3 / norm;
    }
    o[0] = t0 / (double)n;
    o[1] = t1 / (double)n;
    o[2] = t2 / (double)n;
}

/* The largest magnitude of the translations of one frame x (7 x n) of finite values (a maximum
 * needs no order: four running ones). */
static double max_abs_translation(const double *x, long n) {
    double b[4] = {0.0, 0.0, 0.0, 0.0};
    long len = 3 * n, i = 0;
    for (; i + 4 <= len; i += 4)
        for (int l = 0; l < 4; l++) b[l] = fabs(x[i + l]) > b[l] ? fabs(x[i + l]) : b[l];
    for (; i < len; i++) b[0] = fabs(x[i]) > b[0] ? fabs(x[i]) : b[0];
    double m01 = b[0] > b[1] ? b[0] : b[1], m23 = b[2] > b[3] ? b[2] : b[3];
    return m01 > m23 ? m01 : m23;
}

/* Mean poses (translation mean, chordal mean rotation; a point: the identity rotation) of
 * frames idx[0..k) of a component's buffer (frames of 7 x n). */
void mr_means(const double *rows, const int64_t *idx, long k, long n, const uint8_t *point,
              double *out) {
    for (long j = 0; j < k; j++) frame_mean(rows + idx[j] * 7 * n, n, point[j], out + 7 * j);
}

void mk_canonicalize(double *x, long n, int normalize);  /* _kernel.c */

/* q_i <- (dq q_i) / |dq q_i| for the rotation rows (4 x n) of one frame, from src to dst (the
 * same rows or others), CHUNK samples at a time through a local block: mr_qmul's products and
 * sums written out in its order, so the loop vectorises with the same bits. */
static void recentre_rotations(const double *dq, const double *src, double *dst, long n) {
    const double p0 = dq[0], p1 = dq[1], p2 = dq[2], p3 = dq[3];
    double r[4][CHUNK];
    for (long i0 = 0; i0 < n; i0 += CHUNK) {
        long k = n - i0 < CHUNK ? n - i0 : CHUNK;
        const double *sw = src + i0, *sx = src + n + i0, *sy = src + 2 * n + i0,
                     *sz = src + 3 * n + i0;
        for (long i = 0; i < k; i++) {
            double q0 = sw[i], q1 = sx[i], q2 = sy[i], q3 = sz[i];
            double r0 = p0 * q0 - p1 * q1 - p2 * q2 - p3 * q3;
            double r1 = p0 * q1 + p1 * q0 + p2 * q3 - p3 * q2;
            double r2 = p0 * q2 - p1 * q3 + p2 * q0 + p3 * q1;
            double r3 = p0 * q3 + p1 * q2 - p2 * q1 + p3 * q0;
            double s = sqrt(r0 * r0 + r1 * r1 + r2 * r2 + r3 * r3);
            r[0][i] = r0 / s;
            r[1][i] = r1 / s;
            r[2][i] = r2 / s;
            r[3][i] = r3 / s;
        }
        for (int c = 0; c < 4; c++) memcpy(dst + c * n + i0, r[c], sizeof(double) * (size_t)k);
    }
}

/* Frames lo..hi-1 of a component's buffer src copied to dst (the same buffer, or one of the
 * same shape), those among idx[0..k) (never the root, 0) moved from their means mu (mr_means) onto
 * the poses tgt (both k x 7) on the way: t_i += t* - mean t and q_i <- (q* mean_q^-1) q_i,
 * normalised, so every sample keeps its chart deviation [t_i - mean t, 2 vec(mean_q^-1 q_i)].
 * Frames other than 0 are then canonicalised as the kernel does (points pinned). Each frame's
 * values depend on that frame only, so ranges may run on threads. MR_NONFINITE if a value is
 * not finite afterwards (dst is then partly written). */
int mr_recentre(const double *src, double *dst, long lo, long hi, long n, const uint8_t *point,
                const int64_t *idx, long k, const double *mu, const double *tgt) {
    long len = hi > lo ? hi - lo : 0;
    long *which = malloc(sizeof(long) * (size_t)(len ? len : 1));
    if (which == NULL) return MR_NO_MEMORY;
    for (long f = 0; f < len; f++) which[f] = -1;
    for (long j = 0; j < k; j++)
        if (idx[j] >= lo && idx[j] < hi) which[idx[j] - lo] = j;
    int rc = MR_OK;
    for (long f = lo; f < hi && rc == MR_OK; f++) {
        const double *x = src + f * 7 * n;
        double *o = dst + f * 7 * n;
        long j = which[f - lo];
        if (j < 0 || f == 0) {
            if (o != x) memcpy(o, x, sizeof(double) * 7 * (size_t)n);
        } else {
            const double *m = mu + 7 * j, *t = tgt + 7 * j;
            for (int c = 0; c < 3; c++) {
                double d = t[c] - m[c];
                for (long i = 0; i < n; i++) o[c * n + i] = x[c * n + i] + d;
            }
            if (point[f]) {
                if (o != x) memcpy(o + 3 * n, x + 3 * n, sizeof(double) * 4 * (size_t)n);
            } else {
                double mc[4] = {m[3], -m[4], -m[5], -m[6]}, dq[4];
                mr_qmul(t + 3, mc, dq);
                recentre_rotations(dq, x + 3 * n, o + 3 * n, n);
            }
        }
        if (f == 0) continue;
        if (point[f]) {
            for (long i = 0; i < n; i++) {
                double s[4];
                mk_pin_sample(s);
                for (int c = 0; c < 4; c++) o[(3 + c) * n + i] = s[c];
            }
        } else {
            mk_canonicalize(o, n, 0);
        }
        int ok = 1;
        for (long i = 0; i < 7 * n; i++) ok &= mk_finite(o[i]);
        if (!ok) rc = MR_NONFINITE;
    }
    free(which);
    return rc;
}

/* Sets in live[pt] (pt: the frame is a point) the bits of the chart coordinates in which one
 * frame x (7 x n) varies, those already set skipped: bits 0-5 the pose coordinates (t, 2 vec(m^-1
 * q) around the frame's chordal mean m; mq: m, or NULL to compute it), bits 0-2 the point ones.
 * A coordinate varies when a sample differs from the first in it (exactly). A frame whose qx
 * and qy are all zero (a planar map) has no variation in rx, ry (the chart's are then +-0
 * too), so it is charted only where that could change the answer. */
static void active_frame(const double *x, long n, int pt, const double *mq, int64_t *live) {
    for (int c = 0; c < 3; c++) {  /* whole-row reductions: they vectorise */
        if (live[pt] & ((int64_t)1 << c)) continue;
        const double *row = x + c * n, first = row[0];
        int differ = 0;
        for (long i = 1; i < n; i++) differ |= row[i] != first;
        if (differ) live[pt] |= (int64_t)1 << c;
    }
    if (pt || (live[0] & 56) == 56) return;
    int need = !(live[0] & 32);
    if (!need && (live[0] & 24) != 24) {
        const double *qx = x + 4 * n, *qy = x + 5 * n;
        int nonzero = 0;
        for (long i = 0; i < n; i++) nonzero |= (qx[i] != 0.0) | (qy[i] != 0.0);
        need = nonzero;
    }
    if (!need) return;
    double m[4], v0[6], v[6];
    if (mq == NULL) chordal_mean(x + 3 * n, n, m);
    else memcpy(m, mq, sizeof m);
    chart_of(x, n, 0, m, v0);
    for (long i = 1; i < n && (live[0] & 56) != 56; i++) {
        chart_of(x, n, i, m, v);
        for (int c = 3; c < 6; c++)
            if (v[c] != v0[c]) live[0] |= (int64_t)1 << c;
    }
}

/* The chart coordinates in which some frame idx[0..k) varies (active_frame): bits 0-5 of
 * masks[0] the pose coordinates, bits 0-2 of masks[1] the point ones; a kind with no frame gets
 * every bit. The scan stops once every bit is set. */
void mr_active(const double *rows, const int64_t *idx, long k, long n, const uint8_t *point,
               int64_t *masks) {
    int64_t live[2] = {0, 0}, seen[2] = {0, 0};
    const int64_t full[2] = {63, 7};
    for (long j = 0; j < k; j++) {
        if (live[0] == full[0] && live[1] == full[1]) break;
        int pt = point[j] ? 1 : 0;
        seen[pt] = 1;
        active_frame(rows + idx[j] * 7 * n, n, pt, NULL, live);
    }
    masks[0] = seen[0] ? live[0] : full[0];
    masks[1] = seen[1] ? live[1] : full[1];
}

/* mr_means of frames idx[0..k) and, in the same pass (each frame read while it is in the
 * cache), active_frame of those among them other than frame 0 (the root), with each frame's
 * chordal mean shared: ls[0..1] the live bits of poses and points, ls[2..3] whether a pose, a
 * point was seen. Both are unions over the frames, so runs over parts of idx combine by OR. */
void mr_means_live(const double *rows, const int64_t *idx, long k, long n, const uint8_t *point,
                   double *out, int64_t *ls) {
    int64_t live[2] = {0, 0}, seen[2] = {0, 0};
    const int64_t full[2] = {63, 7};
    for (long j = 0; j < k; j++) {
        mr_means(rows, idx + j, 1, n, point + j, out + 7 * j);
        if (idx[j] == 0 || (live[0] == full[0] && live[1] == full[1])) {
            if (idx[j] != 0) seen[point[j] ? 1 : 0] = 1;
            continue;
        }
        int pt = point[j] ? 1 : 0;
        seen[pt] = 1;
        active_frame(rows + idx[j] * 7 * n, n, pt, pt ? NULL : out + 7 * j + 3, live);
    }
    ls[0] = live[0];
    ls[1] = live[1];
    ls[2] = seen[0];
    ls[3] = seen[1];
}

/* mr_means of frames idx[0..k) and mr_active of those other than frame 0 in one pass
 * (mr_means_live, finished): the same values as the two calls. */
void mr_means_active(const double *rows, const int64_t *idx, long k, long n,
                     const uint8_t *point, double *out, int64_t *masks) {
    int64_t ls[4];
    mr_means_live(rows, idx, k, n, point, out, ls);
    masks[0] = ls[2] ? ls[0] : 63;
    masks[1] = ls[3] ? ls[1] : 7;
}

int mk_joint_frames(const mk_joint_args *A, const double *edges, double *out,
                    const uint8_t *point, long lo, long hi);  /* _kernel.c */

/* The joint update's frame pass over frames lo..hi-1 (mk_joint_frames, one frame at a time),
 * each output frame's mean (into means + 7 f), the largest magnitude of its translations (big[f])
 * and live chart coordinates (frames other than 0, into ls, mr_means_live's layout) taken while
 * it is in the cache: the values of mk_joint_frames and then mr_means_live over frames
 * lo..hi-1 of out. */
int mr_joint_frames_means(const mk_joint_args *A, const double *edges, double *out,
                          const uint8_t *point, long lo, long hi, double *means, double *big,
                          int64_t *ls) {
    long n = A->n;
    int64_t live[2] = {ls[0], ls[1]};
    int rc = 0;
    for (long f = lo; f < hi; f++) {
        rc = mk_joint_frames(A, edges, out, point, f, f + 1);
        if (rc != 0) break;
        const double *o = out + f * 7 * n;
        frame_mean(o, n, point[f], means + 7 * f);
        big[f] = max_abs_translation(o, n);
        if (f == 0) continue;
        int pt = point[f] ? 1 : 0;
        ls[2 + pt] = 1;
        if (live[0] == 63 && live[1] == 7) continue;
        active_frame(o, n, pt, pt ? NULL : means + 7 * f + 3, live);
    }
    ls[0] = live[0];
    ls[1] = live[1];
    return rc;
}

/* Spread of frames idx[0..k) in each chart coordinate (mr_active's definition, kept as its
 * reference for the tests): max_i |v_i - v_0| of [t, 2 vec(m^-1 q)]
 * around the frame's chordal mean m (points: t only, the rest 0), k x 6. A coordinate in which
 * no sample differs from the first does not vary in the map (a planar map's z, qx, qy). */
void mr_spread(const double *rows, const int64_t *idx, long k, long n, const uint8_t *point,
               double *out) {
    for (long j = 0; j < k; j++) {
        const double *x = rows + idx[j] * 7 * n;
        double *o = out + 6 * j, m[4], v0[6], v[6];
        for (int c = 0; c < 6; c++) o[c] = 0.0;
        if (point[j]) {
            for (long i = 0; i < n; i++)
                for (int c = 0; c < 3; c++) {
                    double d = x[c * n + i] - x[c * n];
                    d = d < 0.0 ? -d : d;
                    if (d > o[c]) o[c] = d;
                }
            continue;
        }
        chordal_mean(x + 3 * n, n, m);
        chart_of(x, n, 0, m, v0);
        for (long i = 0; i < n; i++) {
            chart_of(x, n, i, m, v);
            for (int c = 0; c < 6; c++) {
                double d = v[c] - v0[c];
                d = d < 0.0 ? -d : d;
                if (d > o[c]) o[c] = d;
            }
        }
    }
}

/* out_j = A o b_j with A = a or a^-1 (poses; a point keeps the identity rotation). */
void mr_transform(const double *a, int invert, const double *b, const int32_t *kind, long k,
                  double *out) {
    double ta[3], qa[4] = {a[3], a[4], a[5], a[6]}, r[9];
    if (invert) {
        qa[1] = -qa[1];
        qa[2] = -qa[2];
        qa[3] = -qa[3];
        mr_rotmat(qa, r);
        for (int i = 0; i < 3; i++) ta[i] = -(r[i * 3] * a[0] + r[i * 3 + 1] * a[1] + r[i * 3 + 2] * a[2]);
    } else {
        mr_rotmat(qa, r);
        for (int i = 0; i < 3; i++) ta[i] = a[i];
    }
    for (long j = 0; j < k; j++) {
        const double *x = b + 7 * j;
        double *o = out + 7 * j;
        double t[3];
        for (int i = 0; i < 3; i++) t[i] = r[i * 3] * x[0] + r[i * 3 + 1] * x[1] + r[i * 3 + 2] * x[2];
        double q[4];
        if (kind[j] == 0) {
            mr_qmul(qa, x + 3, q);
            double s = sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
            for (int i = 0; i < 4; i++) q[i] = q[i] / s;
        } else {
            q[0] = 1.0;
            q[1] = q[2] = q[3] = 0.0;
        }
        for (int i = 0; i < 3; i++) o[i] = ta[i] + t[i];
        for (int i = 0; i < 4; i++) o[3 + i] = q[i];
    }
}

/* ------------------------------------------------------------------ the marginal prior */

/* After mr_solve: the Gaussian of the kept variables with the others eliminated, as a
 * square-root factor: cost = |R d_k + y_k|^2 with R = L_kk^T (rows: kept scalars in
 * elimination order; columns: the full dimensions of the kept, non-fixed variables in
 * ascending variable order) and y = L^-1 g. Rows of dimensions without information are 0. */
int mr_marginal(const mr_problem *P, double *R, double *d) {
    const mr_state *S = P->state;
    if (S == NULL || !S->factored) return MR_BAD_ARGS;
    long kp = S->kept_pos, s0 = S->soff[kp], m = S->nscal - s0;
    long *colbase = malloc(sizeof(long) * (size_t)(P->nv ? P->nv : 1));
    if (colbase == NULL) return MR_NO_MEMORY;
    long cols = 0;
    for (long v = 0; v < P->nv; v++) {
        colbase[v] = -1;
        if (!P->vfixed[v] && P->vkept[v]) {
            colbase[v] = cols;
            cols += P->vkind[v] == 0 ? 6 : 3;
        }
    }
    memset(R, 0, sizeof(double) * (size_t)(m * cols));
    for (long p = kp; p < S->ns; p++) {
        int dp = S->dim[p];
        const double *D = S->val + S->doff[p];
        long cb = colbase[S->var_at[p]];
        const int *ap = S->act + 6 * p;
        for (int b = 0; b < dp; b++) {
            long row = S->soff[p] + b - s0;
            d[row] = S->dead[S->soff[p] + b] ? 0.0 : S->y[S->soff[p] + b];
            if (S->dead[S->soff[p] + b]) continue;
            for (int a = b; a < dp; a++) R[row * cols + cb + ap[a]] = D[a * dp + b];
            for (long q = S->cptr[p]; q < S->cptr[p + 1]; q++) {
                int u = S->crow[q], du = S->dim[u];
                const double *L = S->val + S->boff[q];
                long cu = colbase[S->var_at[u]];
                const int *au = S->act + 6 * u;
                for (int a = 0; a < du; a++) R[row * cols + cu + au[a]] = L[a * dp + b];
            }
        }
    }
    free(colbase);
    return MR_OK;
}

/* ------------------------------------------------------------------ the generator */

static inline uint64_t mix64(uint64_t z) {
    z += 0x9E3779B97F4A7C15ULL;
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ULL;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBULL;
    return z ^ (z >> 31);
}

/* log x for a normal x > 0: the exponent from the bits, log of the mantissa m in
 * [sqrt(1/2), sqrt(2)) as 2 atanh(s) = 2 (s + s^3/3 + ... + s^23/23), s = (m - 1)/(m + 1),
 * |s| <= 0.1716 (truncation below 2e-18). */
static double mr_log(double x) {
    uint64_t b;
    memcpy(&b, &x, sizeof b);
    int e = (int)((b >> 52) & 0x7ff) - 1023;
    b = (b & 0x000fffffffffffffULL) | 0x3ff0000000000000ULL;
    double m;
    memcpy(&m, &b, sizeof m);
    if (m > 1.4142135623730951) {
        m = m * 0.5;
        e += 1;
    }
    double s = (m - 1.0) / (m + 1.0), s2 = s * s;
    static const double inv_odd[12] = {1.0, 1.0 / 3.0, 1.0 / 5.0, 1.0 / 7.0, 1.0 / 9.0,
                                       1.0 / 11.0, 1.0 / 13.0, 1.0 / 15.0, 1.0 / 17.0,
                                       1.0 / 19.0, 1.0 / 21.0, 1.0 / 23.0};
    double t = inv_odd[11];
    for (int k = 10; k >= 0; k--) t = t * s2 + inv_odd[k];
    return (double)e * LN2 + 2.0 * (s * t);
}

/* The standard normal number `counter` of stream `key`. */
static double normal_at(uint64_t key, uint64_t counter) {
    uint64_t base = mix64(key ^ mix64(counter));
    for (uint64_t a = 0; a < 64; a++) {
        uint64_t h1 = mix64(base + 2 * a), h2 = mix64(base + 2 * a + 1);
        double u = (double)(h1 >> 11) * 0x1.0p-52 - 1.0;
        double v = (double)(h2 >> 11) * 0x1.0p-52 - 1.0;
        double s = u * u + v * v;
        if (s > 0.0 && s < 1.0) return u * sqrt(-2.0 * mr_log(s) / s);
    }
    return 0.0;
}

/* n normals of stream key from counter c0 (tests compare their moments with N(0, 1)). */
void mr_normals(uint64_t key, uint64_t c0, long n, double *out) {
    for (long i = 0; i < n; i++) out[i] = normal_at(key, c0 + (uint64_t)i);
}

/* ------------------------------------------------------------------ the redraw */

/* Write chunk columns [i0, i0 + cn) of the kept variables' charts Z (rows: kept scalars,
 * row stride `stride`, column c at Z[row * stride + c]) as edges x (+) delta into out. */
static void write_edges(const mr_problem *P, const mr_state *S, const double *Z, long stride,
                        long i0, long cn, double *out, const int64_t *slot, long n) {
    long kp = S->kept_pos, s0 = S->soff[kp];
    for (long p = kp; p < S->ns; p++) {
        int v = S->var_at[p];
        if (slot[v] < 0) continue;
        double *o = out + slot[v] * 7 * n;
        const double *xh = P->x + 7 * v;
        long k0 = S->soff[p] - s0;
        for (long c = 0; c < cn; c++) {
            double d[6] = {0, 0, 0, 0, 0, 0};
            for (int a = 0; a < S->dim[p]; a++) d[S->act[6 * p + a]] = Z[(k0 + a) * stride + c];
            long i = i0 + c;
            for (int t = 0; t < 3; t++) o[t * n + i] = xh[t] + d[t];
            if (P->vkind[v] == 0) {
                double q[4] = {xh[3], xh[4], xh[5], xh[6]};
                mr_qretract(q, d + 3);
                for (int t = 0; t < 4; t++) o[(3 + t) * n + i] = q[t];
            } else {
                o[3 * n + i] = 1.0;
                o[4 * n + i] = o[5 * n + i] = o[6 * n + i] = 0.0;
            }
        }
    }
}

static uint64_t counter0(const mr_state *S, long p, int a, long n) {
    uint64_t v = (uint64_t)S->var_at[p];
    return (v * 8 + (uint64_t)S->act[6 * p + a]) * (uint64_t)n;
}

/* Z (K x n) <- L^-1 Z with L L^T = Z Z^T / (n - 1): rows whose pivot vanishes (dead or
 * dependent) are zeroed. Afterwards the rows' sample covariance is exactly the identity on
 * the live rows. work: K * K doubles. */
static void whiten_rows(double *Z, long K, long n, const uint8_t *dead, double *L) {
    for (long i = 0; i < K; i++) {
        for (long j = 0; j <= i; j++) {
            double s = 0.0;
            const double *zi = Z + i * n, *zj = Z + j * n;
            for (long c = 0; c < n; c++) s += zi[c] * zj[c];
            L[i * K + j] = s / (double)(n - 1);
        }
    }
    for (long j = 0; j < K; j++) {
        double s = L[j * K + j];
        for (long k = 0; k < j; k++) s -= L[j * K + k] * L[j * K + k];
        if (dead[j] || !(s > 1e-12)) {
            L[j * K + j] = 0.0;
            for (long i = j + 1; i < K; i++) L[i * K + j] = 0.0;
            continue;
        }
        double l = sqrt(s);
        L[j * K + j] = l;
        for (long i = j + 1; i < K; i++) {
            double t = L[i * K + j];
            for (long k = 0; k < j; k++) t -= L[i * K + k] * L[j * K + k];
            L[i * K + j] = t / l;
        }
    }
    for (long i = 0; i < K; i++) {
        double *zi = Z + i * n;
        double l = L[i * K + i];
        if (l == 0.0) {
            for (long c = 0; c < n; c++) zi[c] = 0.0;
            continue;
        }
        for (long k = 0; k < i; k++) {
            double lk = L[i * K + k];
            if (lk == 0.0) continue;
            const double *zk = Z + k * n;
            for (long c = 0; c < n; c++) zi[c] -= lk * zk[c];
        }
        for (long c = 0; c < n; c++) zi[c] = zi[c] / l;
    }
}

/* The spread: every kept position's deviations are multiplied by spread, lowered for a pose
 * whose rotation deviations would then have an RMS above rot_cap (radians, in the chart: the
 * largest over its rotation coordinates; ss[k] holds row k's sum of squares over the n samples),
 * to rot_cap / RMS but never below 1. A pose that uncertain in rotation gets (nearly) the
 * posterior itself: the chart, and the filter's updates after it, degrade at that spread. The
 * factors form a diagonal D, so the covariance D C D stays a covariance. fac: one per kept
 * position. */
static void spread_factors(const mr_problem *P, const mr_state *S, const double *ss, long n,
                           double spread, double rot_cap, double *fac) {
    long kp = S->kept_pos, s0 = S->soff[kp];
    for (long p = kp; p < S->ns; p++) {
        double f = spread, worst = 0.0;
        if (P->vkind[S->var_at[p]] == 0)
            for (int a = 0; a < S->dim[p]; a++)
                if (S->act[6 * p + a] >= 3) {
                    double v = ss[S->soff[p] + a - s0] / (double)n;
                    if (v > worst) worst = v;
                }
        double rms = sqrt(worst);
        if (spread * rms > rot_cap) f = rot_cap / rms;
        fac[p - kp] = f > 1.0 ? f : 1.0;
    }
}

/* Row k's sum of squares of its first cn values (stride ld) added into ss[k]. */
static void add_squares(const double *z, long K, long ld, long cn, double *ss) {
    for (long k = 0; k < K; k++) {
        double t = ss[k];
        for (long c = 0; c < cn; c++) t = t + z[k * ld + c] * z[k * ld + c];
        ss[k] = t;
    }
}

/* The rows of each kept position (each of stride ld, the first cn used) times its factor. */
static void scale(const mr_state *S, double *z, long ld, long cn, const double *fac) {
    long kp = S->kept_pos, s0 = S->soff[kp];
    for (long p = kp; p < S->ns; p++) {
        double f = fac[p - kp];
        if (f == 1.0) continue;
        for (int a = 0; a < S->dim[p]; a++) {
            double *r = z + (S->soff[p] + a - s0) * ld;
            for (long c = 0; c < cn; c++) r[c] = r[c] * f;
        }
    }
}

static int draw(const mr_problem *P, const mr_state *S, double *out, const int64_t *slot,
                long n, uint64_t key, long exact_max, double spread, double rot_cap, double *ss,
                double *fac);

/* After mr_solve: N samples of the kept variables from the Gaussian around the solution with
 * covariance (L_kk L_kk^T)^-1, written as edges (7 rows of n) into out at frame slot[v]
 * (variables with slot < 0 are skipped). Each coordinate's normals are centred on their
 * sample mean, so every edge's mean in the chart is the solution. When the kept dimensions K
 * are fewer than n (and at most exact_max), the normals are also whitened so that their sample
 * covariance is the identity: the samples' covariance is then the posterior's, with no sampling
 * error (second-order exact sampling); otherwise they are independent draws. Every deviation
 * is then multiplied by spread (1: the posterior itself; > 1: a wider ensemble, the policy's
 * allowance for what the model leaves out), capped per pose by rot_cap (spread_factors), one
 * product per value in a fixed order, so the bits stay portable. */
int mr_redraw(const mr_problem *P, double *out, const int64_t *slot, long n, uint64_t key,
              long exact_max, double spread, double rot_cap) {
    const mr_state *S = P->state;
    if (S == NULL || !S->factored || n < 2 || !(spread >= 1.0 && spread <= 4.0) || !(rot_cap > 0.0))
        return MR_BAD_ARGS;
    long kp = S->kept_pos, s0 = S->soff[kp], K = S->nscal - s0;
    int spreading = spread != 1.0;
    double *ss = spreading ? calloc((size_t)(K ? K : 1), sizeof(double)) : NULL;
    double *fac = spreading ? malloc(sizeof(double) * (size_t)(S->ns - kp + 1)) : NULL;
    if (spreading && (ss == NULL || fac == NULL)) {
        free(ss);
        free(fac);
        return MR_NO_MEMORY;
    }
    int rc = draw(P, S, out, slot, n, key, exact_max, spread, rot_cap, ss, fac);
    free(ss);
    free(fac);
    return rc;
}

static int draw(const mr_problem *P, const mr_state *S, double *out, const int64_t *slot,
                long n, uint64_t key, long exact_max, double spread, double rot_cap, double *ss,
                double *fac) {
    long kp = S->kept_pos, s0 = S->soff[kp], K = S->nscal - s0;
    const uint8_t *dead = S->dead + s0;
    int exact = K < n && K <= exact_max;
    if (exact || K * n <= FULL_MAX) {  /* all normals at once (the same bits as in chunks) */
        double *Z = malloc(sizeof(double) * (size_t)(K ? K : 1) * (size_t)n);
        double *L = exact ? malloc(sizeof(double) * (size_t)(K ? K * K : 1)) : NULL;
        if (Z == NULL || (exact && L == NULL)) {
            free(Z);
            free(L);
            return MR_NO_MEMORY;
        }
        for (long p = kp; p < S->ns; p++)
            for (int a = 0; a < S->dim[p]; a++) {
                uint64_t c0 = counter0(S, p, a, n);
                double *z = Z + (S->soff[p] + a - s0) * n, m = 0.0;
                for (long i = 0; i < n; i++) {
                    z[i] = normal_at(key, c0 + (uint64_t)i);
                    m += z[i];
                }
                m = m / (double)n;
                for (long i = 0; i < n; i++) z[i] = z[i] - m;
            }
        if (exact) whiten_rows(Z, K, n, dead, L);
        free(L);
        mr_backward(S, Z, kp, n, n);
        if (fac != NULL) {
            add_squares(Z, K, n, n, ss);
            spread_factors(P, S, ss, n, spread, rot_cap, fac);
            scale(S, Z, n, n, fac);
        }
        write_edges(P, S, Z, n, 0, n, out, slot, n);
        free(Z);
        return MR_OK;
    }
    double *zbar = malloc(sizeof(double) * (size_t)(K ? K : 1));
    double *Z = malloc(sizeof(double) * (size_t)(K ? K : 1) * CHUNK);
    if (zbar == NULL || Z == NULL) {
        free(zbar);
        free(Z);
        return MR_NO_MEMORY;
    }
    for (long p = kp; p < S->ns; p++)
        for (int a = 0; a < S->dim[p]; a++) {
            uint64_t c0 = counter0(S, p, a, n);
            double s = 0.0;
            for (long i = 0; i < n; i++) s += normal_at(key, c0 + (uint64_t)i);
            zbar[S->soff[p] + a - s0] = s / (double)n;
        }
    /* with a spread, a first pass over the chunks sums the squares the factors need */
    for (int pass = fac != NULL ? 0 : 1; pass < 2; pass++) {
        for (long i0 = 0; i0 < n; i0 += CHUNK) {
            long cn = n - i0 < CHUNK ? n - i0 : CHUNK;
            for (long p = kp; p < S->ns; p++)
                for (int a = 0; a < S->dim[p]; a++) {
                    uint64_t c0 = counter0(S, p, a, n) + (uint64_t)i0;
                    long k = S->soff[p] + a - s0;
                    for (long c = 0; c < cn; c++)
                        Z[k * CHUNK + c] = normal_at(key, c0 + (uint64_t)c) - zbar[k];
                }
            mr_backward(S, Z, kp, CHUNK, cn);
            if (pass == 0) {
                add_squares(Z, K, CHUNK, cn, ss);
                continue;
            }
            if (fac != NULL) scale(S, Z, CHUNK, cn, fac);
            write_edges(P, S, Z, CHUNK, i0, cn, out, slot, n);
        }
        if (pass == 0) spread_factors(P, S, ss, n, spread, rot_cap, fac);
    }
    free(zbar);
    free(Z);
    return MR_OK;
}
