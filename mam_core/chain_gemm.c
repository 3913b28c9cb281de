/* The learner's GEMMs under MAM_PORTABLE_GEMM=chain (mam_core/gemm.py, `_Chain`).

   Every element of C = A B is one chain of fused multiply-adds over k in order, from +0:
       c = +0;  for p = 0 .. k-1:  c = fma(A[i][p], B[p][j], c)
   FMA rounds once, as IEEE 754 defines, on every CPU, so the bits are a function of the
   operands alone. The kernels below (AVX-512F, AVX2+FMA, plain C) vectorize across the
   elements of C, never along p, and a later block of p carries each chain on from the float
   the earlier block stored: the kernel, the blocking, the tile shapes, the orientation
   (C or its transpose) and the thread that computes a tile cannot change a bit.
   tests/test_gemm.py checks the kernels against each other (the plain C one is the definition
   above, written out) and against the product in float64. */
#include <immintrin.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <math.h>

#define KC 256
#define MC 96
#define NC 2048

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

/* A panel: mr rows, for each p its mr values; rows past mc are zeros (their results are dropped). */
static void pack_a(const float *a, long ars, long acs, int mc, int kc, int mr, float *dst, int avx2) {
    for (int i0 = 0; i0 < mc; i0 += mr, dst += (long)mr * kc) {
        int rows = mc - i0 < mr ? mc - i0 : mr;
        if (acs == 1 && rows == mr) {  /* row-major: each row read along p */
            gather_rows(a + (long)i0 * ars, ars, mr, kc, dst, mr, avx2);
            continue;
        }
        if (ars == 1 && rows == mr) {  /* column-major: each p's rows lie side by side */
            for (int p = 0; p < kc; p++) memcpy(dst + (long)p * mr, a + (long)i0 + (long)p * acs, sizeof(float) * mr);
            continue;
        }
        for (int p = 0; p < kc; p++)
            for (int r = 0; r < mr; r++)
                dst[(long)p * mr + r] = r < rows ? a[(long)(i0 + r) * ars + (long)p * acs] : 0.0f;
    }
}

/* B panels: nr columns, for each p its nr values; columns past nc are zeros. */
static void pack_b(const float *b, long brs, long bcs, int kc, int nc, int nr, float *dst, int avx2) {
    for (int j0 = 0; j0 < nc; j0 += nr, dst += (long)nr * kc) {
        int cols = nc - j0 < nr ? nc - j0 : nr;
        if (brs == 1 && cols == nr) {  /* column-major: each column read along p */
            gather_rows(b + (long)j0 * bcs, bcs, nr, kc, dst, nr, avx2);
            continue;
        }
        if (bcs == 1 && cols == nr) {  /* row-major */
            for (int p = 0; p < kc; p++) memcpy(dst + (long)p * nr, b + (long)p * brs + j0, sizeof(float) * nr);
            continue;
        }
        for (int p = 0; p < kc; p++) {
            const float *row = b + (long)p * brs + (long)j0 * bcs;
            for (int c = 0; c < nr; c++) dst[(long)p * nr + c] = c < cols ? row[(long)c * bcs] : 0.0f;
        }
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
                pack_b(bk, brs, bcs, kc, nc, NR, pb, avx2);
            else if (nc % NR)  /* the last, partial panel: packed (zeros past nc) */
                pack_b(bk + nc / NR * NR, brs, bcs, kc, nc % NR, NR, pb + (long)nc / NR * NR * kc, avx2);
            for (int ic = 0; ic < m; ic += MC) {
                int mc = m - ic < MC ? m - ic : MC;
                pack_a(a + (long)ic * ars + (long)pc * acs, ars, acs, mc, kc, MR, pa, avx2);
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

/* e products C_q = A_q B_q (q < e), strides in elements (es: from one member to the next).
   Each element of C is one FMA chain over k in order from +0, so neither the kernel, nor the
   blocking, nor the orientation below changes a bit. Returns 0, or -1 if out of memory. */
int chain_sgemm(int isa, long e, int m, int n, int k,
                const float *a, long aes, long ars, long acs,
                const float *b, long bes, long brs, long bcs,
                float *c, long ces, long crs, long ccs) {
    kernels ks = pick(isa);
    if (k <= 0) {  /* an empty sum: +0 */
        for (long q = 0; q < e; q++)
            for (int i = 0; i < m; i++)
                for (int j = 0; j < n; j++) c[q * ces + i * crs + j * ccs] = 0.0f;
        return 0;
    }
    /* C = A B or Cᵀ = Bᵀ Aᵀ (the same chains): the one that pads the fewest tiles */
    int swap = padded(m, ks.mr) * padded(n, ks.nr) > padded(n, ks.mr) * padded(m, ks.nr) || (n == 1 && m > 1);
    if (swap) {  /* A' = Bᵀ, B' = Aᵀ, C' = Cᵀ */
        const float *a2 = b, *b2 = a;
        long aes2 = bes, ars2 = bcs, acs2 = brs, bes2 = aes, brs2 = acs, bcs2 = ars, crs2 = ccs, ccs2 = crs;
        int m2 = n, n2 = m;
        a = a2; b = b2; aes = aes2; ars = ars2; acs = acs2; bes = bes2; brs = brs2; bcs = bcs2;
        crs = crs2; ccs = ccs2; m = m2; n = n2;
    }
    int ncmax = n < NC ? n : NC, kcmax = k < KC ? k : KC, mcmax = m < MC ? m : MC;
    size_t bsz = padded(ncmax, ks.nr) * kcmax, asz = padded(mcmax, ks.mr) * kcmax;
    float *pb = aligned_alloc(64, padded(bsz * 4, 64)), *pa = aligned_alloc(64, padded(asz * 4, 64));
    if (!pa || !pb) { free(pa); free(pb); return -1; }
    for (long q = 0; q < e; q++)
        product(ks, m, n, k, a + q * aes, ars, acs, b + q * bes, brs, bcs, c + q * ces, crs, ccs, pa, pb);
    free(pa); free(pb);
    return 0;
}
