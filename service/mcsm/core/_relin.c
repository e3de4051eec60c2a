/* mcsm's relinearisation solve: Gauss-Newton with Levenberg-Marquardt damping over a
 * component's recorded factors, on a block-sparse Cholesky factorisation.
 *
 * Errors are in the chart of the inputs' moments: a pose factor a->b compares h = a^-1 b with
 * its mean z as [t_h - t_z, 2 s vec(z_q^-1 q_h)] (s puts the relative rotation on the positive
 * hemisphere), a point factor as R_a^T (p - t_a) - z; a variable moves by x (+) d =
 * (t + d_t, q (x) (sqrt(1 - |d_r/2|^2), d_r/2)). Jacobians are analytic. The root of the
 * component is fixed (the star forest is conditional on it).
 *
 * Trimming: after the solve, every loop closure (a factor with a threshold in ftrim) whose
 * chi-square at the solution exceeds its threshold is left out and the solve continues once
 * from there: an accepted closure that the whole history contradicts (a wrong one the gate let
 * through while the map was uncertain) does not pull the solution.
 *
 * Ordering: minimum degree on the variables' graph, with integer arithmetic only (ties by
 * variable index), removed variables first and kept ones last, so that the kept variables'
 * joint covariance conditional on the root is (L_kk L_kk^T)^-1: the trailing block. Only the
 * active coordinates are solved for (a planar map: x, y, yaw). A pivot below 1e-10 of its
 * diagonal marks a dimension without information: it is held at its estimate and gets no
 * spread.
 *
 * Portability: _relin.h.
 */
#include <math.h>
#include <stdlib.h>
#include <string.h>

#include "_relin.h"

#define MAX_TRIES 10
/* halvings of a step that does not lower the cost, before the damping grows */
#define BACKTRACK 6

int mr_version(void) { return 7; }
long mr_problem_size(void) { return (long)sizeof(mr_problem); }

static int full_dim(int kind) { return kind == 0 ? 6 : 3; }

/* ------------------------------------------------------------------ factor errors */

/* e = chart of (a^-1 b) around z (6 values); ja, jb (6 x 6, row-major) if ja is not NULL. */
static void pose_error(const double *xa, const double *xb, const double *z, double *e,
                       double *ja, double *jb) {
    double ra[9];
    mr_rotmat(xa + 3, ra);
    double d[3] = {xb[0] - xa[0], xb[1] - xa[1], xb[2] - xa[2]};
    double th[3];
    for (int i = 0; i < 3; i++) th[i] = ra[i] * d[0] + ra[3 + i] * d[1] + ra[6 + i] * d[2];
    for (int i = 0; i < 3; i++) e[i] = th[i] - z[i];
    double qac[4] = {xa[3], -xa[4], -xa[5], -xa[6]};
    double qh[4], r[4];
    mr_qmul(qac, xb + 3, qh);
    double zc[4] = {z[3], -z[4], -z[5], -z[6]};
    mr_qmul(zc, qh, r);
    double s = r[0] < 0.0 ? -1.0 : 1.0;
    for (int i = 0; i < 3; i++) e[3 + i] = 2.0 * (s * r[1 + i]);
    if (ja == NULL) return;
    memset(ja, 0, 36 * sizeof(double));
    memset(jb, 0, 36 * sizeof(double));
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            ja[i * 6 + j] = -ra[j * 3 + i];
            jb[i * 6 + j] = ra[j * 3 + i];
        }
    /* d t_h / d rotation of a = [t_h]x */
    ja[0 * 6 + 4] = -th[2];
    ja[0 * 6 + 5] = th[1];
    ja[1 * 6 + 3] = th[2];
    ja[1 * 6 + 5] = -th[0];
    ja[2 * 6 + 3] = -th[1];
    ja[2 * 6 + 4] = th[0];
    double rw = s * r[0], rv[3] = {s * r[1], s * r[2], s * r[3]};
    /* b: (r_w I + [r_v]x); a: -(r_w I - [r_v]x) R(z_q)^T */
    double p[9] = {rw, -rv[2], rv[1], rv[2], rw, -rv[0], -rv[1], rv[0], rw};
    double m[9] = {rw, rv[2], -rv[1], -rv[2], rw, rv[0], rv[1], -rv[0], rw};
    double rz[9];
    mr_rotmat(z + 3, rz);
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            jb[(3 + i) * 6 + 3 + j] = p[i * 3 + j];
            ja[(3 + i) * 6 + 3 + j] =
                -(m[i * 3] * rz[j * 3] + m[i * 3 + 1] * rz[j * 3 + 1] + m[i * 3 + 2] * rz[j * 3 + 2]);
        }
}

/* e = R_a^T (p - t_a) - z (3 values); ja (3 x 6), jp (3 x 3) if ja is not NULL. */
static void point_error(const double *xa, const double *xp, const double *z, double *e,
                        double *ja, double *jp) {
    double ra[9];
    mr_rotmat(xa + 3, ra);
    double d[3] = {xp[0] - xa[0], xp[1] - xa[1], xp[2] - xa[2]};
    double h[3];
    for (int i = 0; i < 3; i++) h[i] = ra[i] * d[0] + ra[3 + i] * d[1] + ra[6 + i] * d[2];
    for (int i = 0; i < 3; i++) e[i] = h[i] - z[i];
    if (ja == NULL) return;
    memset(ja, 0, 18 * sizeof(double));
    for (int i = 0; i < 3; i++)
        for (int j = 0; j < 3; j++) {
            ja[i * 6 + j] = -ra[j * 3 + i];
            jp[i * 3 + j] = ra[j * 3 + i];
        }
    ja[0 * 6 + 4] = -h[2];
    ja[0 * 6 + 5] = h[1];
    ja[1 * 6 + 3] = h[2];
    ja[1 * 6 + 5] = -h[0];
    ja[2 * 6 + 3] = -h[1];
    ja[2 * 6 + 4] = h[0];
}

/* ------------------------------------------------------------------ the system */

typedef struct {
    const mr_problem *P;
    mr_state *S;
    double *prior_buf;  /* work for the largest prior: charts and Jacobians */
    long prior_buf_len;
} ctx;

/* Offset of block (row, col), row >= col, in val / hval; -1 if not in the structure. */
static long find_block(const mr_state *S, int col, int row) {
    if (row == col) return S->doff[col];
    long lo = S->cptr[col], hi = S->cptr[col + 1] - 1;
    while (lo <= hi) {
        long mid = lo + (hi - lo) / 2;
        if (S->crow[mid] == row) return S->boff[mid];
        if (S->crow[mid] < row) lo = mid + 1;
        else hi = mid - 1;
    }
    return -1;
}

/* Add one factor's whitened residual r (m) and Jacobian J (m x ncols, row-major; variable i
 * at columns coloff[i]..) to g and H (hval), lower blocks only. */
static void accumulate(mr_state *S, int m, const double *r, const double *J, int ncols, int k,
                       const int *vars, const int *coloff) {
    for (int i = 0; i < k; i++) {
        int pi = S->pos_of[vars[i]];
        if (pi < 0) continue;
        int di = S->dim[pi];
        const int *ai = S->act + 6 * pi;
        double *gi = S->g + S->soff[pi];
        for (int a = 0; a < di; a++) {
            double s = 0.0;
            for (int row = 0; row < m; row++) s += J[row * ncols + coloff[i] + ai[a]] * r[row];
            gi[a] += s;
        }
        for (int j = 0; j < k; j++) {
            int pj = S->pos_of[vars[j]];
            if (pj < 0 || pj > pi || (pj == pi && j != i)) continue;
            int dj = S->dim[pj];
            const int *aj = S->act + 6 * pj;
            long off = find_block(S, pj, pi);
            if (off < 0) continue;  /* cannot happen: the structure holds every factor */
            double *blk = S->hval + off;
            for (int a = 0; a < di; a++)
                for (int b = 0; b < dj; b++) {
                    double s = 0.0;
                    for (int row = 0; row < m; row++)
                        s += J[row * ncols + coloff[i] + ai[a]] * J[row * ncols + coloff[j] + aj[b]];
                    blk[a * dj + b] += s;
                }
        }
    }
}

/* r = W e, out = W J for a packed lower-triangular W (m x m). */
static void whiten(const double *w, int m, const double *e, const double *j, int ncols,
                   double *r, double *out) {
    for (int i = 0; i < m; i++) {
        const double *wi = w + i * (i + 1) / 2;
        double s = 0.0;
        for (int k = 0; k <= i; k++) s += wi[k] * e[k];
        r[i] = s;
        if (out == NULL) continue;
        for (int c = 0; c < ncols; c++) {
            double t = 0.0;
            for (int k = 0; k <= i; k++) t += wi[k] * j[k * ncols + c];
            out[i * ncols + c] = t;
        }
    }
}

/* Prior pi at x: residual r (rows) and, if J, its Jacobian (rows x ncols: anchor 6, then each
 * variable's full dimension). Returns the number of columns. */
static int prior_eval(ctx *C, long pi, const double *x, double *r, double *J) {
    const mr_problem *P = C->P;
    long v0 = P->pvoff[pi];
    int k = (int)(P->pvoff[pi + 1] - v0 - 1);
    int anchor = P->pvars[v0];
    long m = P->prows[pi];
    int cols = 0;
    for (int j = 0; j < k; j++) cols += full_dim(P->vkind[P->pvars[v0 + 1 + j]]);
    const double *zhat = P->pdata + P->pdoff[pi];
    const double *R = zhat + 7 * k;
    const double *d = R + m * cols;
    double *c = C->prior_buf, *jc = c + cols;  /* jc: per variable, fd x (6 + fd) */
    int off = 0;
    long joff = 0;
    for (int j = 0; j < k; j++) {
        int v = P->pvars[v0 + 1 + j];
        int fd = full_dim(P->vkind[v]);
        double ja[36], jv[36];
        if (fd == 6) pose_error(x + 7 * anchor, x + 7 * v, zhat + 7 * j, c + off, ja, jv);
        else point_error(x + 7 * anchor, x + 7 * v, zhat + 7 * j, c + off, ja, jv);
        for (int a = 0; a < fd; a++) {
            for (int b = 0; b < 6; b++) jc[joff + a * (6 + fd) + b] = ja[a * 6 + b];
            for (int b = 0; b < fd; b++) jc[joff + a * (6 + fd) + 6 + b] = jv[a * fd + b];
        }
        off += fd;
        joff += (long)fd * (6 + fd);
    }
    int ncols = 6 + cols;
    for (long i = 0; i < m; i++) {
        const double *ri = R + i * cols;
        double s = d[i];
        for (int q = 0; q < cols; q++) s += ri[q] * c[q];
        r[i] = s;
        if (J == NULL) continue;
        double *Ji = J + i * ncols;
        for (int b = 0; b < ncols; b++) Ji[b] = 0.0;
        off = 0;
        joff = 0;
        for (int j = 0; j < k; j++) {
            int fd = full_dim(P->vkind[P->pvars[v0 + 1 + j]]);
            for (int a = 0; a < fd; a++) {
                double rv = ri[off + a];
                const double *row = jc + joff + a * (6 + fd);
                for (int b = 0; b < 6; b++) Ji[b] += rv * row[b];
                for (int b = 0; b < fd; b++) Ji[6 + off + b] += rv * row[6 + b];
            }
            off += fd;
            joff += (long)fd * (6 + fd);
        }
    }
    return ncols;
}

/* The cost sum r^2 at x; with `assemble`, also H (hval) and g at x. NaN if anything is not
 * finite. */
static double evaluate(ctx *C, const double *x, int assemble, double *prior_r, double *prior_j) {
    const mr_problem *P = C->P;
    mr_state *S = C->S;
    if (assemble) {
        memset(S->hval, 0, sizeof(double) * S->nval);
        memset(S->g, 0, sizeof(double) * S->nscal);
    }
    double cost = 0.0;
    for (long f = 0; f < P->nf; f++) {
        if (S->off[f]) continue;
        int a = P->fvars[2 * f], b = P->fvars[2 * f + 1];
        const double *z = P->fz + 7 * f, *w = P->fw + 21 * f;
        double e[6], r[6], ja[36], jb[36], J[72] = {0}, Jw[72];
        int m, ncols;
        if (P->fkind[f] == 0) {
            pose_error(x + 7 * a, x + 7 * b, z, e, assemble ? ja : NULL, jb);
            m = 6;
            ncols = 12;
        } else {
            point_error(x + 7 * a, x + 7 * b, z, e, assemble ? ja : NULL, jb);
            m = 3;
            ncols = 9;
        }
        if (assemble) {
            int fb = ncols - 6;
            for (int i = 0; i < m; i++) {
                for (int c = 0; c < 6; c++) J[i * ncols + c] = ja[i * 6 + c];
                for (int c = 0; c < fb; c++) J[i * ncols + 6 + c] = jb[i * fb + c];
            }
        }
        whiten(w, m, e, J, ncols, r, assemble ? Jw : NULL);
        for (int i = 0; i < m; i++) cost += r[i] * r[i];
        if (assemble) {
            int vars[2] = {a, b}, coloff[2] = {0, 6};
            accumulate(S, m, r, Jw, ncols, 2, vars, coloff);
        }
    }
    for (long p = 0; p < P->np; p++) {
        long m = P->prows[p];
        int ncols = prior_eval(C, p, x, prior_r, assemble ? prior_j : NULL);
        for (long i = 0; i < m; i++) cost += prior_r[i] * prior_r[i];
        if (assemble) {
            long v0 = P->pvoff[p];
            int k = (int)(P->pvoff[p + 1] - v0);
            int *vars = malloc(sizeof(int) * 2 * (size_t)k);
            if (vars == NULL) return NAN;
            int *coloff = vars + k, off = 6;
            for (int j = 0; j < k; j++) {
                vars[j] = P->pvars[v0 + j];
                coloff[j] = j == 0 ? 0 : off;
                if (j > 0) off += full_dim(P->vkind[vars[j]]);
            }
            accumulate(S, (int)m, prior_r, prior_j, ncols, k, vars, coloff);
            free(vars);
        }
    }
    if (!(cost - cost == 0.0)) return NAN;
    return cost;
}

/* Leave out every loop closure whose chi-square at x exceeds its threshold; how many. */
static long trim(const mr_problem *P, mr_state *S, const double *x) {
    long n = 0;
    for (long f = 0; f < P->nf; f++) {
        if (S->off[f] || !(P->ftrim[f] > 0.0)) continue;
        int a = P->fvars[2 * f], b = P->fvars[2 * f + 1];
        double e[6], r[6];
        int m = P->fkind[f] == 0 ? 6 : 3;
        if (m == 6) pose_error(x + 7 * a, x + 7 * b, P->fz + 7 * f, e, NULL, NULL);
        else point_error(x + 7 * a, x + 7 * b, P->fz + 7 * f, e, NULL, NULL);
        whiten(P->fw + 21 * f, m, e, NULL, 0, r, NULL);
        double s = 0.0;
        for (int i = 0; i < m; i++) s += r[i] * r[i];
        if (s > P->ftrim[f]) {
            S->off[f] = 1;
            n++;
        }
    }
    return n;
}

static void set_hdiag(mr_state *S) {
    for (long p = 0; p < S->ns; p++)
        for (int a = 0; a < S->dim[p]; a++)
            S->hdiag[S->soff[p] + a] = S->hval[S->doff[p] + a * S->dim[p] + a];
}

/* x (+) the step dx for every variable in the system. */
static void retract_all(const mr_problem *P, const mr_state *S, const double *x, const double *dx,
                        double *out) {
    memcpy(out, x, sizeof(double) * 7 * (size_t)P->nv);
    for (long p = 0; p < S->ns; p++) {
        int v = S->var_at[p];
        double d[6] = {0, 0, 0, 0, 0, 0};
        for (int a = 0; a < S->dim[p]; a++) d[S->act[6 * p + a]] = dx[S->soff[p] + a];
        double *o = out + 7 * v;
        for (int i = 0; i < 3; i++) o[i] = o[i] + d[i];
        if (P->vkind[v] == 0) mr_qretract(o + 3, d + 3);
    }
}

void mr_free(mr_problem *P) {
    mr_state *S = P->state;
    if (S == NULL) return;
    free(S->var_at);
    free(S->pos_of);
    free(S->dim);
    free(S->act);
    free(S->soff);
    free(S->cptr);
    free(S->crow);
    free(S->boff);
    free(S->doff);
    free(S->val);
    free(S->hval);
    free(S->g);
    free(S->y);
    free(S->dx);
    free(S->hdiag);
    free(S->dead);
    free(S->off);
    free(S);
    P->state = NULL;
}

static int check_problem(const mr_problem *P) {
    if (P->nv < 1 || P->nf < 0 || P->np < 0) return MR_BAD_ARGS;
    for (long v = 0; v < P->nv; v++)
        if (P->vkind[v] != 0 && P->vkind[v] != 1) return MR_BAD_ARGS;
    for (long f = 0; f < P->nf; f++) {
        int a = P->fvars[2 * f], b = P->fvars[2 * f + 1];
        if (a < 0 || b < 0 || a >= P->nv || b >= P->nv || a == b) return MR_BAD_ARGS;
        if (P->vkind[a] != 0 || (P->fkind[f] == 0) != (P->vkind[b] == 0)) return MR_BAD_ARGS;
    }
    for (long p = 0; p < P->np; p++) {
        if (P->pvoff[p + 1] - P->pvoff[p] < 2 || P->prows[p] < 0) return MR_BAD_ARGS;
        for (long i = P->pvoff[p]; i < P->pvoff[p + 1]; i++)
            if (P->pvars[i] < 0 || P->pvars[i] >= P->nv) return MR_BAD_ARGS;
        if (P->vkind[P->pvars[P->pvoff[p]]] != 0) return MR_BAD_ARGS;
    }
    return MR_OK;
}

/* Solve (max_iter > 0) from P->x, then factorise at the result (unless keep_factor is 0: the
 * same x, no factor kept); P->state keeps the factor for mr_redraw / mr_marginal. stats:
 * 0 iterations, 1 cost before, 2 cost after, 3 the
 * active coordinates (pose bits, point bits << 6),
 * 4 scalars solved, 5 kept scalars, 6 values in L, 7 factorisations, 8 dead scalars,
 * 9 LM damping at the end, 10 loop closures trimmed. */
int mr_solve(mr_problem *P) {
    mr_free(P);
    int rc = check_problem(P);
    if (rc != MR_OK) return rc;
    mr_state *S = calloc(1, sizeof(mr_state));
    if (S == NULL) return MR_NO_MEMORY;
    P->state = S;
    rc = mr_build_structure(P, S);
    if (rc != MR_OK) return rc;
    long ns = S->ns;
    S->dim = malloc(sizeof(int) * (size_t)(ns ? ns : 1));
    S->act = malloc(sizeof(int) * 6 * (size_t)(ns ? ns : 1));
    if (!S->dim || !S->act) return MR_NO_MEMORY;
    long nscal = 0;
    for (long p = 0; p < ns; p++) {
        int pose = P->vkind[S->var_at[p]] == 0;
        int *a = S->act + 6 * p, d = 0;
        int64_t mask = pose ? P->pose_active : P->point_active;
        for (int k = 0; k < (pose ? 6 : 3); k++)
            if (mask & ((int64_t)1 << k)) a[d++] = k;
        S->dim[p] = d;
        S->soff[p] = nscal;
        nscal += S->dim[p];
    }
    S->soff[ns] = nscal;
    S->nscal = nscal;
    long nval = 0;
    for (long p = 0; p < ns; p++) {
        S->doff[p] = nval;
        nval += (long)S->dim[p] * S->dim[p];
        for (long q = S->cptr[p]; q < S->cptr[p + 1]; q++) {
            S->boff[q] = nval;
            nval += (long)S->dim[S->crow[q]] * S->dim[p];
        }
    }
    S->nval = nval;
    S->val = malloc(sizeof(double) * (size_t)(nval ? nval : 1));
    S->hval = malloc(sizeof(double) * (size_t)(nval ? nval : 1));
    S->g = malloc(sizeof(double) * (size_t)(nscal ? nscal : 1));
    S->y = malloc(sizeof(double) * (size_t)(nscal ? nscal : 1));
    S->dx = malloc(sizeof(double) * (size_t)(nscal ? nscal : 1));
    S->hdiag = malloc(sizeof(double) * (size_t)(nscal ? nscal : 1));
    S->dead = malloc((size_t)(nscal ? nscal : 1));
    S->off = calloc((size_t)(P->nf ? P->nf : 1), 1);
    int *slot = malloc(sizeof(int) * (size_t)(ns ? ns : 1));
    double *xn = malloc(sizeof(double) * 7 * (size_t)P->nv);
    long maxm = 0, maxc = 0, maxbuf = 0;
    for (long p = 0; p < P->np; p++) {
        long v0 = P->pvoff[p], k = P->pvoff[p + 1] - v0 - 1, cols = 0, jb = 0;
        for (long j = 0; j < k; j++) {
            long fd = full_dim(P->vkind[P->pvars[v0 + 1 + j]]);
            cols += fd;
            jb += fd * (6 + fd);
        }
        if (P->prows[p] > maxm) maxm = P->prows[p];
        if (6 + cols > maxc) maxc = 6 + cols;
        if (cols + jb > maxbuf) maxbuf = cols + jb;
    }
    double *prior_r = malloc(sizeof(double) * (size_t)(maxm ? maxm : 1));
    double *prior_j = malloc(sizeof(double) * (size_t)(maxm * maxc > 0 ? maxm * maxc : 1));
    ctx C = {P, S, malloc(sizeof(double) * (size_t)(maxbuf ? maxbuf : 1)), maxbuf};
    rc = MR_NO_MEMORY;
    if (!S->val || !S->hval || !S->g || !S->y || !S->dx || !S->hdiag || !S->dead || !S->off ||
        !slot ||
        !xn || !prior_r || !prior_j || !C.prior_buf)
        goto out;
    for (long p = 0; p < ns; p++) slot[p] = -1;
    rc = MR_NONFINITE;
    double cost = evaluate(&C, P->x, 1, prior_r, prior_j);
    if (cost != cost) goto out;
    set_hdiag(S);
    double cost0 = cost, lambda = 0.0;
    long it = 0, nfact = 0, trimmed = 0;
    for (int round = 0; round < 2; round++) {
        long it0 = it;
        while (it - it0 < P->max_iter) {
            int accepted = 0, full = 1;
            double cn = 0.0;
            for (int t = 0; t < MAX_TRIES; t++) {
                mr_factorise(S, lambda, slot);
                nfact++;
                mr_forward(S, S->g, S->dx);
                mr_backward(S, S->dx, 0, 1, 1);
                for (long i = 0; i < nscal; i++) S->dx[i] = -S->dx[i];
                retract_all(P, S, P->x, S->dx, xn);
                cn = evaluate(&C, xn, 0, prior_r, prior_j);
                /* a step that does not lower the cost is halved (a backtracking line search
                 * along it) before the damping grows: along a long chain's flat, curved
                 * valley the full step overshoots and a damped one barely moves */
                for (int b = 0; b < BACKTRACK && !(cn < cost); b++) {
                    full = 0;
                    for (long i = 0; i < nscal; i++) S->dx[i] = 0.5 * S->dx[i];
                    retract_all(P, S, P->x, S->dx, xn);
                    cn = evaluate(&C, xn, 0, prior_r, prior_j);
                }
                if (cn < cost) {
                    accepted = 1;
                    break;
                }
                full = 1;
                lambda = lambda == 0.0 ? 1e-5 : lambda * 10.0;
            }
            it++;
            if (!accepted) break;
            double prev = cost;
            memcpy(P->x, xn, sizeof(double) * 7 * (size_t)P->nv);
            cost = cn;
            lambda = lambda * 0.1;
            if (lambda < 1e-6) lambda = 0.0;
            /* converged: a whole step that lowered the cost by less than tol (a halved step's
             * small decrease says only that the step was too long) */
            if (full && prev - cost <= P->tol * prev) break;
            double again = evaluate(&C, P->x, 1, prior_r, prior_j);
            if (again != again) goto out;
            set_hdiag(S);
        }
        if (round == 1 || P->max_iter == 0) break;
        long newly = trim(P, S, P->x);
        if (newly == 0) break;
        trimmed += newly;
        lambda = 0.0;
        cost = evaluate(&C, P->x, 1, prior_r, prior_j);
        if (cost != cost) goto out;
        set_hdiag(S);
    }
    long ndead = 0;
    if (P->keep_factor || P->max_iter == 0) {
        double last = evaluate(&C, P->x, 1, prior_r, prior_j);
        if (last != last) goto out;
        set_hdiag(S);
        mr_factorise(S, 0.0, slot);
        nfact++;
        mr_forward(S, S->g, S->y);
        for (long i = 0; i < nscal; i++) ndead += S->dead[i];
        S->factored = 1;
    }
    P->stats[0] = (double)it;
    P->stats[1] = cost0;
    P->stats[2] = cost;
    P->stats[3] = (double)(P->pose_active | (P->point_active << 6));
    P->stats[4] = (double)nscal;
    P->stats[5] = (double)(nscal - S->soff[S->kept_pos]);
    P->stats[6] = (double)nval;
    P->stats[7] = (double)nfact;
    P->stats[8] = (double)ndead;
    P->stats[9] = lambda;
    P->stats[10] = (double)trimmed;
    rc = MR_OK;
out:
    free(slot);
    free(xn);
    free(prior_r);
    free(prior_j);
    free(C.prior_buf);
    return rc;
}
