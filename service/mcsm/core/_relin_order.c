/* mcsm's relinearisation: the elimination order and the structure of the Cholesky factor.
 *
 * Minimum degree on the graph of the variables (two variables are neighbours when a factor
 * holds both), eliminating one variable at a time on an explicit elimination graph, in integer
 * arithmetic only: ties go to the smaller variable index, removed variables are all eliminated
 * before kept ones. A variable's neighbours when it is eliminated are the rows of its column of
 * L. Portability: _relin.h.
 */
#include <stdlib.h>
#include <string.h>

#include "_relin.h"

static int full_dim(int kind) { return kind == 0 ? 6 : 3; }


typedef struct { int kept, deg, v; } hent;

static int hless(hent a, hent b) {
    if (a.kept != b.kept) return a.kept < b.kept;
    if (a.deg != b.deg) return a.deg < b.deg;
    return a.v < b.v;
}

static int hpush(hent **h, long *n, long *cap, hent e) {
    if (*n == *cap) {
        long nc = *cap ? 2 * *cap : 1024;
        hent *nh = realloc(*h, sizeof(hent) * (size_t)nc);
        if (nh == NULL) return -1;
        *h = nh;
        *cap = nc;
    }
    long i = (*n)++;
    (*h)[i] = e;
    while (i > 0) {
        long par = (i - 1) / 2;
        if (!hless((*h)[i], (*h)[par])) break;
        hent t = (*h)[i];
        (*h)[i] = (*h)[par];
        (*h)[par] = t;
        i = par;
    }
    return 0;
}

static hent hpop(hent *h, long *n) {
    hent top = h[0];
    h[0] = h[--(*n)];
    long i = 0;
    for (;;) {
        long l = 2 * i + 1, r = l + 1, m = i;
        if (l < *n && hless(h[l], h[m])) m = l;
        if (r < *n && hless(h[r], h[m])) m = r;
        if (m == i) break;
        hent t = h[i];
        h[i] = h[m];
        h[m] = t;
        i = m;
    }
    return top;
}

static int cmp_int(const void *a, const void *b) {
    int x = *(const int *)a, y = *(const int *)b;
    return (x > y) - (x < y);
}

/* The variables of factor f (fixed ones included); returns their count (at most 2 or a
 * prior's size), writing them into out if not NULL. */
static long factor_vars(const mr_problem *P, long f, const int **out) {
    if (f < P->nf) {
        *out = P->fvars + 2 * f;
        return 2;
    }
    long p = f - P->nf;
    *out = P->pvars + P->pvoff[p];
    return P->pvoff[p + 1] - P->pvoff[p];
}

/* Minimum-degree elimination order and the column structure of L. */
int mr_build_structure(const mr_problem *P, mr_state *S) {
    long nv = P->nv, nfac = P->nf + P->np;
    int rc = MR_NO_MEMORY;
    long *cnt = calloc((size_t)nv + 1, sizeof(long));
    int **adj = calloc((size_t)nv, sizeof(int *));
    int *adjn = calloc((size_t)nv, sizeof(int));
    uint8_t *elim = calloc((size_t)nv, 1);
    int *cur = calloc((size_t)nv, sizeof(int));
    hent *heap = NULL;
    long hn = 0, hcap = 0;
    int *srows = NULL;
    long srn = 0, srcap = 0;
    long *sstart = malloc(sizeof(long) * ((size_t)nv + 1));
    int *merged = NULL;
    if (!cnt || !adj || !adjn || !elim || !cur || !sstart) goto out;
    /* initial adjacency (duplicates removed after sorting) */
    for (long f = 0; f < nfac; f++) {
        const int *vs;
        long k = factor_vars(P, f, &vs);
        for (long i = 0; i < k; i++) {
            if (P->vfixed[vs[i]]) continue;
            for (long j = 0; j < k; j++)
                if (j != i && !P->vfixed[vs[j]] && vs[j] != vs[i]) cnt[vs[i]]++;
        }
    }
    for (long v = 0; v < nv; v++) {
        adj[v] = malloc(sizeof(int) * (size_t)(cnt[v] ? cnt[v] : 1));
        if (adj[v] == NULL) goto out;
    }
    for (long f = 0; f < nfac; f++) {
        const int *vs;
        long k = factor_vars(P, f, &vs);
        for (long i = 0; i < k; i++) {
            if (P->vfixed[vs[i]]) continue;
            for (long j = 0; j < k; j++)
                if (j != i && !P->vfixed[vs[j]] && vs[j] != vs[i]) adj[vs[i]][adjn[vs[i]]++] = vs[j];
        }
    }
    long ns = 0;
    for (long v = 0; v < nv; v++) {
        if (P->vfixed[v]) continue;
        ns++;
        qsort(adj[v], (size_t)adjn[v], sizeof(int), cmp_int);
        int u = 0;
        for (int i = 0; i < adjn[v]; i++)
            if (u == 0 || adj[v][i] != adj[v][u - 1]) adj[v][u++] = adj[v][i];
        adjn[v] = u;
        cur[v] = u;
        if (hpush(&heap, &hn, &hcap, (hent){P->vkept[v] ? 1 : 0, u, (int)v})) goto out;
    }
    S->ns = ns;
    S->var_at = malloc(sizeof(int) * (size_t)(ns ? ns : 1));
    S->pos_of = malloc(sizeof(int) * (size_t)(nv ? nv : 1));
    if (!S->var_at || !S->pos_of) goto out;
    for (long v = 0; v < nv; v++) S->pos_of[v] = -1;
    S->kept_pos = ns;
    long step = 0;
    while (hn > 0) {
        hent e = hpop(heap, &hn);
        int v = e.v;
        if (elim[v] || e.deg != cur[v]) continue;
        if (e.kept && S->kept_pos == ns) S->kept_pos = step;
        elim[v] = 1;
        S->var_at[step] = v;
        S->pos_of[v] = (int)step;
        sstart[step] = srn;
        int k = adjn[v];
        if (srn + k > srcap) {
            long nc = srcap ? 2 * srcap : 4096;
            while (nc < srn + k) nc *= 2;
            int *nr = realloc(srows, sizeof(int) * (size_t)nc);
            if (nr == NULL) goto out;
            srows = nr;
            srcap = nc;
        }
        memcpy(srows + srn, adj[v], sizeof(int) * (size_t)k);
        srn += k;
        step++;
        for (int i = 0; i < k; i++) {
            int u = adj[v][i];
            merged = malloc(sizeof(int) * (size_t)(adjn[u] + k));
            if (merged == NULL) goto out;
            int a = 0, b = 0, o = 0;
            while (a < adjn[u] || b < k) {
                int x;
                if (b >= k || (a < adjn[u] && adj[u][a] < adj[v][b])) x = adj[u][a++];
                else if (a >= adjn[u] || adj[v][b] < adj[u][a]) x = adj[v][b++];
                else { x = adj[u][a++]; b++; }
                if (x != u && x != v) merged[o++] = x;
            }
            free(adj[u]);
            adj[u] = merged;
            merged = NULL;
            adjn[u] = o;
            cur[u] = o;
            if (hpush(&heap, &hn, &hcap, (hent){P->vkept[u] ? 1 : 0, o, u})) goto out;
        }
        free(adj[v]);
        adj[v] = NULL;
        adjn[v] = 0;
    }
    sstart[step] = srn;
    /* column structure in positions, ascending */
    S->cptr = malloc(sizeof(long) * ((size_t)ns + 1));
    S->crow = malloc(sizeof(int) * (size_t)(srn ? srn : 1));
    S->boff = malloc(sizeof(long) * (size_t)(srn ? srn : 1));
    S->doff = malloc(sizeof(long) * (size_t)(ns ? ns : 1));
    S->soff = malloc(sizeof(long) * ((size_t)ns + 1));
    if (!S->cptr || !S->crow || !S->boff || !S->doff || !S->soff) goto out;
    for (long p = 0; p <= ns; p++) S->cptr[p] = sstart[p];
    for (long q = 0; q < srn; q++) S->crow[q] = S->pos_of[srows[q]];
    for (long p = 0; p < ns; p++)
        qsort(S->crow + S->cptr[p], (size_t)(S->cptr[p + 1] - S->cptr[p]), sizeof(int), cmp_int);
    rc = MR_OK;
out:
    if (adj) for (long v = 0; v < nv; v++) free(adj[v]);
    free(adj);
    free(adjn);
    free(elim);
    free(cur);
    free(heap);
    free(srows);
    free(sstart);
    free(cnt);
    return rc;
}

