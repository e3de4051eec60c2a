/* mcsm's compiled kernel: every computation that changes map state, in a fixed order of
 * operations.
 *
 * Portability rules (README "Portable arithmetic"): only IEEE-754 +, -, *, / and sqrt, which
 * give the same bits on every x86-64 and aarch64 CPU; no libm transcendental function; no
 * fast-math; compiled with -ffp-contract=off so that no multiply-add is fused. Every sum over
 * samples runs in four lanes (sample i goes to lane i mod 4) combined as (l0 + l1) + (l2 + l3),
 * then the tail in order: the same order whatever the SIMD width the compiler picks. Each frame
 * is computed by one call on one thread, whatever the frame ranges given to threads.
 *
 * Layout: an AT is stored as 7 rows of N samples ("rows": x, y, z, qw, qx, qy, qz, each
 * contiguous); a component is a contiguous block of frames, frame f at f * 7 * N. The API's
 * (N, 7) arrays are transposed into rows by the Python side (an exact copy).
 *
 * Return codes: 0 ok; MK_NONFINITE_GAIN; MK_BAD_QUATERNION; MK_NONFINITE; MK_BAD_ARGS.
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

/* the shared per-sample functions on four samples at a time (kernel_common.h: mk_lane) */
#define MK_LANE_VECTOR
#include "kernel_common.h"

typedef mk_lane v4;

static inline v4 ld4(const double *p) { return mk_lane_load(p); }
static inline double hsum(v4 v) { return mk_lanes(v[0], v[1], v[2], v[3]); }
static inline v4 splat(double x) { return mk_lane_splat(x); }

int mk_version(void) { return 3; }

/* 1 if this CPU runs the AVX2 build of this same source (same bits, about 7x faster: the
 * four lanes become one register); the baseline build answers. */
int mk_cpu_has_avx2(void) {
#if defined(__x86_64__) || defined(__i386__)
    __builtin_cpu_init();
    return __builtin_cpu_supports("avx2") ? 1 : 0;
#else
    return 0;
#endif
}

/* ------------------------------------------------------------------ row reductions */

static double row_sum(const double *x, long n) {
    v4 a = splat(0.0);
    long i = 0;
    for (; i + 4 <= n; i += 4) a += ld4(x + i);
    double s = hsum(a);
    for (; i < n; i++) s += x[i];
    return s;
}

static double row_dot(const double *x, const double *y, long n) {
    v4 a = splat(0.0);
    long i = 0;
    for (; i + 4 <= n; i += 4) a += ld4(x + i) * ld4(y + i);
    double s = hsum(a);
    for (; i < n; i++) s += x[i] * y[i];
    return s;
}

/* ------------------------------------------------------------------ per-sample algebra */

/* The per-sample functions (mk_qmul, mk_qrot, mk_compound_sample, ...) are in
 * kernel_common.h, shared with the device kernel. */
#define qmul1 mk_qmul
#define qrot1 mk_qrot

/* o = a (+) b, rows; o may not alias a or b */
void mk_compound(const double *a, const double *b, double *o, long n) {
    for (long i = 0; i < n; i++) {
        double as[7], bs[7], os[7];
        for (int d = 0; d < 7; d++) {
            as[d] = a[d * n + i];
            bs[d] = b[d * n + i];
        }
        mk_compound_sample(as, bs, os);
        for (int d = 0; d < 7; d++) o[d * n + i] = os[d];
    }
}

/* o = a^R: q' = q*, t' = -R(q*) t */
void mk_invert(const double *a, double *o, long n) {
    for (long i = 0; i < n; i++) {
        double t[3];
        double w = a[3 * n + i], x = -a[4 * n + i], y = -a[5 * n + i], z = -a[6 * n + i];
        qrot1(w, x, y, z, a[i], a[n + i], a[2 * n + i], t);
        o[i] = -t[0];
        o[n + i] = -t[1];
        o[2 * n + i] = -t[2];
        o[3 * n + i] = w;
        o[4 * n + i] = x;
        o[5 * n + i] = y;
        o[6 * n + i] = z;
    }
}

/* o = a^R (+) b (the query r->a, r->b gives a->b); o in rows */
void mk_relative(const double *a, const double *b, double *o, long n) {
    for (long i = 0; i < n; i++) {
        double t[3], q[4];
        double w = a[3 * n + i], x = -a[4 * n + i], y = -a[5 * n + i], z = -a[6 * n + i];
        qrot1(w, x, y, z, b[i] - a[i], b[n + i] - a[n + i], b[2 * n + i] - a[2 * n + i], t);
        o[i] = t[0];
        o[n + i] = t[1];
        o[2 * n + i] = t[2];
        qmul1(w, x, y, z, b[3 * n + i], b[4 * n + i], b[5 * n + i], b[6 * n + i], q);
        o[3 * n + i] = q[0];
        o[4 * n + i] = q[1];
        o[5 * n + i] = q[2];
        o[6 * n + i] = q[3];
    }
}

/* o = a^R (+) b written as (N, 7) (the API's layout: a query's answer): computed on blocks of
 * rows (vectorised), then interleaved. Same arithmetic as mk_relative. */
void mk_relative_nm7(const double *a, const double *b, double *o, long n) {
    enum { B = 256 };
    double r[7][B];
    for (long lo = 0; lo < n; lo += B) {
        long m = n - lo < B ? n - lo : B;
        const double *a0 = a + lo, *b0 = b + lo;
        for (long j = 0; j < m; j++) {
            double w = a0[3 * n + j], x = -a0[4 * n + j], y = -a0[5 * n + j],
                   z = -a0[6 * n + j];
            double vx = b0[j] - a0[j], vy = b0[n + j] - a0[n + j],
                   vz = b0[2 * n + j] - a0[2 * n + j];
            double tx = 2.0 * (y * vz - z * vy);
            double ty = 2.0 * (z * vx - x * vz);
            double tz = 2.0 * (x * vy - y * vx);
            r[0][j] = vx + w * tx + (y * tz - z * ty);
            r[1][j] = vy + w * ty + (z * tx - x * tz);
            r[2][j] = vz + w * tz + (x * ty - y * tx);
            double qw = b0[3 * n + j], qx = b0[4 * n + j], qy = b0[5 * n + j],
                   qz = b0[6 * n + j];
            r[3][j] = w * qw - x * qx - y * qy - z * qz;
            r[4][j] = w * qx + x * qw + y * qz - z * qy;
            r[5][j] = w * qy - x * qz + y * qw + z * qx;
            r[6][j] = w * qz + x * qy - y * qx + z * qw;
        }
        double *out = o + 7 * lo;
        for (long j = 0; j < m; j++)
            for (int k = 0; k < 7; k++) out[7 * j + k] = r[k][j];
    }
}

/* the point edge of a point p (3 rows) seen from r->a: t = t_a + R(q_a) p, q = 1 */
void mk_point_edge(const double *a, const double *p, double *o, long n) {
    for (long i = 0; i < n; i++) {
        double t[3];
        qrot1(a[3 * n + i], a[4 * n + i], a[5 * n + i], a[6 * n + i], p[i], p[n + i],
              p[2 * n + i], t);
        o[i] = a[i] + t[0];
        o[n + i] = a[n + i] + t[1];
        o[2 * n + i] = a[2 * n + i] + t[2];
        o[3 * n + i] = 1.0;
        o[4 * n + i] = 0.0;
        o[5 * n + i] = 0.0;
        o[6 * n + i] = 0.0;
    }
}

/* Unit quaternion rows q (4 rows of n, stride n between rows): scale to unit norm. */
static void normalize_q(double *q, long n) {
    for (long i = 0; i < n; i++) {
        double s[4] = {q[i], q[n + i], q[2 * n + i], q[3 * n + i]};
        mk_normalize_sample(s);
        for (int k = 0; k < 4; k++) q[k * n + i] = s[k];
    }
}

/* Chordal mean of quaternion rows q (4 x n): samples aligned to the first sample's hemisphere,
 * summed in four lanes, divided by n, normalised (kernel_common.h: mk_meanrot_*). */
static void mean_rotation(const double *q, long n, double *m) {
    double r[4] = {q[0], q[n], q[2 * n], q[3 * n]};
    v4 acc[4] = {splat(0.0), splat(0.0), splat(0.0), splat(0.0)};
    long i = 0;
    for (; i + 4 <= n; i += 4) {
        v4 a = ld4(q + i), b = ld4(q + n + i), c = ld4(q + 2 * n + i), d = ld4(q + 3 * n + i);
        v4 dot = MK_QDOT(a, b, c, d, r[0], r[1], r[2], r[3]);
        v4 s;
        for (int l = 0; l < 4; l++) s[l] = mk_sign(dot[l]);
        acc[0] += a * s;
        acc[1] += b * s;
        acc[2] += c * s;
        acc[3] += d * s;
    }
    double sum[4];
    for (int k = 0; k < 4; k++) sum[k] = hsum(acc[k]);
    for (; i < n; i++) mk_meanrot_add(sum, q[i], q[n + i], q[2 * n + i], q[3 * n + i], r);
    mk_meanrot_finish(sum, n, m);
}

/* Put every sample of one AT (rows, in place) on the hemisphere of its mean rotation, after
 * renormalising the quaternions if `normalize`. */
void mk_canonicalize(double *x, long n, int normalize) {
    double *q = x + 3 * n;
    if (normalize) normalize_q(q, n);
    double m[4];
    mean_rotation(q, n, m);
    for (long i = 0; i < n; i++) {
        double s[4] = {q[i], q[n + i], q[2 * n + i], q[3 * n + i]};
        mk_flip_sample(s, m);
        for (int k = 0; k < 4; k++) q[k * n + i] = s[k];
    }
}

static void set_identity(double *o, long n) {
    memset(o, 0, sizeof(double) * 7 * n);
    for (long i = 0; i < n; i++) o[3 * n + i] = 1.0;
}

static void pin_point(double *o, long n) {
    for (long i = 0; i < n; i++) {
        double s[4];
        mk_pin_sample(s);
        for (int k = 0; k < 4; k++) o[(3 + k) * n + i] = s[k];
    }
}

static int all_finite(const double *x, long len) {
    int ok = 1;
    for (long i = 0; i < len; i++) ok &= mk_finite(x[i]);
    return ok;
}

/* Frames lo..hi-1 of a component (blocks of 7 n): out_f = pre (+) in_f, canonicalised; a frame
 * with point[f] gets identity quaternions (and is not canonicalised). `pre` is rows of one AT.
 * Used by joins (the moved component) and re-rooting. Returns MK_NONFINITE on a non-finite
 * result. */
int mk_transform_frames(const double *pre, const double *in, double *out, const uint8_t *point,
                        long lo, long hi, long n) {
    for (long f = lo; f < hi; f++) {
        const double *e = in + f * 7 * n;
        double *o = out + f * 7 * n;
        mk_compound(pre, e, o, n);
        if (point[f]) pin_point(o, n);
        else mk_canonicalize(o, n, 1);
        if (!all_finite(o, 7 * n)) return MK_NONFINITE;
    }
    return MK_OK;
}

/* Frames lo..hi-1 canonicalised in place (points pinned instead); MK_NONFINITE if any value is
 * not finite afterwards. Used by submap imports. */
int mk_canonicalize_frames(double *frames, const uint8_t *point, long lo, long hi, long n,
                           int normalize) {
    for (long f = lo; f < hi; f++) {
        double *o = frames + f * 7 * n;
        if (point[f]) pin_point(o, n);
        else mk_canonicalize(o, n, normalize);
        if (!all_finite(o, 7 * n)) return MK_NONFINITE;
    }
    return MK_OK;
}

/* ------------------------------------------------------------------ small dense algebra */

/* Symmetric eigen-decomposition of a (m x m, row-major; destroyed) by cyclic Jacobi: sweeps
 * over (p, q) in row order, a fixed rotation formula, and a fixed stopping rule (an exactly
 * zero off-diagonal, or 60 sweeps). lam ascending (ties keep index order), v columns. */
static void jacobi_eigh(double *a, int m, double *lam, double *v) {
    double vv[MAXD * MAXD];
    for (int i = 0; i < m; i++)
        for (int j = 0; j < m; j++) vv[i * m + j] = (i == j) ? 1.0 : 0.0;
    double d[MAXD], b[MAXD], z[MAXD];
    for (int i = 0; i < m; i++) { d[i] = a[i * m + i]; b[i] = d[i]; z[i] = 0.0; }
    for (int sweep = 0; sweep < 60; sweep++) {
        double off = 0.0;
        for (int p = 0; p < m - 1; p++)
            for (int q = p + 1; q < m; q++) off += fabs(a[p * m + q]);
        if (off == 0.0) break;
        double thresh = sweep < 3 ? 0.2 * off / (double)(m * m) : 0.0;
        for (int p = 0; p < m - 1; p++) {
            for (int q = p + 1; q < m; q++) {
                double apq = a[p * m + q];
                double g = 100.0 * fabs(apq);
                if (sweep > 3 && fabs(d[p]) + g == fabs(d[p]) && fabs(d[q]) + g == fabs(d[q])) {
                    a[p * m + q] = 0.0;
                    continue;
                }
                if (fabs(apq) <= thresh) continue;
                double h = d[q] - d[p];
                double t;
                if (fabs(h) + g == fabs(h)) {
                    t = apq / h;
                } else {
                    double theta = 0.5 * h / apq;
                    t = 1.0 / (fabs(theta) + sqrt(1.0 + theta * theta));
                    if (theta < 0.0) t = -t;
                }
                double c = 1.0 / sqrt(1.0 + t * t), s = t * c, tau = s / (1.0 + c);
                h = t * apq;
                z[p] -= h; z[q] += h; d[p] -= h; d[q] += h;
                a[p * m + q] = 0.0;
                for (int j = 0; j < p; j++) {
                    double g1 = a[j * m + p], h1 = a[j * m + q];
                    a[j * m + p] = g1 - s * (h1 + g1 * tau);
                    a[j * m + q] = h1 + s * (g1 - h1 * tau);
                }
                for (int j = p + 1; j < q; j++) {
                    double g1 = a[p * m + j], h1 = a[j * m + q];
                    a[p * m + j] = g1 - s * (h1 + g1 * tau);
                    a[j * m + q] = h1 + s * (g1 - h1 * tau);
                }
                for (int j = q + 1; j < m; j++) {
                    double g1 = a[p * m + j], h1 = a[q * m + j];
                    a[p * m + j] = g1 - s * (h1 + g1 * tau);
                    a[q * m + j] = h1 + s * (g1 - h1 * tau);
                }
                for (int j = 0; j < m; j++) {
                    double g1 = vv[j * m + p], h1 = vv[j * m + q];
                    vv[j * m + p] = g1 - s * (h1 + g1 * tau);
                    vv[j * m + q] = h1 + s * (g1 - h1 * tau);
                }
            }
        }
        for (int p = 0; p < m; p++) { b[p] += z[p]; d[p] = b[p]; z[p] = 0.0; }
    }
    /* ascending, stable */
    int idx[MAXD];
    for (int i = 0; i < m; i++) idx[i] = i;
    for (int i = 1; i < m; i++) {
        int k = idx[i], j = i - 1;
        while (j >= 0 && d[idx[j]] > d[k]) { idx[j + 1] = idx[j]; j--; }
        idx[j + 1] = k;
    }
    for (int i = 0; i < m; i++) {
        lam[i] = d[idx[i]];
        for (int j = 0; j < m; j++) v[j * m + i] = vv[j * m + idx[i]];
    }
}

/* D s D with D = diag(1/sqrt(diag s)) (0 for dead dimensions), decomposed; eigenvalues below
 * RTOL x the largest magnitude set to 0 (mcsm.core.at.scaled_eigh). */
static void scaled_eigh(const double *s, int m, double *dsc, double *lam, double *v) {
    double a[MAXD * MAXD];
    for (int i = 0; i < m; i++) {
        double di = s[i * m + i];
        dsc[i] = di > ZERO_VARIANCE ? 1.0 / sqrt(di) : 0.0;
    }
    for (int i = 0; i < m; i++)
        for (int j = 0; j < m; j++) {
            double x = s[i * m + j] * dsc[i] * dsc[j];
            double y = s[j * m + i] * dsc[j] * dsc[i];
            a[i * m + j] = 0.5 * (x + y);
        }
    jacobi_eigh(a, m, lam, v);
    double big = 0.0;
    for (int i = 0; i < m; i++) big = fabs(lam[i]) > big ? fabs(lam[i]) : big;
    double cut = RTOL * big;
    for (int i = 0; i < m; i++) lam[i] = lam[i] > cut ? lam[i] : 0.0;
}

/* o = V diag(f) V^T (m x m) */
static void vfv(const double *v, const double *f, int m, double *o) {
    for (int i = 0; i < m; i++)
        for (int j = 0; j < m; j++) {
            double acc = 0.0;
            for (int k = 0; k < m; k++) acc += v[i * m + k] * f[k] * v[j * m + k];
            o[i * m + j] = acc;
        }
}

static void matmul(const double *a, const double *b, int r, int k, int c, double *o) {
    for (int i = 0; i < r; i++)
        for (int j = 0; j < c; j++) {
            double acc = 0.0;
            for (int l = 0; l < k; l++) acc += a[i * k + l] * b[l * c + j];
            o[i * c + j] = acc;
        }
}

/* Sample covariance (p x p) of rows x (p rows of n), each row centred first. */
static void row_cov(const double *x, int p, long n, double *mean, double *cov, double *tmp) {
    for (int k = 0; k < p; k++) {
        mean[k] = row_sum(x + k * n, n) / (double)n;
        for (long i = 0; i < n; i++) tmp[k * n + i] = x[k * n + i] - mean[k];
    }
    for (int a = 0; a < p; a++)
        for (int b = a; b < p; b++) {
            double c = row_dot(tmp + a * n, tmp + b * n, n) / (double)(n - 1);
            cov[a * p + b] = c;
            cov[b * p + a] = c;
        }
}

/* ------------------------------------------------------------------ the joint update */

/* Predict the observation per sample and express both in the update's vector space.
 * e_a, e_b: rows of the endpoint edges r->a, r->b; x: the observation, 7 rows (an AT) or 3
 * rows (a point). space: 0 tangent ([t, 2 vec(q_ref^-1 q)], 6-D), 1 quaternion (7-D). Writes
 * y (p rows) and z (p rows); returns p. h = (r->a)^R (+) (r->b); q_ref its mean rotation. */
static int predict(const double *e_a, const double *e_b, const double *x, long n, int point,
                   int space, double *y, double *z, double *h) {
    if (point) {
        for (long i = 0; i < n; i++) {
            double t[3];
            qrot1(e_a[3 * n + i], -e_a[4 * n + i], -e_a[5 * n + i], -e_a[6 * n + i],
                  e_b[i] - e_a[i], e_b[n + i] - e_a[n + i], e_b[2 * n + i] - e_a[2 * n + i], t);
            y[i] = t[0];
            y[n + i] = t[1];
            y[2 * n + i] = t[2];
        }
        memcpy(z, x, sizeof(double) * 3 * n);
        return 3;
    }
    mk_relative(e_a, e_b, h, n);
    double m[4];
    mean_rotation(h + 3 * n, n, m);
    /* The prediction's samples go on the hemisphere of its own mean m (each sample's sign by
     * its own relative rotation). The observation's samples are first put on the hemisphere
     * of the observation's own mean rotation mx, then all on the side where mx is closest to
     * m: an observation half a turn from the prediction keeps its samples together (its mean
     * stays half a turn away) instead of splitting into two opposite halves. */
    double mx[4];
    mean_rotation(x + 3 * n, n, mx);
    double gsign;
    if (space == 1) {
        gsign = (mx[0] * m[0] + mx[1] * m[1] + mx[2] * m[2] + mx[3] * m[3]) < 0.0 ? -1.0 : 1.0;
    } else {
        double r[4];
        qmul1(m[0], -m[1], -m[2], -m[3], mx[0], mx[1], mx[2], mx[3], r);
        gsign = r[0] < 0.0 ? -1.0 : 1.0;
    }
    const double *srcs[2] = {h, x};
    double *dsts[2] = {y, z};
    for (int s = 0; s < 2; s++) {
        const double *src = srcs[s];
        double *dst = dsts[s];
        memcpy(dst, src, sizeof(double) * 3 * n);
        for (long i = 0; i < n; i++) {
            double qw = src[3 * n + i], qx = src[4 * n + i], qy = src[5 * n + i],
                   qz = src[6 * n + i];
            double sx = 1.0;
            if (s == 1) {
                double dx = qw * mx[0] + qx * mx[1] + qy * mx[2] + qz * mx[3];
                sx = (dx < 0.0 ? -1.0 : 1.0) * gsign;
            }
            if (space == 1) {
                double sg = sx;
                if (s == 0) {
                    double dot = qw * m[0] + qx * m[1] + qy * m[2] + qz * m[3];
                    sg = dot < 0.0 ? -1.0 : 1.0;
                }
                dst[3 * n + i] = qw * sg;
                dst[4 * n + i] = qx * sg;
                dst[5 * n + i] = qy * sg;
                dst[6 * n + i] = qz * sg;
            } else {
                double r[4];
                qmul1(m[0], -m[1], -m[2], -m[3], qw, qx, qy, qz, r);
                double sg = s == 0 ? (r[0] < 0.0 ? -1.0 : 1.0) : sx;
                dst[3 * n + i] = 2.0 * (r[1] * sg);
                dst[4 * n + i] = 2.0 * (r[2] * sg);
                dst[5 * n + i] = 2.0 * (r[3] * sg);
            }
        }
    }
    return space == 1 ? 7 : 6;
}

/* Everything of a loop closure that is O(N) and independent of the other frames:
 * prediction, analysis weights, the normalised innovation squared.
 *
 * rule: 0 ensrf, 1 denkf, 2 enkf. Outputs: yc (p rows, centred prediction), w (p rows, the
 * per-sample weights), stats[0] = NIS (sum over live dimensions of S = C_yy + R), stats[1] =
 * live dimensions (dof), stats[2] = sum of each yc row (p values from stats[3])... see below.
 * info layout: info[0] p, info[1] nis, info[2] dof, info[3..3+p) var_y, info[3+p..3+2p) row
 * sums of yc, info[3+2p..3+3p) mean of w. work: at least 3 * 7 * n doubles. */
int mk_analysis(const double *e_a, const double *e_b, const double *x, long n, int point,
                int space, int rule, double *yc, double *w, double *info, double *work) {
    double *y = yc, *z = work, *h = work + 7 * n, *zc = work + 14 * n;
    int p = predict(e_a, e_b, x, n, point, space, y, z, h);
    double y_mean[MAXP], z_mean[MAXP], r[MAXP * MAXP], cyy[MAXP * MAXP], s[MAXP * MAXP];
    for (int k = 0; k < p; k++) {
        y_mean[k] = row_sum(y + k * n, n) / (double)n;
        for (long i = 0; i < n; i++) yc[k * n + i] = y[k * n + i] - y_mean[k];
    }
    row_cov(z, p, n, z_mean, r, zc);
    for (int a = 0; a < p; a++)
        for (int b = a; b < p; b++) {
            double c = row_dot(yc + a * n, yc + b * n, n) / (double)(n - 1);
            cyy[a * p + b] = c;
            cyy[b * p + a] = c;
        }
    for (int i = 0; i < p * p; i++) s[i] = cyy[i] + r[i];
    double dsc[MAXP], lam[MAXP], v[MAXP * MAXP];
    scaled_eigh(s, p, dsc, lam, v);
    double inv[MAXP], isq[MAXP], sq[MAXP];
    for (int k = 0; k < p; k++) {
        int live = lam[k] > 0.0;
        inv[k] = live ? 1.0 / lam[k] : 0.0;
        isq[k] = live ? 1.0 / sqrt(lam[k]) : 0.0;
        sq[k] = live ? sqrt(lam[k]) : 0.0;
    }
    double spinv[MAXP * MAXP];
    vfv(v, inv, p, spinv);
    for (int a = 0; a < p; a++)
        for (int b = 0; b < p; b++) spinv[a * p + b] = spinv[a * p + b] * dsc[a] * dsc[b];
    double innov[MAXP];
    for (int k = 0; k < p; k++) innov[k] = z_mean[k] - y_mean[k];
    /* a = S+ (z_mean - y_mean) */
    double amean[MAXP];
    for (int a = 0; a < p; a++) {
        double acc = 0.0;
        for (int b = 0; b < p; b++) acc += innov[b] * spinv[b * p + a];
        amean[a] = acc;
    }
    /* NIS: over the live dimensions of S; in quaternion space first projected onto the
     * tangent plane at the mean rotation (a unit quaternion has 3 dof, not 4). */
    {
        double ss[MAXP * MAXP], iv[MAXP];
        const double *sp = s;
        for (int k = 0; k < p; k++) iv[k] = innov[k];
        if (p == 7) {
            double qb[4], nq = 0.0;
            for (int k = 0; k < 4; k++) nq += y_mean[3 + k] * y_mean[3 + k];
            nq = sqrt(nq);
            for (int k = 0; k < 4; k++) qb[k] = y_mean[3 + k] / nq;
            /* P = I - e e^T on the quaternion block (e = qb): S' = P S P, innov' = P innov */
            double pm[MAXP * MAXP];
            for (int a = 0; a < 7; a++)
                for (int b = 0; b < 7; b++) {
                    double e = (a == b) ? 1.0 : 0.0;
                    if (a >= 3 && b >= 3) e -= qb[a - 3] * qb[b - 3];
                    pm[a * 7 + b] = e;
                }
            double t1[MAXP * MAXP];
            matmul(pm, s, 7, 7, 7, t1);
            matmul(t1, pm, 7, 7, 7, ss);
            double dot = 0.0;
            for (int k = 0; k < 4; k++) dot += innov[3 + k] * qb[k];
            for (int k = 0; k < 4; k++) iv[3 + k] = innov[3 + k] - dot * qb[k];
            sp = ss;
        }
        double d2[MAXP], l2[MAXP], v2[MAXP * MAXP];
        scaled_eigh(sp, p, d2, l2, v2);
        double nis = 0.0;
        int dof = 0;
        for (int k = 0; k < p; k++) {
            if (!(l2[k] > 0.0)) continue;
            double u = 0.0;
            for (int j = 0; j < p; j++) u += v2[j * p + k] * (iv[j] * d2[j]);
            nis += u * u / l2[k];
            dof++;
        }
        info[1] = nis;
        info[2] = (double)dof;
    }
    double g[MAXP * MAXP];  /* w_i = amean - G yc_i (ensrf, denkf); enkf separately */
    if (rule == 0) {
        double ssqrt[MAXP * MAXP], sisq[MAXP * MAXP], rs[MAXP * MAXP];
        vfv(v, sq, p, ssqrt);
        vfv(v, isq, p, sisq);
        for (int a = 0; a < p; a++)
            for (int b = 0; b < p; b++) rs[a * p + b] = r[a * p + b] * dsc[a] * dsc[b];
        /* sym_sqrt of the scaled R: eigen, clip negatives, sqrt */
        double rsym[MAXP * MAXP], lr[MAXP], vr[MAXP * MAXP], fr[MAXP], rsq[MAXP * MAXP];
        for (int a = 0; a < p; a++)
            for (int b = 0; b < p; b++) rsym[a * p + b] = 0.5 * (rs[a * p + b] + rs[b * p + a]);
        jacobi_eigh(rsym, p, lr, vr);
        for (int k = 0; k < p; k++) fr[k] = lr[k] > 0.0 ? sqrt(lr[k]) : 0.0;
        vfv(vr, fr, p, rsq);
        /* pinv (hermitian, rcond 1e-12) of ssqrt + rsq */
        double sum[MAXP * MAXP], ls[MAXP], vs[MAXP * MAXP], fs[MAXP], pinv[MAXP * MAXP];
        for (int a = 0; a < p; a++)
            for (int b = 0; b < p; b++)
                sum[a * p + b] = 0.5 * ((ssqrt[a * p + b] + rsq[a * p + b]) +
                                        (ssqrt[b * p + a] + rsq[b * p + a]));
        jacobi_eigh(sum, p, ls, vs);
        double big = 0.0;
        for (int k = 0; k < p; k++) big = fabs(ls[k]) > big ? fabs(ls[k]) : big;
        for (int k = 0; k < p; k++) fs[k] = fabs(ls[k]) > 1e-12 * big ? 1.0 / ls[k] : 0.0;
        vfv(vs, fs, p, pinv);
        double dd[MAXP * MAXP];
        matmul(sisq, pinv, p, p, p, dd);
        for (int a = 0; a < p; a++)
            for (int b = 0; b < p; b++) g[a * p + b] = dd[a * p + b] * dsc[a] * dsc[b];
    } else if (rule == 1) {
        for (int i = 0; i < p * p; i++) g[i] = 0.5 * spinv[i];
    }
    if (rule == 0 || rule == 1) {
        /* w_i[a] = amean[a] - sum_b yc_i[b] G[a][b] */
        for (int a = 0; a < p; a++) {
            double *wa = w + a * n;
            for (long i = 0; i < n; i++) wa[i] = amean[a];
            for (int b = 0; b < p; b++) {
                double gab = g[a * p + b];
                const double *yb = yc + b * n;
                for (long i = 0; i < n; i++) wa[i] = wa[i] - yb[i] * gab;
            }
        }
    } else {
        /* enkf: w_i = S+ (z_i - y_i) with y_i = yc_i + y_mean */
        for (int a = 0; a < p; a++) {
            double *wa = w + a * n;
            for (long i = 0; i < n; i++) wa[i] = 0.0;
            for (int b = 0; b < p; b++) {
                double sab = spinv[b * p + a];
                const double *zb = z + b * n, *yb = yc + b * n;
                for (long i = 0; i < n; i++) wa[i] = wa[i] + (zb[i] - (yb[i] + y_mean[b])) * sab;
            }
        }
    }
    if (!all_finite(w, p * n)) return MK_NONFINITE_GAIN;
    info[0] = (double)p;
    for (int k = 0; k < p; k++) {
        info[3 + k] = row_dot(yc + k * n, yc + k * n, n) / (double)(n - 1);
        info[3 + p + k] = row_sum(yc + k * n, n);
        info[3 + 2 * p + k] = row_sum(w + k * n, n) / (double)n;
    }
    double wmax = 0.0;
    for (long i = 0; i < p * n; i++) wmax = fabs(w[i]) > wmax ? fabs(w[i]) : wmax;
    info[3 + 3 * p] = wmax;
    return MK_OK;
}

/* The endpoint components (gain="endpoints"): principal components of the endpoint edges'
 * coordinates v = [tangent(e_a), tangent(e_b) or t_b] (mcsm.core.analysis.endpoint_components),
 * their variances and their shrunk cross-covariances with the prediction.
 * Writes pcs (K rows of n), lam (K), cpy (K x p), sum_pc (K row sums); returns K (0 if nothing varies) or -1.
 * work: 12 n doubles. */
int mk_endpoint_prep(const double *e_a, const double *e_b, long n, int point, const double *yc,
                     int p, const double *var_y, double shrink, double *pcs, double *lam_out,
                     double *cpy, double *sum_pc, double *work) {
    double *vrows = work;  /* up to 12 rows */
    int L = 0;
    const double *edges[2] = {e_a, e_b};
    for (int s = 0; s < 2; s++) {
        const double *e = edges[s];
        memcpy(vrows + L * n, e, sizeof(double) * 3 * n);
        L += 3;
        if (s == 1 && point) break;
        double m[4];
        mean_rotation(e + 3 * n, n, m);
        for (long i = 0; i < n; i++) {
            double r[4];
            qmul1(m[0], -m[1], -m[2], -m[3], e[3 * n + i], e[4 * n + i], e[5 * n + i],
                  e[6 * n + i], r);
            double sg = r[0] < 0.0 ? -1.0 : 1.0;
            vrows[(L + 0) * n + i] = 2.0 * (r[1] * sg);
            vrows[(L + 1) * n + i] = 2.0 * (r[2] * sg);
            vrows[(L + 2) * n + i] = 2.0 * (r[3] * sg);
        }
        L += 3;
    }
    /* centre, variances, live dims scaled to unit variance (in place) */
    int live[MAXK], nl = 0;
    for (int k = 0; k < L; k++) {
        double *row = vrows + k * n;
        double mu = row_sum(row, n) / (double)n;
        for (long i = 0; i < n; i++) row[i] = row[i] - mu;
        double var = row_dot(row, row, n) / (double)(n - 1);
        if (var > ZERO_VARIANCE) {
            double sd = sqrt(var);
            for (long i = 0; i < n; i++) row[i] = row[i] / sd;
            live[nl++] = k;
        }
    }
    if (nl == 0) return 0;
    double c[MAXK * MAXK], lam[MAXK], vec[MAXK * MAXK];
    for (int a = 0; a < nl; a++)
        for (int b = a; b < nl; b++) {
            double x = row_dot(vrows + live[a] * n, vrows + live[b] * n, n) / (double)(n - 1);
            c[a * nl + b] = x;
            c[b * nl + a] = x;
        }
    jacobi_eigh(c, nl, lam, vec);
    double big = 0.0;
    for (int k = 0; k < nl; k++) big = lam[k] > big ? lam[k] : big;
    int K = 0;
    for (int k = 0; k < nl; k++) {
        if (!(lam[k] > RTOL * big)) continue;
        double *out = pcs + K * n;
        for (long i = 0; i < n; i++) out[i] = 0.0;
        for (int a = 0; a < nl; a++) {
            double va = vec[a * nl + k];
            const double *row = vrows + live[a] * n;
            for (long i = 0; i < n; i++) out[i] = out[i] + row[i] * va;
        }
        lam_out[K] = lam[k];
        sum_pc[K] = row_sum(out, n);
        K++;
    }
    for (int k = 0; k < K; k++)
        for (int j = 0; j < p; j++) {
            double cv = row_dot(pcs + k * n, yc + j * n, n) / (double)(n - 1);
            if (shrink >= 0.0) {
                double denom = lam_out[k] * var_y[j];
                double r2 = denom > 0.0 ? cv * cv / denom : 0.0;
                double f = r2 > 0.0 ? 1.0 - shrink * ((1.0 - r2) * (1.0 - r2)) / ((double)n * r2)
                                    : 0.0;
                f = f < 0.0 ? 0.0 : (f > 1.0 ? 1.0 : f);
                if (f != f) f = 0.0;
                cv = cv * f;
            }
            cpy[k * p + j] = cv;
        }
    return K;
}

/* mk_joint_args, the per-frame algebra (mk_joint_gain) and the per-sample apply step
 * (mk_joint_apply) are in kernel_common.h, shared with the device kernel. */

/* Moments of one row x against `m` centred rows r (m <= 12), with a shift s = x[0]:
 * S1 = sum(x - s), S2 = sum((x - s)^2), C[j] = sum((x - s) r_j), in four lanes (the step
 * macros of kernel_common.h). Specialised for each m (row_moments dispatches), so that the
 * accumulators stay in registers. */
static inline __attribute__((always_inline)) void row_moments_m(
        const double *x, long n, const double *r, const int m, double *s1, double *s2,
        double *c) {
    double s = x[0];
    v4 a1 = splat(0.0), a2 = splat(0.0), ac[MAXK];
    for (int j = 0; j < m; j++) ac[j] = splat(0.0);
    v4 vs = splat(s), d;
    long i = 0;
    for (; i + 4 <= n; i += 4) {
        MK_MOMENT_STEP(d, ld4(x + i), vs, a1, a2);
        for (int j = 0; j < m; j++) MK_CROSS_STEP(ac[j], d, ld4(r + j * n + i));
    }
    double t1 = hsum(a1), t2 = hsum(a2), tc[MAXK];
    for (int j = 0; j < m; j++) tc[j] = hsum(ac[j]);
    for (; i < n; i++) {
        double e;
        MK_MOMENT_STEP(e, x[i], s, t1, t2);
        for (int j = 0; j < m; j++) MK_CROSS_STEP(tc[j], e, r[j * n + i]);
    }
    *s1 = t1;
    *s2 = t2;
    for (int j = 0; j < m; j++) c[j] = tc[j];
}

#define MOMENTS_CASE(M) case M: row_moments_m(x, n, r, M, s1, s2, c); return;
static void row_moments(const double *x, long n, const double *r, int m, double *s1, double *s2,
                        double *c) {
    switch (m) {
        MOMENTS_CASE(0) MOMENTS_CASE(1) MOMENTS_CASE(2) MOMENTS_CASE(3) MOMENTS_CASE(4)
        MOMENTS_CASE(5) MOMENTS_CASE(6) MOMENTS_CASE(7) MOMENTS_CASE(8) MOMENTS_CASE(9)
        MOMENTS_CASE(10) MOMENTS_CASE(11) MOMENTS_CASE(12)
        default: return;
    }
}

/* shifted product sum of two rows (the endpoint gain's quaternion covariance) */
static double row_cov_sum(const double *xa, const double *xb, long n) {
    double sa = xa[0], sb = xb[0];
    v4 acc = splat(0.0), va = splat(sa), vb = splat(sb);
    long i = 0;
    for (; i + 4 <= n; i += 4) MK_COV_STEP(acc, ld4(xa + i), va, ld4(xb + i), vb);
    double t = hsum(acc);
    for (; i < n; i++) MK_COV_STEP(t, xa[i], sa, xb[i], sb);
    return t;
}

/* the apply step over the samples of one frame (rows x -> rows o), four samples at a time
 * (mk_joint_apply on mk_lane vectors), specialised for each p; the last n % 4 samples go
 * through the same function in a block of four padded with copies of the last sample (the
 * lanes never mix, and a copy's flags are its original's). The OR of the samples' flags. */
static inline __attribute__((always_inline)) int apply_rows_p(
        const double *restrict cxy, const double *restrict nmean, const int inflate,
        double lam, const int p, const double *restrict x, const double *restrict w, long n,
        double *restrict o) {
    int flags = 0;
    long i = 0;
    for (; i + MK_LANES <= n; i += MK_LANES)
        flags |= mk_joint_apply(cxy, nmean, inflate, lam, p, x + i, n, w + i, n, o + i, n);
    if (i < n) {
        double xt[7 * MK_LANES], wt[MAXP * MK_LANES], ot[7 * MK_LANES];
        for (int l = 0; l < MK_LANES; l++) {
            long j = i + l < n ? i + l : n - 1;
            for (int d = 0; d < 7; d++) xt[d * MK_LANES + l] = x[d * n + j];
            for (int k = 0; k < p; k++) wt[k * MK_LANES + l] = w[k * n + j];
        }
        flags |= mk_joint_apply(cxy, nmean, inflate, lam, p, xt, MK_LANES, wt, MK_LANES, ot,
                                MK_LANES);
        for (long j = i; j < n; j++)
            for (int d = 0; d < 7; d++) o[d * n + j] = ot[d * MK_LANES + (j - i)];
    }
    return flags;
}

#define APPLY_CASE(P) case P: return inflate ? \
    apply_rows_p(cxy, nmean, 1, lam, P, x, w, n, o) : apply_rows_p(cxy, nmean, 0, lam, P, x, w, n, o);
static int apply_rows(const double *cxy, const double *nmean, int inflate, double lam, int p,
                      const double *x, const double *w, long n, double *o) {
    switch (p) {
        APPLY_CASE(1) APPLY_CASE(2) APPLY_CASE(3) APPLY_CASE(4) APPLY_CASE(5) APPLY_CASE(6)
        APPLY_CASE(7)
        default: return MK_FLAG_NONFINITE;
    }
}

/* One frame of the joint update: sums, gain, move, inflation, renormalisation.
 * x: the frame's rows (7 x n), o: its output rows. Returns an MK_ code. */
static int joint_frame(const mk_joint_args *A, const double *x, double *o) {
    long n = A->n;
    int m = A->gain == 0 ? A->p : A->k;
    const double *r = A->gain == 0 ? A->yc : A->pcs;
    double x0[7], s1[7], s2[7], c[7 * MAXK], covq[MK_NPAIRS];
    for (int d = 0; d < 7; d++) {
        x0[d] = x[d * n];
        row_moments(x + d * n, n, r, m, s1 + d, s2 + d, c + d * MAXK);
    }
    if (A->gain == 1)
        for (int t = 0; t < MK_NPAIRS; t++)
            covq[t] = row_cov_sum(x + (3 + mk_pair_a(t)) * n, x + (3 + mk_pair_b(t)) * n, n);
    double cxy[MAXP * 7], nmean[7];
    int rc = mk_joint_gain(A, x0, s1, s2, c, covq, cxy, nmean);
    if (rc != MK_OK) return rc;
    int flags = apply_rows(cxy, nmean, A->inflation != 1.0, A->inflation, A->p, x, A->w, n, o);
    return mk_flags_code(flags);
}

int mk_joint_frames(const mk_joint_args *A, const double *edges, double *out,
                    const uint8_t *point, long lo, long hi) {
    long n = A->n;
    for (long f = lo; f < hi; f++) {
        double *o = out + f * 7 * n;
        if (f == 0) {
            set_identity(o, n);
            continue;
        }
        int rc = joint_frame(A, edges + f * 7 * n, o);
        if (rc != MK_OK) return rc;
        if (point[f]) pin_point(o, n);
    }
    return MK_OK;
}

long mk_joint_args_size(void) { return (long)sizeof(mk_joint_args); }

/* ------------------------------------------------------------------ the paper's update */

/* Scaled, truncated pseudo-inverse of a symmetric PSD m x m matrix (mcsm.core.at.scaled_pinv) */
static void scaled_pinv(const double *s, int m, double *out) {
    double dsc[MAXD], lam[MAXD], v[MAXD * MAXD], f[MAXD];
    scaled_eigh(s, m, dsc, lam, v);
    for (int k = 0; k < m; k++) f[k] = lam[k] > 0.0 ? 1.0 / lam[k] : 0.0;
    vfv(v, f, m, out);
    for (int a = 0; a < m; a++)
        for (int b = 0; b < m; b++) out[a * m + b] = out[a * m + b] * dsc[a] * dsc[b];
}

/* Revised merge (PAPER eq. 6) of two correlated estimates given as p rows each (p <= 6):
 * c, d (p rows of n) -> out = c + K (d - c), K = (cov c - C_X) cov(c - d)^+,
 * C_X = (cov c + cov d - cov(c - d)) / 2. work: 3 p n doubles. */
static void merge_vectors_rows(const double *c, const double *d, int p, long n, double *out,
                               double *work) {
    double *ac = work, *ad = work + p * n, *adiff = work + 2 * p * n;
    for (int k = 0; k < p; k++) {
        double mc = row_sum(c + k * n, n) / (double)n, md = row_sum(d + k * n, n) / (double)n;
        for (long i = 0; i < n; i++) {
            ac[k * n + i] = c[k * n + i] - mc;
            ad[k * n + i] = d[k * n + i] - md;
            adiff[k * n + i] = ac[k * n + i] - ad[k * n + i];
        }
    }
    double cc[36], cd[36], cdf[36], ca[36], pinv[36], gain[36];
    for (int a = 0; a < p; a++)
        for (int b = 0; b < p; b++) {
            cc[a * p + b] = row_dot(ac + a * n, ac + b * n, n) / (double)(n - 1);
            cd[a * p + b] = row_dot(ad + a * n, ad + b * n, n) / (double)(n - 1);
            cdf[a * p + b] = row_dot(adiff + a * n, adiff + b * n, n) / (double)(n - 1);
        }
    for (int i = 0; i < p * p; i++) ca[i] = cc[i] - 0.5 * (cc[i] + cd[i] - cdf[i]);
    scaled_pinv(cdf, p, pinv);
    matmul(ca, pinv, p, p, p, gain);
    for (int a = 0; a < p; a++) {
        double *o = out + a * n;
        for (long i = 0; i < n; i++) o[i] = c[a * n + i];
        for (int b = 0; b < p; b++) {
            double g = gain[a * p + b];
            for (long i = 0; i < n; i++) o[i] = o[i] + (d[b * n + i] - c[b * n + i]) * g;
        }
    }
}

/* [t, 2 vec(q_ref^-1 q)] rows (6 x n) of an AT in rows x, quaternions on q_ref's side */
static void tangent_rows(const double *x, const double *m, long n, double *v) {
    memcpy(v, x, sizeof(double) * 3 * n);
    for (long i = 0; i < n; i++) {
        double r[4];
        qmul1(m[0], -m[1], -m[2], -m[3], x[3 * n + i], x[4 * n + i], x[5 * n + i],
              x[6 * n + i], r);
        double sg = r[0] < 0.0 ? -1.0 : 1.0;
        v[3 * n + i] = 2.0 * (r[1] * sg);
        v[4 * n + i] = 2.0 * (r[2] * sg);
        v[5 * n + i] = 2.0 * (r[3] * sg);
    }
}

/* The merged main edge G' = G (x) X of PAPER Fig. 3 (tangent chart; or the 3-D points of a
 * point observation, x then 3 rows), written into out (7 rows). work: 36 n doubles. */
void mk_paper_main_edge(const double *g, const double *x, long n, int point, double *out,
                        double *work) {
    double *pc = work, *pd = work + 6 * n, *res = work + 12 * n, *tmp = work + 18 * n;
    if (point) {  /* the translation rows only; work[0, 9 n) as scratch */
        memcpy(out, g, sizeof(double) * 7 * n);
        merge_vectors_rows(g, x, 3, n, res, pc);
        memcpy(out, res, sizeof(double) * 3 * n);
        return;
    }
    double m[4];
    mean_rotation(g + 3 * n, n, m);
    tangent_rows(g, m, n, pc);
    tangent_rows(x, m, n, pd);
    merge_vectors_rows(pc, pd, 6, n, res, tmp);
    memcpy(out, res, sizeof(double) * 3 * n);
    for (long i = 0; i < n; i++) {
        double hx = 0.5 * res[3 * n + i], hy = 0.5 * res[4 * n + i], hz = 0.5 * res[5 * n + i];
        double w2 = 1.0 - (hx * hx + hy * hy + hz * hz);
        double w = sqrt(w2 > 0.0 ? w2 : 0.0);
        double nrm = sqrt(w * w + hx * hx + hy * hy + hz * hz);
        double q[4];
        qmul1(m[0], m[1], m[2], m[3], w / nrm, hx / nrm, hy / nrm, hz / nrm, q);
        out[3 * n + i] = q[0];
        out[4 * n + i] = q[1];
        out[5 * n + i] = q[2];
        out[6 * n + i] = q[3];
    }
}

/* merge_correlated(C, shift (+) C) in the tangent chart of C's mean rotation, for frames
 * lo..hi-1 of `in` (each first re-rooted: C = pre (+) e, points pinned, when pre is given),
 * written to out[f + dst_offset]. PAPER Fig. 3's E_j' = E_j (x) (G' (+) G^R (+) E_j), with
 * Delta = p_D - p_C: C_A = -sym(cov(p_C, Delta)), C_A + C_B = cov(Delta) (in delta = 2 v
 * units), p = p_C + K Delta. work: 17 n doubles. */
int mk_paper_frames(const double *pre, const double *shift, const double *in, double *out,
                    const uint8_t *point, long lo, long hi, long dst_offset, long n,
                    double *work) {
    double *c = work, *dlt = work + 7 * n, *qd = work + 13 * n;
    const double s6[6] = {1.0, 1.0, 1.0, 2.0, 2.0, 2.0};
    for (long f = lo; f < hi; f++) {
        const double *e = in + f * 7 * n;
        double *o = out + (f + dst_offset) * 7 * n;
        if (pre != NULL) {
            mk_compound(pre, e, c, n);
            if (point[f]) pin_point(c, n);
        } else {
            memcpy(c, e, sizeof(double) * 7 * n);
        }
        /* D = shift (+) C: Delta t = t_D - t_C, q_D */
        for (long i = 0; i < n; i++) {
            double t[3], q[4];
            qrot1(shift[3 * n + i], shift[4 * n + i], shift[5 * n + i], shift[6 * n + i], c[i],
                  c[n + i], c[2 * n + i], t);
            dlt[i] = (shift[i] + t[0]) - c[i];
            dlt[n + i] = (shift[n + i] + t[1]) - c[n + i];
            dlt[2 * n + i] = (shift[2 * n + i] + t[2]) - c[2 * n + i];
            qmul1(shift[3 * n + i], shift[4 * n + i], shift[5 * n + i], shift[6 * n + i],
                  c[3 * n + i], c[4 * n + i], c[5 * n + i], c[6 * n + i], q);
            qd[i] = q[0];
            qd[n + i] = q[1];
            qd[2 * n + i] = q[2];
            qd[3 * n + i] = q[3];
        }
        double m[4];
        mean_rotation(c + 3 * n, n, m);
        /* v_C into c's rows 3..5 (c's quaternion rows are not needed after this), v_D - v_C
         * into dlt's rows 3..5 */
        for (long i = 0; i < n; i++) {
            double rc[4], rd[4];
            qmul1(m[0], -m[1], -m[2], -m[3], c[3 * n + i], c[4 * n + i], c[5 * n + i],
                  c[6 * n + i], rc);
            qmul1(m[0], -m[1], -m[2], -m[3], qd[i], qd[n + i], qd[2 * n + i], qd[3 * n + i],
                  rd);
            double sc = rc[0] < 0.0 ? -1.0 : 1.0, sd = rd[0] < 0.0 ? -1.0 : 1.0;
            double vc0 = rc[1] * sc, vc1 = rc[2] * sc, vc2 = rc[3] * sc;
            dlt[3 * n + i] = rd[1] * sd - vc0;
            dlt[4 * n + i] = rd[2] * sd - vc1;
            dlt[5 * n + i] = rd[3] * sd - vc2;
            c[3 * n + i] = vc0;
            c[4 * n + i] = vc1;
            c[5 * n + i] = vc2;
        }
        /* p_C = c rows 0..5 ([t, v]), Delta = dlt rows 0..5: cross-covariances */
        double mc[6], md[6];
        for (int k = 0; k < 6; k++) {
            mc[k] = row_sum(c + k * n, n) / (double)n;
            md[k] = row_sum(dlt + k * n, n) / (double)n;
        }
        double ccd[36], cdd[36];
        for (int a = 0; a < 6; a++) {
            for (int b = 0; b < 6; b++) {
                const double *xa = c + a * n, *xb = dlt + b * n;
                double sa = mc[a], sb = md[b];
                v4 acc = splat(0.0), va = splat(sa), vb = splat(sb);
                long i = 0;
                for (; i + 4 <= n; i += 4) acc += (ld4(xa + i) - va) * (ld4(xb + i) - vb);
                double t = hsum(acc);
                for (; i < n; i++) t += (xa[i] - sa) * (xb[i] - sb);
                ccd[a * 6 + b] = t / (double)(n - 1) * s6[a] * s6[b];
            }
            for (int b = a; b < 6; b++) {
                const double *xa = dlt + a * n, *xb = dlt + b * n;
                double sa = md[a], sb = md[b];
                v4 acc = splat(0.0), va = splat(sa), vb = splat(sb);
                long i = 0;
                for (; i + 4 <= n; i += 4) acc += (ld4(xa + i) - va) * (ld4(xb + i) - vb);
                double t = hsum(acc);
                for (; i < n; i++) t += (xa[i] - sa) * (xb[i] - sb);
                double v = t / (double)(n - 1) * s6[a] * s6[b];
                cdd[a * 6 + b] = v;
                cdd[b * 6 + a] = v;
            }
        }
        double ca[36], pinv[36], gain[36];
        for (int a = 0; a < 6; a++)
            for (int b = 0; b < 6; b++) ca[a * 6 + b] = -0.5 * (ccd[a * 6 + b] + ccd[b * 6 + a]);
        scaled_pinv(cdd, 6, pinv);
        matmul(ca, pinv, 6, 6, 6, gain);
        for (int a = 0; a < 6; a++)
            for (int b = 0; b < 6; b++) gain[a * 6 + b] = gain[a * 6 + b] * (s6[b] / s6[a]);
        /* [t, v] = p_C + K Delta */
        for (int a = 0; a < 6; a++) {
            double *r = (a < 3) ? o + a * n : qd + (a - 3) * n;  /* v into qd rows 0..2 */
            const double *pa = c + a * n;
            for (long i = 0; i < n; i++) r[i] = pa[i];
            for (int b = 0; b < 6; b++) {
                double g = gain[a * 6 + b];
                const double *db = dlt + b * n;
                for (long i = 0; i < n; i++) r[i] = r[i] + db[i] * g;
            }
        }
        /* back from the chart: w = sqrt(1 - |v|^2) (v scaled to unit if |v| > 1), q_ref (w, v) */
        for (long i = 0; i < n; i++) {
            double vx = qd[i], vy = qd[n + i], vz = qd[2 * n + i];
            double s2 = vx * vx + vy * vy + vz * vz;
            double w2 = 1.0 - s2;
            double w = sqrt(w2 > 0.0 ? w2 : 0.0);
            if (s2 > 1.0) {
                double sn = sqrt(s2);
                vx = vx / sn;
                vy = vy / sn;
                vz = vz / sn;
            }
            double q[4];
            qmul1(m[0], m[1], m[2], m[3], w, vx, vy, vz, q);
            o[3 * n + i] = q[0];
            o[4 * n + i] = q[1];
            o[5 * n + i] = q[2];
            o[6 * n + i] = q[3];
        }
        if (!all_finite(o, 7 * n)) return MK_NONFINITE;
    }
    return MK_OK;
}
