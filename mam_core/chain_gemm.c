/* The learner's GEMMs under portable arithmetic (mam_core/chain.py; built by `make venv`
   or at the first product).

   Every element of C = A B is one chain of fused multiply-adds over k in order, from +0:
       c = +0;  for p = 0 .. k-1:  c = fma(A[i][p], B[p][j], c)
   FMA rounds once, as IEEE 754 defines, on every CPU, so the bits are a function of the
   operands alone. The kernels below (AVX-512F, AVX2+FMA, plain C) vectorize across the
   elements of C, never along p, and a later block of p carries each chain on from the float
   the earlier block stored: the kernel, the blocking, the tile shapes, the orientation
   (C or its transpose) and the thread that computes a tile cannot change a bit. Packing and
   threads only move data. tests/test_chain_gemm.py checks every kernel against the chain
   computed exactly in rationals and the kernels against each other in every layout. */
#include <immintrin.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <math.h>
#include <pthread.h>
#include <stdatomic.h>
#include <time.h>

#define KC 256   /* a block of p (the chain goes on across blocks) */
#define MC 96    /* rows of A packed at a time */
#define NC 2048  /* columns of B packed at a time */

typedef void (*kernel_fn)(int kc, const float *pa, const float *pb, long ldb, float *c, long ldc, int first);

/* dst[q * ld + i] = src[i * ss + q] for i, q < 8: eight rows of eight floats, transposed. */
__attribute__((target("avx2")))
static void transpose8(const float *src, long ss, float *dst, long ld) {
    __m256 r[8], t[8];
    for (int i = 0; i < 8; i++) r[i] = _mm256_loadu_ps(src + i * ss);
    for (int i = 0; i < 8; i += 2) {
        t[i] = _mm256_unpacklo_ps(r[i], r[i + 1]);
        t[i + 1] = _mm256_unpackhi_ps(r[i], r[i + 1]);
    }
    for (int h = 0; h < 8; h += 4) {
        r[h] = _mm256_shuffle_ps(t[h], t[h + 2], _MM_SHUFFLE(1, 0, 1, 0));
        r[h + 1] = _mm256_shuffle_ps(t[h], t[h + 2], _MM_SHUFFLE(3, 2, 3, 2));
        r[h + 2] = _mm256_shuffle_ps(t[h + 1], t[h + 3], _MM_SHUFFLE(1, 0, 1, 0));
        r[h + 3] = _mm256_shuffle_ps(t[h + 1], t[h + 3], _MM_SHUFFLE(3, 2, 3, 2));
    }
    for (int q = 0; q < 4; q++) {
        _mm256_storeu_ps(dst + q * ld, _mm256_permute2f128_ps(r[q], r[q + 4], 0x20));
        _mm256_storeu_ps(dst + (q + 4) * ld, _mm256_permute2f128_ps(r[q], r[q + 4], 0x31));
    }
}

/* dst[p * ld + i] = src[i * ss + p] for i < rows, p < kc (rows of src, each along p, laid
   side by side): by 8x8 blocks where the CPU has AVX2. */
static void gather_rows(const float *src, long ss, int rows, int kc, float *dst, long ld, int avx2) {
    int i = 0;
    if (avx2)
        for (; i + 8 <= rows; i += 8) {
            int p = 0;
            for (; p + 8 <= kc; p += 8) transpose8(src + i * ss + p, ss, dst + (long)p * ld + i, ld);
            for (; p < kc; p++)
                for (int r = i; r < i + 8; r++) dst[(long)p * ld + r] = src[r * ss + p];
        }
    for (; i < rows; i++)
        for (int p = 0; p < kc; p++) dst[(long)p * ld + i] = src[i * ss + p];
}

/* Panels of `width` lines of X (line l, step p at x[l * ls + p * ps]): for each p its `width`
   values side by side; lines past `lines` are zeros (their results are dropped). A's panels are
   its rows (ls, ps = ars, acs), B's its columns (bcs, brs). */
static void pack(const float *x, long ls, long ps, int lines, int kc, int width, float *dst, int avx2) {
    for (int l0 = 0; l0 < lines; l0 += width, dst += (long)width * kc) {
        int n = lines - l0 < width ? lines - l0 : width;
        if (ps == 1 && n == width) {  /* each line read along p */
            gather_rows(x + (long)l0 * ls, ls, width, kc, dst, width, avx2);
            continue;
        }
        if (ls == 1 && n == width) {  /* each p's lines lie side by side */
            for (int p = 0; p < kc; p++) memcpy(dst + (long)p * width, x + l0 + (long)p * ps, sizeof(float) * width);
            continue;
        }
        for (int p = 0; p < kc; p++)
            for (int l = 0; l < width; l++)
                dst[(long)p * width + l] = l < n ? x[(long)(l0 + l) * ls + (long)p * ps] : 0.0f;
    }
}

/* An MR x (2 W) tile of C: for p = 0..kc-1 in order, acc[r][j] = fma(a[r][p], b[p][j], acc[r][j]),
   starting from +0 (first) or from C's values (a later K block carries the chain on exactly). */
#define TILE_KERNEL(NAME, TARGET, VEC, W, MR, ZERO, LOAD, STORE, BCAST, FMA)                      \
__attribute__((target(TARGET)))                                                                  \
static void NAME(int kc, const float *pa, const float *pb, long ldb, float *c, long ldc, int first) {\
    VEC acc[MR][2];                                                                              \
    _Pragma("GCC unroll 16")                                                                     \
    for (int r = 0; r < MR; r++) {                                                               \
        acc[r][0] = first ? ZERO() : LOAD(c + r * ldc);                                          \
        acc[r][1] = first ? ZERO() : LOAD(c + r * ldc + W);                                      \
    }                                                                                            \
    for (int p = 0; p < kc; p++) {                                                               \
        VEC b0 = LOAD(pb + p * ldb), b1 = LOAD(pb + p * ldb + W);                                \
        _Pragma("GCC unroll 16")                                                                 \
        for (int r = 0; r < MR; r++) {                                                           \
            VEC av = BCAST(pa + p * MR + r);                                                     \
            acc[r][0] = FMA(av, b0, acc[r][0]);                                                  \
            acc[r][1] = FMA(av, b1, acc[r][1]);                                                  \
        }                                                                                        \
    }                                                                                            \
    _Pragma("GCC unroll 16")                                                                     \
    for (int r = 0; r < MR; r++) {                                                               \
        STORE(c + r * ldc, acc[r][0]);                                                           \
        STORE(c + r * ldc + W, acc[r][1]);                                                       \
    }                                                                                            \
}

#define BCAST512(x) _mm512_set1_ps(*(x))
TILE_KERNEL(kernel_avx2, "avx2,fma", __m256, 8, 6, _mm256_setzero_ps, _mm256_loadu_ps, _mm256_storeu_ps,
            _mm256_broadcast_ss, _mm256_fmadd_ps)
TILE_KERNEL(kernel_avx2_row, "avx2,fma", __m256, 8, 1, _mm256_setzero_ps, _mm256_loadu_ps, _mm256_storeu_ps,
            _mm256_broadcast_ss, _mm256_fmadd_ps)
TILE_KERNEL(kernel_avx512, "avx512f", __m512, 16, 12, _mm512_setzero_ps, _mm512_loadu_ps, _mm512_storeu_ps,
            BCAST512, _mm512_fmadd_ps)
TILE_KERNEL(kernel_avx512_row, "avx512f", __m512, 16, 1, _mm512_setzero_ps, _mm512_loadu_ps, _mm512_storeu_ps,
            BCAST512, _mm512_fmadd_ps)

static void kernel_scalar(int kc, const float *pa, const float *pb, long ldb, float *c, long ldc, int first) {
    enum { MR = 4, NR = 4 };
    for (int r = 0; r < MR; r++)
        for (int j = 0; j < NR; j++) {
            float acc = first ? 0.0f : c[r * ldc + j];
            for (int p = 0; p < kc; p++) acc = fmaf(pa[p * MR + r], pb[p * ldb + j], acc);
            c[r * ldc + j] = acc;
        }
}

typedef struct { kernel_fn tile, row; int mr, nr, isa; } kernels;

static int best_isa(void) {
    static int best;  /* 0 until the first call finds it (any thread finds the same) */
    if (!best) {
        __builtin_cpu_init();
        best = __builtin_cpu_supports("avx512f") ? 3
             : __builtin_cpu_supports("avx2") && __builtin_cpu_supports("fma") ? 2 : 1;
    }
    return best;
}

/* isa: 1 plain C, 2 AVX2+FMA, 3 AVX-512F; 0, or more than this CPU has: the best it has.
   Any gives the same bits. */
static kernels pick(int isa) {
    if (isa <= 0 || isa > best_isa()) isa = best_isa();
    if (isa == 3) return (kernels){kernel_avx512, kernel_avx512_row, 12, 32, 3};
    if (isa == 2) return (kernels){kernel_avx2, kernel_avx2_row, 6, 16, 2};
    return (kernels){kernel_scalar, NULL, 4, 4, 1};
}

int chain_isa(int isa) { return pick(isa).isa; }

static long padded(long x, long to) { return (x + to - 1) / to * to; }

/* One product C[m,n] = A[m,k] B[k,n], element (i,j) of X at x[i*rs + j*cs]. */
static void product(kernels ks, int m, int n, int k, const float *a, long ars, long acs,
                    const float *b, long brs, long bcs, float *c, long crs, long ccs, float *pa, float *pb) {
    kernel_fn kern = m == 1 && ks.row ? ks.row : ks.tile;
    int MR = m == 1 && ks.row ? 1 : ks.mr, NR = ks.nr, avx2 = ks.isa >= 2;
    /* one panel of A's rows reads each panel of B once: a row-major B is read where it lies */
    int direct = m <= MR && bcs == 1;
    float tmp[12 * 32] __attribute__((aligned(64)));
    for (int jc = 0; jc < n; jc += NC) {
        int nc = n - jc < NC ? n - jc : NC;
        for (int pc = 0; pc < k; pc += KC) {
            int kc = k - pc < KC ? k - pc : KC, first = pc == 0;
            const float *bk = b + (long)pc * brs + (long)jc * bcs;
            if (!direct)
                pack(bk, bcs, brs, nc, kc, NR, pb, avx2);
            else if (nc % NR)  /* the last, partial panel: packed (zeros past nc) */
                pack(bk + nc / NR * NR * bcs, bcs, brs, nc % NR, kc, NR, pb + (long)nc / NR * NR * kc, avx2);
            for (int ic = 0; ic < m; ic += MC) {
                int mc = m - ic < MC ? m - ic : MC;
                pack(a + (long)ic * ars + (long)pc * acs, ars, acs, mc, kc, MR, pa, avx2);
                for (int jr = 0; jr < nc; jr += NR) {
                    int nr = nc - jr < NR ? nc - jr : NR;
                    const float *pbj = direct && nr == NR ? bk + jr : pb + (long)jr * kc;
                    long ldb = direct && nr == NR ? brs : NR;
                    for (int ir = 0; ir < mc; ir += MR) {
                        int mr = mc - ir < MR ? mc - ir : MR;
                        float *ct = c + (long)(ic + ir) * crs + (long)(jc + jr) * ccs;
                        const float *pai = pa + (long)ir * kc;
                        if (mr == MR && nr == NR && ccs == 1) { kern(kc, pai, pbj, ldb, ct, crs, first); continue; }
                        if (!first)
                            for (int r = 0; r < mr; r++)
                                for (int j = 0; j < nr; j++) tmp[r * NR + j] = ct[r * crs + j * ccs];
                        kern(kc, pai, pbj, ldb, tmp, NR, first);
                        for (int r = 0; r < mr; r++)
                            for (int j = 0; j < nr; j++) ct[r * crs + j * ccs] = tmp[r * NR + j];
                    }
                }
            }
        }
    }
}

/* Packing buffers, one pair a thread, grown as needed and kept. */
static __thread float *tl_pa, *tl_pb;
static __thread size_t tl_pa_n, tl_pb_n;

static float *grown(float **buf, size_t *have, size_t need) {
    if (*have >= need) return *buf;
    free(*buf);
    *buf = aligned_alloc(64, padded(need * sizeof(float), 64));
    *have = *buf ? need : 0;
    return *buf;
}

/* One product C[m,n] = A[m,k] B[k,n] in this thread: C = A B or Cᵀ = Bᵀ Aᵀ (the same chains),
   the one that pads the fewest tiles. 0, or -1 if out of memory. */
static int one(kernels ks, int m, int n, int k, const float *a, long ars, long acs,
               const float *b, long brs, long bcs, float *c, long crs, long ccs) {
    if (m <= 0 || n <= 0) return 0;
    if (k <= 0) {  /* an empty sum: +0 */
        for (int i = 0; i < m; i++)
            for (int j = 0; j < n; j++) c[i * crs + j * ccs] = 0.0f;
        return 0;
    }
    if (padded(m, ks.mr) * padded(n, ks.nr) > padded(n, ks.mr) * padded(m, ks.nr) || (n == 1 && m > 1)) {
        const float *t = a; a = b; b = t;  /* A' = Bᵀ, B' = Aᵀ, C' = Cᵀ */
        long ars2 = bcs, acs2 = brs, brs2 = acs, bcs2 = ars, s = crs;
        ars = ars2; acs = acs2; brs = brs2; bcs = bcs2; crs = ccs; ccs = s;
        int tm = m; m = n; n = tm;
    }
    int ncmax = n < NC ? n : NC, kcmax = k < KC ? k : KC, mcmax = m < MC ? m : MC;
    float *pb = grown(&tl_pb, &tl_pb_n, padded(ncmax, ks.nr) * kcmax);
    float *pa = grown(&tl_pa, &tl_pa_n, padded(mcmax, ks.mr) * kcmax);
    if (!pa || !pb) return -1;
    product(ks, m, n, k, a, ars, acs, b, brs, bcs, c, crs, ccs, pa, pb);
    return 0;
}

/* A batch of e products C_q = A_q B_q, cut into tasks: task t is member t (by_members), or the
   rows (or columns) lo..hi of every member. Any cut gives the same bits. */
typedef struct {
    kernels ks;
    long e;
    int m, n, k, by_members, by_rows, width;
    const float *a, *b;
    float *c;
    long aes, ars, acs, bes, brs, bcs, ces, crs, ccs;
} job_t;

static int task(const job_t *j, int t) {
    long q0 = j->by_members ? t : 0, q1 = j->by_members ? t + 1 : j->e;
    int lo = j->by_members ? 0 : t * j->width;
    int hi = j->by_members ? (j->by_rows ? j->m : j->n) : lo + j->width;
    hi = hi < (j->by_rows ? j->m : j->n) ? hi : (j->by_rows ? j->m : j->n);
    for (long q = q0; q < q1; q++) {
        const float *a = j->a + q * j->aes, *b = j->b + q * j->bes;
        float *c = j->c + q * j->ces;
        int failed = j->by_rows
            ? one(j->ks, hi - lo, j->n, j->k, a + lo * j->ars, j->ars, j->acs, b, j->brs, j->bcs,
                  c + lo * j->crs, j->crs, j->ccs)
            : one(j->ks, j->m, hi - lo, j->k, a, j->ars, j->acs, b + lo * j->bcs, j->brs, j->bcs,
                  c + lo * j->ccs, j->crs, j->ccs);
        if (failed) return -1;
    }
    return 0;
}

/* The threads: workers claim the tasks of the current job (generation << 32 | next task) with a
   compare-and-swap, so a worker late for one job can never take a task of the next; the caller
   takes tasks too and returns once every task is done. Between jobs a worker spins spin_ns,
   then sleeps on a condition variable (a long spin burns the core the env workers need). */
#define MAX_THREADS 64
static struct {
    pthread_mutex_t mu;
    pthread_cond_t cv;
    job_t job;
    int ntasks, started, want;
    _Atomic unsigned long long claim;
    atomic_int done, failed, sleeping;
    long spin_ns;
} P = {.mu = PTHREAD_MUTEX_INITIALIZER, .cv = PTHREAD_COND_INITIALIZER};
static pthread_mutex_t one_job = PTHREAD_MUTEX_INITIALIZER;

static void run_tasks(unsigned gen) {
    for (;;) {
        unsigned long long v = atomic_load(&P.claim);
        if ((unsigned)(v >> 32) != gen || (int)(v & 0xffffffffu) >= P.ntasks) return;
        if (!atomic_compare_exchange_weak(&P.claim, &v, v + 1)) continue;
        if (task(&P.job, (int)(v & 0xffffffffu)) != 0) atomic_store(&P.failed, 1);
        atomic_fetch_add(&P.done, 1);
    }
}

static long since_ns(const struct timespec *t0) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (t.tv_sec - t0->tv_sec) * 1000000000L + (t.tv_nsec - t0->tv_nsec);
}

static void *worker(void *arg) {
    int index = (int)(long)arg;
    unsigned seen = (unsigned)(atomic_load(&P.claim) >> 32);
    for (;;) {
        struct timespec t0;
        clock_gettime(CLOCK_MONOTONIC, &t0);
        unsigned gen;
        for (int n = 1; (gen = (unsigned)(atomic_load(&P.claim) >> 32)) == seen; n++) {
            _mm_pause();
            if (n % 64 == 0 && since_ns(&t0) > P.spin_ns) {
                pthread_mutex_lock(&P.mu);
                atomic_fetch_add(&P.sleeping, 1);
                while ((unsigned)(atomic_load(&P.claim) >> 32) == seen) pthread_cond_wait(&P.cv, &P.mu);
                atomic_fetch_sub(&P.sleeping, 1);
                pthread_mutex_unlock(&P.mu);
                clock_gettime(CLOCK_MONOTONIC, &t0);
            }
        }
        seen = gen;
        if (index < P.want) run_tasks(gen);
    }
    return NULL;
}

/* Spread the job's ntasks over this thread and threads - 1 workers. 0, or -1 (out of memory). */
static int run_job(const job_t *job, int ntasks, int threads) {
    pthread_mutex_lock(&one_job);
    while (P.started < threads - 1 && P.started < MAX_THREADS) {
        pthread_t t;
        pthread_attr_t attr;
        pthread_attr_init(&attr);
        pthread_attr_setdetachstate(&attr, PTHREAD_CREATE_DETACHED);
        int failed = pthread_create(&t, &attr, worker, (void *)(long)P.started);
        pthread_attr_destroy(&attr);
        if (failed) break;  /* fewer threads: the same bits */
        P.started++;
    }
    P.job = *job;
    P.ntasks = ntasks;
    P.want = threads - 1;
    atomic_store(&P.done, 0);
    atomic_store(&P.failed, 0);
    unsigned gen = (unsigned)(atomic_load(&P.claim) >> 32) + 1;
    atomic_store(&P.claim, (unsigned long long)gen << 32);
    if (atomic_load(&P.sleeping) > 0) {
        pthread_mutex_lock(&P.mu);
        pthread_cond_broadcast(&P.cv);
        pthread_mutex_unlock(&P.mu);
    }
    run_tasks(gen);
    while (atomic_load(&P.done) < ntasks) _mm_pause();
    int failed = atomic_load(&P.failed);
    pthread_mutex_unlock(&one_job);
    return failed ? -1 : 0;
}

/* e products C_q = A_q B_q (q < e), strides in elements (es: from one member to the next), over
   `threads` threads where the batch is big enough (spin_us: how long an idle thread spins for
   the next batch). Each element of C is one FMA chain over k in order from +0, so neither the
   kernel, nor the blocking, nor the orientation, nor the cut over threads changes a bit.
   Returns 0, or -1 if out of memory. */
int chain_sgemm(int isa, int threads, long spin_us, long e, int m, int n, int k,
                const float *a, long aes, long ars, long acs,
                const float *b, long bes, long brs, long bcs,
                float *c, long ces, long crs, long ccs) {
    job_t j = {pick(isa), e, m, n, k, 0, 0, 0, a, b, c, aes, ars, acs, bes, brs, bcs, ces, crs, ccs};
    double flops = 2.0 * e * m * n * k;
    threads = threads < 1 ? 1 : threads > MAX_THREADS + 1 ? MAX_THREADS + 1 : threads;
    if (threads == 1 || flops < (double)(1 << 20)) {
        j.by_members = 1;
        for (long t = 0; t < e; t++)
            if (task(&j, (int)t) != 0) return -1;
        return 0;
    }
    P.spin_ns = spin_us * 1000;
    if (e >= threads) {
        j.by_members = 1;
        return run_job(&j, (int)e, threads);
    }
    j.by_rows = m > n;  /* cut the longer side in `threads` blocks of whole tiles */
    int side = j.by_rows ? m : n;
    j.width = (int)padded((side + threads - 1) / threads, 32);
    return run_job(&j, (side + j.width - 1) / j.width, threads);
}
