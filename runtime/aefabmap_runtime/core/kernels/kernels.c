/* aefabmap's kernels compiled ahead of time (runtime/aefabmap_runtime/core/kernels/native.py loads this library with ctypes).
 *
 * Plain C with no Python API, so the library builds without Python headers and loads under a
 * process that may not map writable+executable memory (MemoryDenyWriteExecute=yes): unlike the
 * numba JIT, nothing is generated at run time. Each function does what the numba kernel of the
 * same name does (runtime/core/{scatter,bits,word_matches,verification,model_errors,bit_centroids}.py)
 * with the same operations in the same order, so both give the same results; arrays are C-contiguous
 * and their shapes come as arguments. Built with -ffp-contract=off: a fused multiply-add would
 * change float rounding against the numpy forms.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define API __attribute__((visibility("default")))

/* Version of this library's functions and arguments: native.py refuses a library built from other sources. */
API int64_t aefabmap_kernels_version(void) { return 7; }

/* ---- popcount: the CPU instruction where it has one (x86-64 without POPCNT gets libgcc's) ---- */
#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define HAVE_DISPATCH 1
#include <immintrin.h>
#define POPCNT_TARGET __attribute__((target("popcnt")))
#define AVX2_TARGET __attribute__((target("avx2,popcnt")))
#define AVX512_POPCNT_TARGET __attribute__((target("avx512f,avx512vpopcntdq,avx2,popcnt")))
#else
#define HAVE_DISPATCH 0
#define POPCNT_TARGET
#define AVX2_TARGET
#endif

/* aarch64: Advanced SIMD is in every core; the dot-product instructions (ARMv8.2's optional
 * FEAT_DotProd, ARMv8.4 onwards) are asked of the kernel on Linux. */
#if defined(__aarch64__) && (defined(__GNUC__) || defined(__clang__))
#define HAVE_NEON 1
#include <arm_neon.h>
#if defined(__linux__)
#define HAVE_NEON_DOTPROD 1
#include <sys/auxv.h>
#ifndef HWCAP_ASIMDDP
#define HWCAP_ASIMDDP (1UL << 20)
#endif
#if defined(__clang__)
#define DOTPROD_TARGET __attribute__((target("dotprod")))
#else
#define DOTPROD_TARGET __attribute__((target("arch=armv8.2-a+dotprod")))
#endif
#else
#define HAVE_NEON_DOTPROD 0
#endif
#else
#define HAVE_NEON 0
#define HAVE_NEON_DOTPROD 0
#endif

/* ---- FAB-MAP scatter (scatter.py) ---- */

API void scatter_buffers(double *acc, const intptr_t *addresses, const double *weights, const int32_t *lens,
                         int64_t n_rows) {
    for (int64_t i = 0; i < n_rows; i++) {
        const int32_t *row = (const int32_t *)addresses[i];
        double w = weights[i];
        int32_t len = lens[i];
        for (int32_t j = 0; j < len; j++) acc[row[j]] += w;
    }
}

API void append_postings(const intptr_t *addresses, const int32_t *positions, int32_t pid, int64_t n_rows) {
    for (int64_t i = 0; i < n_rows; i++) ((int32_t *)addresses[i])[positions[i]] = pid;
}

/* ---- two nearest rows by Hamming distance (bits.py) ---- */

/* Keys d * 2^32 + j order candidates by distance, then by row; they are distinct (they hold j),
 * so the two lowest of any set of candidates are found by keeping the two lowest seen so far. */
static inline void keep_two(int64_t key, int64_t *best, int64_t *second) {
    if (key < *best) {
        *second = *best;
        *best = key;
    } else if (key < *second) {
        *second = key;
    }
}

static inline void write_two(int64_t best, int64_t second, int64_t none, int32_t *dist, int32_t *index) {
    dist[0] = (int32_t)(best >> 32);
    index[0] = (int32_t)(best & 0xFFFFFFFF);
    if (second != none) {
        dist[1] = (int32_t)(second >> 32);
        index[1] = (int32_t)(second & 0xFFFFFFFF);
    }
}

#define NEAREST_TWO_BODY                                                                              \
    const int64_t none = (int64_t)1 << 62;                                                            \
    int64_t *key = (int64_t *)malloc((size_t)(m > 0 ? m : 1) * sizeof(int64_t));                      \
    if (!key) return -1;                                                                              \
    for (int64_t i = 0; i < n; i++) {                                                                 \
        int64_t best = none;                                                                          \
        const uint64_t *ai = a + i * w;                                                               \
        if (w == 4) {                                                                                 \
            uint64_t a0 = ai[0], a1 = ai[1], a2 = ai[2], a3 = ai[3];                                  \
            const uint64_t *b0 = bt, *b1 = bt + m, *b2 = bt + 2 * m, *b3 = bt + 3 * m;                \
            for (int64_t j = 0; j < m; j++) {                                                         \
                int64_t d = __builtin_popcountll(a0 ^ b0[j]) + __builtin_popcountll(a1 ^ b1[j])        \
                          + __builtin_popcountll(a2 ^ b2[j]) + __builtin_popcountll(a3 ^ b3[j]);       \
                key[j] = (d << 32) | j;                                                               \
                best = key[j] < best ? key[j] : best;                                                 \
            }                                                                                         \
        } else {                                                                                      \
            memset(key, 0, (size_t)m * sizeof(int64_t));                                              \
            for (int64_t k = 0; k < w; k++) {                                                         \
                uint64_t ak = ai[k];                                                                  \
                const uint64_t *bk = bt + k * m;                                                      \
                for (int64_t j = 0; j < m; j++) key[j] += __builtin_popcountll(ak ^ bk[j]);            \
            }                                                                                         \
            for (int64_t j = 0; j < m; j++) {                                                         \
                key[j] = (key[j] << 32) | j;                                                          \
                best = key[j] < best ? key[j] : best;                                                 \
            }                                                                                         \
        }                                                                                             \
        key[best & 0xFFFFFFFF] = none;                                                                \
        int64_t second = none;                                                                        \
        for (int64_t j = 0; j < m; j++) second = key[j] < second ? key[j] : second;                   \
        write_two(best, second, none, dist + 2 * i, index + 2 * i);                                   \
    }                                                                                                 \
    free(key);                                                                                        \
    return 0;

static int nearest_two_generic(const uint64_t *a, const uint64_t *bt, int32_t *dist, int32_t *index, int64_t n,
                               int64_t w, int64_t m) {
    NEAREST_TWO_BODY
}

/* The vector forms' tail: searched rows j in [from, m) of a 256-bit query row ai, into best / second. */
static POPCNT_TARGET inline void keep_tail_256(const uint64_t *ai, const uint64_t *bt, int64_t m, int64_t from,
                                               int64_t *best, int64_t *second) {
    for (int64_t j = from; j < m; j++) {
        int64_t d = __builtin_popcountll(ai[0] ^ bt[j]) + __builtin_popcountll(ai[1] ^ bt[m + j])
                  + __builtin_popcountll(ai[2] ^ bt[2 * m + j]) + __builtin_popcountll(ai[3] ^ bt[3 * m + j]);
        keep_two((d << 32) | j, best, second);
    }
}

#if HAVE_DISPATCH
/* Bits set in each byte of v (the nibble-table popcount: AVX2 has no vector popcount instruction). */
static AVX2_TARGET inline __m256i byte_counts(__m256i v) {
    const __m256i table = _mm256_setr_epi8(0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3, 3, 4,
                                           0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3, 3, 4);
    const __m256i nibble = _mm256_set1_epi8(0x0f);
    __m256i lo = _mm256_and_si256(v, nibble), hi = _mm256_and_si256(_mm256_srli_epi16(v, 4), nibble);
    return _mm256_add_epi8(_mm256_shuffle_epi8(table, lo), _mm256_shuffle_epi8(table, hi));
}

/* 256-bit rows (w == 4), four searched rows per step: the same keys d * 2^32 + j and minima as
 * NEAREST_TWO_BODY (a byte holds at most 32 set bits of the four words, so byte sums cannot wrap).
 * Each lane keeps its two lowest keys; keys are distinct (they hold j), so the two lowest of all
 * are among those eight and the tail's. */
static AVX2_TARGET int nearest_two_avx2_256(const uint64_t *a, const uint64_t *bt, int32_t *dist, int32_t *index,
                                            int64_t n, int64_t m) {
    const int64_t none = (int64_t)1 << 62;
    const uint64_t *b0 = bt, *b1 = bt + m, *b2 = bt + 2 * m, *b3 = bt + 3 * m;
    const int64_t m4 = m - m % 4;
    for (int64_t i = 0; i < n; i++) {
        const uint64_t *ai = a + i * 4;
        const __m256i a0 = _mm256_set1_epi64x((long long)ai[0]), a1 = _mm256_set1_epi64x((long long)ai[1]);
        const __m256i a2 = _mm256_set1_epi64x((long long)ai[2]), a3 = _mm256_set1_epi64x((long long)ai[3]);
        __m256i lowest = _mm256_set1_epi64x(none), next = lowest, j4 = _mm256_setr_epi64x(0, 1, 2, 3);
        const __m256i four = _mm256_set1_epi64x(4), zero = _mm256_setzero_si256();
        for (int64_t j = 0; j < m4; j += 4) {
            __m256i c = byte_counts(_mm256_xor_si256(a0, _mm256_loadu_si256((const __m256i *)(b0 + j))));
            c = _mm256_add_epi8(c, byte_counts(_mm256_xor_si256(a1, _mm256_loadu_si256((const __m256i *)(b1 + j)))));
            c = _mm256_add_epi8(c, byte_counts(_mm256_xor_si256(a2, _mm256_loadu_si256((const __m256i *)(b2 + j)))));
            c = _mm256_add_epi8(c, byte_counts(_mm256_xor_si256(a3, _mm256_loadu_si256((const __m256i *)(b3 + j)))));
            __m256i k = _mm256_or_si256(_mm256_slli_epi64(_mm256_sad_epu8(c, zero), 32), j4);
            __m256i below_lowest = _mm256_cmpgt_epi64(lowest, k), below_next = _mm256_cmpgt_epi64(next, k);
            next = _mm256_blendv_epi8(_mm256_blendv_epi8(next, k, below_next), lowest, below_lowest);
            lowest = _mm256_blendv_epi8(lowest, k, below_lowest);
            j4 = _mm256_add_epi64(j4, four);
        }
        int64_t keys[8], best = none, second = none;
        _mm256_storeu_si256((__m256i *)keys, lowest);
        _mm256_storeu_si256((__m256i *)(keys + 4), next);
        for (int t = 0; t < 8; t++) keep_two(keys[t], &best, &second);
        keep_tail_256(ai, bt, m, m4, &best, &second);
        write_two(best, second, none, dist + 2 * i, index + 2 * i);
    }
    return 0;
}

/* The same search with AVX-512's vector popcount, eight searched rows per step: each lane keeps its
 * two lowest keys as nearest_two_avx2_256 does, so the two lowest of all are among those sixteen and
 * the tail's (the same result, fewer instructions per distance). */
static AVX512_POPCNT_TARGET int nearest_two_avx512_256(const uint64_t *a, const uint64_t *bt, int32_t *dist,
                                                       int32_t *index, int64_t n, int64_t m) {
    const int64_t none = (int64_t)1 << 62;
    const uint64_t *b0 = bt, *b1 = bt + m, *b2 = bt + 2 * m, *b3 = bt + 3 * m;
    const int64_t m8 = m - m % 8;
    for (int64_t i = 0; i < n; i++) {
        const uint64_t *ai = a + i * 4;
        const __m512i a0 = _mm512_set1_epi64((long long)ai[0]), a1 = _mm512_set1_epi64((long long)ai[1]);
        const __m512i a2 = _mm512_set1_epi64((long long)ai[2]), a3 = _mm512_set1_epi64((long long)ai[3]);
        __m512i lowest = _mm512_set1_epi64(none), next = lowest, j8 = _mm512_setr_epi64(0, 1, 2, 3, 4, 5, 6, 7);
        const __m512i eight = _mm512_set1_epi64(8);
        for (int64_t j = 0; j < m8; j += 8) {
            __m512i d = _mm512_popcnt_epi64(_mm512_xor_si512(a0, _mm512_loadu_si512((const void *)(b0 + j))));
            d = _mm512_add_epi64(d, _mm512_popcnt_epi64(_mm512_xor_si512(a1, _mm512_loadu_si512((const void *)(b1 + j)))));
            d = _mm512_add_epi64(d, _mm512_popcnt_epi64(_mm512_xor_si512(a2, _mm512_loadu_si512((const void *)(b2 + j)))));
            d = _mm512_add_epi64(d, _mm512_popcnt_epi64(_mm512_xor_si512(a3, _mm512_loadu_si512((const void *)(b3 + j)))));
            __m512i k = _mm512_or_si512(_mm512_slli_epi64(d, 32), j8);
            __mmask8 below_lowest = _mm512_cmpgt_epi64_mask(lowest, k), below_next = _mm512_cmpgt_epi64_mask(next, k);
            next = _mm512_mask_blend_epi64(below_lowest, _mm512_mask_blend_epi64(below_next, next, k), lowest);
            lowest = _mm512_mask_blend_epi64(below_lowest, lowest, k);
            j8 = _mm512_add_epi64(j8, eight);
        }
        int64_t keys[16], best = none, second = none;
        _mm512_storeu_si512((void *)keys, lowest);
        _mm512_storeu_si512((void *)(keys + 8), next);
        for (int t = 0; t < 16; t++) keep_two(keys[t], &best, &second);
        keep_tail_256(ai, bt, m, m8, &best, &second);
        write_two(best, second, none, dist + 2 * i, index + 2 * i);
    }
    return 0;
}

static POPCNT_TARGET int nearest_two_popcnt(const uint64_t *a, const uint64_t *bt, int32_t *dist, int32_t *index,
                                            int64_t n, int64_t w, int64_t m) {
    NEAREST_TWO_BODY
}
#endif

#if HAVE_NEON
/* Bits set in each 64-bit lane of the four rows' XOR with a query (Advanced SIMD counts bits per
 * byte; a byte's sum over the four words is at most 32, the lane's at most 256). */
static inline uint64x2_t lane_distances(const uint8x16_t *q, const uint64_t *b0, const uint64_t *b1,
                                        const uint64_t *b2, const uint64_t *b3) {
    uint8x16_t c = vcntq_u8(veorq_u8(q[0], vld1q_u8((const uint8_t *)b0)));
    c = vaddq_u8(c, vcntq_u8(veorq_u8(q[1], vld1q_u8((const uint8_t *)b1))));
    c = vaddq_u8(c, vcntq_u8(veorq_u8(q[2], vld1q_u8((const uint8_t *)b2))));
    c = vaddq_u8(c, vcntq_u8(veorq_u8(q[3], vld1q_u8((const uint8_t *)b3))));
    return vpaddlq_u32(vpaddlq_u16(vpaddlq_u8(c)));
}

/* nearest_two_avx2_256 with Advanced SIMD (aarch64 boards): four searched rows per step, two per
 * vector; each lane keeps its two lowest keys, so the two lowest of all are among those eight and
 * the tail's. */
static int nearest_two_neon_256(const uint64_t *a, const uint64_t *bt, int32_t *dist, int32_t *index, int64_t n,
                                int64_t m) {
    const int64_t none = (int64_t)1 << 62;
    const uint64_t *b0 = bt, *b1 = bt + m, *b2 = bt + 2 * m, *b3 = bt + 3 * m;
    const int64_t m4 = m - m % 4;
    const int64_t first_rows[4] = {0, 1, 2, 3};
    for (int64_t i = 0; i < n; i++) {
        const uint64_t *ai = a + i * 4;
        uint8x16_t q[4];
        for (int w = 0; w < 4; w++) q[w] = vreinterpretq_u8_u64(vdupq_n_u64(ai[w]));
        int64x2_t lowest[2], next[2], rows[2];
        for (int h = 0; h < 2; h++) {
            lowest[h] = next[h] = vdupq_n_s64(none);
            rows[h] = vld1q_s64(first_rows + 2 * h);
        }
        const int64x2_t four = vdupq_n_s64(4);
        for (int64_t j = 0; j < m4; j += 4) {
            for (int h = 0; h < 2; h++) {
                const int64_t at = j + 2 * h;
                const uint64x2_t d = lane_distances(q, b0 + at, b1 + at, b2 + at, b3 + at);
                const int64x2_t k = vorrq_s64(vreinterpretq_s64_u64(vshlq_n_u64(d, 32)), rows[h]);
                const uint64x2_t below_lowest = vcgtq_s64(lowest[h], k), below_next = vcgtq_s64(next[h], k);
                next[h] = vbslq_s64(below_lowest, lowest[h], vbslq_s64(below_next, k, next[h]));
                lowest[h] = vbslq_s64(below_lowest, k, lowest[h]);
                rows[h] = vaddq_s64(rows[h], four);
            }
        }
        int64_t keys[8], best = none, second = none;
        for (int h = 0; h < 2; h++) {
            vst1q_s64(keys + 4 * h, lowest[h]);
            vst1q_s64(keys + 4 * h + 2, next[h]);
        }
        for (int t = 0; t < 8; t++) keep_two(keys[t], &best, &second);
        keep_tail_256(ai, bt, m, m4, &best, &second);
        write_two(best, second, none, dist + 2 * i, index + 2 * i);
    }
    return 0;
}
#endif

/* a (n, w) query rows; bt (w, m) the searched rows transposed; dist, index (n, 2) pre-filled by the
 * caller for a missing second neighbour. Returns 0, or -1 when out of memory. */
API int nearest_two(const uint64_t *a, const uint64_t *bt, int32_t *dist, int32_t *index, int64_t n, int64_t w,
                    int64_t m) {
#if HAVE_DISPATCH
    __builtin_cpu_init();
    if (w == 4 && __builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512vpopcntdq"))
        return nearest_two_avx512_256(a, bt, dist, index, n, m);
    if (w == 4 && __builtin_cpu_supports("avx2") && __builtin_cpu_supports("popcnt"))
        return nearest_two_avx2_256(a, bt, dist, index, n, m);
    if (__builtin_cpu_supports("popcnt")) return nearest_two_popcnt(a, bt, dist, index, n, w, m);
#endif
#if HAVE_NEON
    if (w == 4) return nearest_two_neon_256(a, bt, dist, index, n, m);
#endif
    return nearest_two_generic(a, bt, dist, index, n, w, m);
}

/* ---- same-word matching (word_matches.py) ---- */

static int64_t search_left(const int64_t *v, int64_t n, int64_t x) {
    int64_t lo = 0, hi = n;
    while (lo < hi) {
        int64_t mid = lo + (hi - lo) / 2;
        if (v[mid] < x) lo = mid + 1; else hi = mid;
    }
    return lo;
}

static int64_t search_right(const int64_t *v, int64_t n, int64_t x) {
    int64_t lo = 0, hi = n;
    while (lo < hi) {
        int64_t mid = lo + (hi - lo) / 2;
        if (v[mid] <= x) lo = mid + 1; else hi = mid;
    }
    return lo;
}

#define SAME_WORD_BODY                                                                                \
    const int64_t far = (int64_t)1 << 62;                                                             \
    int64_t *best_d = (int64_t *)malloc((size_t)(m > 0 ? m : 1) * sizeof(int64_t));                    \
    int64_t *best_q = (int64_t *)malloc((size_t)(m > 0 ? m : 1) * sizeof(int64_t));                    \
    if (!best_d || !best_q) { free(best_d); free(best_q); return -1; }                                \
    for (int64_t j = 0; j < m; j++) { best_d[j] = far; best_q[j] = -1; }                              \
    for (int64_t i = 0; i < n; i++) {                                                                 \
        int64_t word = qw[i];                                                                         \
        if (word < 0) continue;                                                                       \
        int64_t lo = search_left(pw, m, word), hi = search_right(pw, m, word);                        \
        if (lo == hi) continue;                                                                       \
        int64_t d1 = far, d2 = far, p1 = -1;                                                          \
        for (int64_t k = lo; k < hi; k++) {                                                           \
            int64_t j = order[k], d = 0;                                                              \
            for (int64_t b = 0; b < w; b++) d += __builtin_popcountll(qd[i * w + b] ^ pd[j * w + b]);  \
            if (d < d1) { d2 = d1; d1 = d; p1 = j; }                                                  \
            else if (d < d2) d2 = d;                                                                  \
        }                                                                                             \
        float f1 = (float)d1;                                                                         \
        float bar = hi - lo > 1 ? ratio * (float)d2 : INFINITY;                                       \
        if (f1 <= cap && f1 < bar && d1 < best_d[p1]) { best_d[p1] = d1; best_q[p1] = i; }            \
    }                                                                                                 \
    int64_t count = 0;                                                                                \
    for (int64_t j = 0; j < m; j++)                                                                   \
        if (best_q[j] >= 0) { out[2 * count] = best_q[j]; out[2 * count + 1] = j; count++; }          \
    free(best_d);                                                                                     \
    free(best_q);                                                                                     \
    return count;

static int64_t same_word_generic(const int64_t *qw, const uint64_t *qd, const int64_t *pw, const int64_t *order,
                                 const uint64_t *pd, float cap, float ratio, int64_t *out, int64_t n, int64_t w,
                                 int64_t m) {
    SAME_WORD_BODY
}

#if HAVE_DISPATCH
static POPCNT_TARGET int64_t same_word_popcnt(const int64_t *qw, const uint64_t *qd, const int64_t *pw,
                                              const int64_t *order, const uint64_t *pd, float cap, float ratio,
                                              int64_t *out, int64_t n, int64_t w, int64_t m) {
    SAME_WORD_BODY
}
#endif

/* qw (n,) query words (negative: none); qd (n, w); pw (m,) sorted place words; order (m,); pd (m, w);
 * out (min(n, m), 2). Returns the number of matches written, or -1 when out of memory. */
API int64_t same_word(const int64_t *qw, const uint64_t *qd, const int64_t *pw, const int64_t *order,
                      const uint64_t *pd, float cap, float ratio, int64_t *out, int64_t n, int64_t w, int64_t m) {
#if HAVE_DISPATCH
    __builtin_cpu_init();
    if (__builtin_cpu_supports("popcnt")) return same_word_popcnt(qw, qd, pw, order, pd, cap, ratio, out, n, w, m);
#endif
    return same_word_generic(qw, qd, pw, order, pd, cap, ratio, out, n, w, m);
}

/* ---- one match per location (verification.py, distinct_matches) ---- */

typedef struct { int64_t key, index; } keyed;

static int by_key_then_index(const void *x, const void *y) {
    const keyed *a = (const keyed *)x, *b = (const keyed *)y;
    if (a->key != b->key) return a->key < b->key ? -1 : 1;
    return a->index < b->index ? -1 : (a->index > b->index);
}

/* xq, xp (k, 2); offsets (4, 2); keep (k,) starts all 1. Returns 0, or -1 when out of memory. */
API int distinct(const double *xq, const double *xp, double radius_q, double radius_p, const double *offsets,
                 uint8_t *keep, int64_t k) {
    keyed *cells = (keyed *)malloc((size_t)(k > 0 ? k : 1) * sizeof(keyed));
    if (!cells) return -1;
    for (int g = 0; g < 8; g++) {
        const double *x = g < 4 ? xq : xp;
        double r = g < 4 ? radius_q : radius_p;
        double ox = offsets[2 * (g % 4)], oy = offsets[2 * (g % 4) + 1];
        for (int64_t i = 0; i < k; i++) {
            double cx = fmin(fmax(floor(x[2 * i] / r + ox), 0.0), 32767.0);
            double cy = fmin(fmax(floor(x[2 * i + 1] / r + oy), 0.0), 32767.0);
            cells[i].key = ((int64_t)cx << 15) + (int64_t)cy;
            cells[i].index = i;
        }
        /* (key, index) order is the stable sort by key */
        qsort(cells, (size_t)k, sizeof(keyed), by_key_then_index);
        for (int64_t t = 1; t < k; t++)
            if (cells[t].key == cells[t - 1].key) keep[cells[t].index] = 0;
    }
    free(cells);
    return 0;
}

/* ---- per-match model errors (model_errors.py) ---- */

/* H, Hi (3, 3); src, dst (k, 2); out (k,). */
API void transfer_errors(const double *H, const double *Hi, const double *src, const double *dst, double *out,
                         int64_t k) {
    for (int64_t i = 0; i < k; i++) {
        double x = src[2 * i], y = src[2 * i + 1], qx = dst[2 * i], qy = dst[2 * i + 1];
        double w = H[6] * x + H[7] * y + H[8];
        double u = (H[0] * x + H[1] * y + H[2]) / w - qx;
        double v = (H[3] * x + H[4] * y + H[5]) / w - qy;
        double forward = sqrt(u * u + v * v);
        w = Hi[6] * qx + Hi[7] * qy + Hi[8];
        u = (Hi[0] * qx + Hi[1] * qy + Hi[2]) / w - x;
        v = (Hi[3] * qx + Hi[4] * qy + Hi[5]) / w - y;
        double backward = sqrt(u * u + v * v);
        out[i] = isfinite(forward) && isfinite(backward) ? (forward >= backward ? forward : backward) : INFINITY;
    }
}

/* F (3, 3); xq, xp (k, 2); out (k,). */
API void epipolar_errors(const double *F, const double *xq, const double *xp, double min_normal, double *out,
                         int64_t k) {
    for (int64_t i = 0; i < k; i++) {
        double qx = xq[2 * i], qy = xq[2 * i + 1], px = xp[2 * i], py = xp[2 * i + 1];
        double a = px * F[0] + py * F[1] + F[2];
        double b = px * F[3] + py * F[4] + F[5];
        double c = px * F[6] + py * F[7] + F[8];
        double d = qx * F[0] + qy * F[3] + F[6];
        double e = qx * F[1] + qy * F[4] + F[7];
        double num = fabs(qx * a + qy * b + c);
        double nq = hypot(a, b), np_ = hypot(d, e);
        double err = INFINITY;
        if (nq > min_normal && np_ > min_normal) {
            double s = num / nq, t = num / np_;
            err = s >= t ? s : t;
        }
        out[i] = isfinite(err) ? err : INFINITY;
    }
}

/* ---- the int8 vocabulary search's selection and re-rank (bit_centroids.py) ---- */

/* The two passes over each row of products (z + hi in place, the floor max_j (z_j + lo_j), then the
 * candidates above it, whose id is the word when there is one): written so that they vectorise,
 * with AVX-512 and AVX2 clones on x86-64. `where` is unsigned: it is the word only when count is 1 (and may
 * wrap otherwise). */
#if HAVE_DISPATCH
__attribute__((target_clones("avx512f", "avx2", "default")))
#endif
static void select_rows(int32_t *products, const int32_t *upper_offset, const int32_t *width, int32_t *best,
                        int32_t *floors, int64_t n, int64_t k) {
    for (int64_t i = 0; i < n; i++) {
        int32_t *upper = products + i * k;
        int32_t floor_ = -2147483647;
        for (int64_t j = 0; j < k; j++) {
            int32_t u = upper[j] + upper_offset[j];
            upper[j] = u;
            int32_t low = u - width[j];
            floor_ = low > floor_ ? low : floor_;
        }
        uint32_t count = 0, where = 0;
        for (int64_t j = 0; j < k; j++) {
            uint32_t inside = upper[j] >= floor_;
            count += inside;
            where += (uint32_t)j * inside;
        }
        best[i] = count == 1 ? (int32_t)where : -1;
        floors[i] = floor_;
    }
}

/* products (n, k) int32, overwritten with z + hi; upper_offset, width (k,); bits (n, d) 0/1;
 * centroids (k, d) float32; half_sq_norms (k,); best (n,). Returns 0, or -1 when out of memory. */
API int select_words(int32_t *products, const int32_t *upper_offset, const int32_t *width, const uint8_t *bits,
                     const float *centroids, const double *half_sq_norms, int32_t *best, int64_t n, int64_t k,
                     int64_t d) {
    int32_t *floors = (int32_t *)malloc((size_t)(n > 0 ? n : 1) * sizeof(int32_t));
    if (!floors) return -1;
    select_rows(products, upper_offset, width, best, floors, n, k);
    for (int64_t i = 0; i < n; i++) {
        if (best[i] >= 0) continue;
        const int32_t *upper = products + i * k;
        const uint8_t *x = bits + i * d;
        double top = -INFINITY;
        int64_t arg = 0;
        for (int64_t j = 0; j < k; j++) {
            if (upper[j] < floors[i]) continue;
            const float *c = centroids + j * d;
            double s = 0.0; /* float64 sum of float32 centroid values, in bit order */
            for (int64_t t = 0; t < d; t++) s += (double)c[t] * (double)x[t];
            s -= half_sq_norms[j];
            if (s > top) { top = s; arg = j; }
        }
        best[i] = (int32_t)arg;
    }
    free(floors);
    return 0;
}


/* ---- ORB descriptors of detected keypoints, oriented and upright (features/orb_description.py) ---- */

/* To nearest, ties to even, as OpenCV's cvRound in the default rounding mode: adding and removing
 * 1.5 * 2^23 leaves a float of magnitude under 2^22 rounded to an integer (no libm call, vectorisable). */
static inline float round_even(float v) {
    const float shift = 12582912.0f; /* built without -ffast-math: the two steps are kept */
    return (v + shift) - shift;
}

/* levels: n_levels addresses of the blurred pyramid levels (uint8, row strides `steps`, sizes rows x cols);
 * inv_scale (n_levels,) float32: 1 / the level's scale; x, y (n,) float32: keypoint positions on level 0;
 * angle (n,) float32 degrees; octave (n,) int32; pattern (pairs, 4) int32: x1, y1, x2, y2 of each bit's
 * pair around the centre, bit j of byte j / 8 at position j % 8; oriented / upright: (n, pairs / 8) uint8
 * outputs, either may be NULL. Bit j is 1 when the level's value at the first point is below the value
 * at the second (oriented: the points turned by the keypoint's angle in float32, as OpenCV's ORB turns
 * them). Returns the number of keypoints whose points leave their level (their rows are zero), -1 when
 * out of memory, -2 for an octave outside the levels. The points' turn vectorises: AVX-512 and AVX2
 * clones on x86-64 (no fused multiply-add in any: the library is built with -ffp-contract=off). */
#if HAVE_DISPATCH
__attribute__((target_clones("avx512f", "avx2", "default")))
#endif
API int64_t orb_describe(const intptr_t *levels, const int64_t *steps, const int64_t *rows, const int64_t *cols,
                         int64_t n_levels, const float *inv_scale, const float *x, const float *y, const float *angle,
                         const int32_t *octave, int64_t n, const int32_t *pattern, int64_t pairs, uint8_t *oriented,
                         uint8_t *upright) {
    const int64_t width = pairs / 8, points = 2 * pairs;
    const float to_radians = (float)(3.14159265358979323846 / 180.f);
    float *px = (float *)malloc((size_t)points * sizeof(float)), *py = (float *)malloc((size_t)points * sizeof(float));
    int32_t *offset = (int32_t *)malloc((size_t)points * sizeof(int32_t));
    if (!px || !py || !offset) {
        free(px); free(py); free(offset);
        return -1;
    }
    int reach = 0; /* every turned point lies within max |x| + max |y| of the centre */
    for (int64_t j = 0; j < points; j++) {
        px[j] = (float)pattern[2 * j];
        py[j] = (float)pattern[2 * j + 1];
        int r = abs(pattern[2 * j]) + abs(pattern[2 * j + 1]);
        reach = r > reach ? r : reach;
    }
    reach += 1;
    int64_t outside = 0;
    for (int64_t i = 0; i < n; i++) {
        int32_t o = octave[i];
        if (o < 0 || o >= n_levels) {
            free(px); free(py); free(offset);
            return -2;
        }
        const int64_t step = steps[o];
        const int cx = (int)round_even(x[i] * inv_scale[o]), cy = (int)round_even(y[i] * inv_scale[o]);
        uint8_t *d_or = oriented ? oriented + i * width : NULL;
        uint8_t *d_up = upright ? upright + i * width : NULL;
        if (cx - reach < 0 || cy - reach < 0 || cx + reach >= cols[o] || cy + reach >= rows[o]) {
            if (d_or) memset(d_or, 0, (size_t)width);
            if (d_up) memset(d_up, 0, (size_t)width);
            outside++;
            continue;
        }
        const uint8_t *center = (const uint8_t *)levels[o] + cy * step + cx;
        if (d_or) {
            const float rad = angle[i] * to_radians;
            const float a = (float)cos((double)rad), b = (float)sin((double)rad);
            for (int64_t j = 0; j < points; j++) {
                const float tx = px[j] * a - py[j] * b, ty = px[j] * b + py[j] * a;
                offset[j] = (int32_t)round_even(ty) * (int32_t)step + (int32_t)round_even(tx);
            }
            for (int64_t byte = 0; byte < width; byte++) {
                unsigned v = 0;
                const int32_t *off = offset + byte * 16;
                for (int k = 0; k < 8; k++) v |= (unsigned)(center[off[2 * k]] < center[off[2 * k + 1]]) << k;
                d_or[byte] = (uint8_t)v;
            }
        }
        if (d_up) {
            for (int64_t byte = 0; byte < width; byte++) {
                unsigned v = 0;
                for (int k = 0; k < 8; k++) {
                    const int32_t *p = pattern + (byte * 8 + k) * 4;
                    v |= (unsigned)(center[p[1] * step + p[0]] < center[p[3] * step + p[2]]) << k;
                }
                d_up[byte] = (uint8_t)v;
            }
        }
    }
    free(px); free(py); free(offset);
    return outside;
}


/* ---- ORB keypoints of one pyramid (features/orb_levels.py): FAST-9, Harris, orientation ---- */

/* The 16 pixels of FAST's circle of radius 3, in circle order (OpenCV's offsets16). */
static const int fast_ring[16][2] = {{0, 3}, {1, 3}, {2, 2}, {3, 1}, {3, 0}, {3, -1}, {2, -2}, {1, -3},
                                     {0, -3}, {-1, -3}, {-2, -2}, {-3, -1}, {-3, 0}, {-3, 1}, {-2, 2}, {-1, 3}};

typedef uint8_t u8x64 __attribute__((vector_size(64)));

/* FAST-9 (OpenCV's FAST with TYPE_9_16 and non-maximum suppression). A pixel is a corner when its
 * circle of 16 holds an arc of 9 pixels all brighter than centre + threshold, or all darker than
 * centre - threshold; its score (OpenCV's cornerScore<16>) is the largest such threshold less 1:
 * the larger, over the 16 arcs of each side, of the arc's smallest difference to the centre, less 1.
 * Computed 64 pixels at a time, byte-wise: the differences clamped at 0 (an arc whose minimum is
 * below the threshold is no corner either way), each arc's minimum by doubling (pairs, fours,
 * eights, then the ninth). A block where no two neighbouring compass pixels (0, 4, 8, 12 of the
 * circle) pass the threshold on one side holds no arc of 9 and is skipped.
 *
 * block_corners: pixels p[0 .. width - 1] (width <= 64) of an image whose circle offsets are
 * `ring`; writes each one's score (0 where no corner) to out[0 .. width - 1], unless the block is
 * skipped (out is left as it is: zeros); returns the corners as bits (bit k: pixel k). */
typedef uint64_t (*block_corners_fn)(const uint8_t *p, const int32_t *ring, int64_t width, int threshold, uint8_t *out);

#define U8_MIN(a, b) ((b) ^ (((a) ^ (b)) & (u8x64)((a) < (b))))
#define U8_MAX(a, b) ((b) ^ (((a) ^ (b)) & (u8x64)((a) > (b))))
#define U8_SUBS(a, b) (((a) - (b)) & (u8x64)((a) > (b)))

static inline void load_u8x64(u8x64 *out, const uint8_t *p, int64_t width) {
    if (width == 64) {
        memcpy(out, p, 64);
    } else {
        *out = (u8x64){0};
        memcpy(out, p, (size_t)width);
    }
}

static uint64_t block_corners_generic(const uint8_t *p, const int32_t *ring, int64_t width, int threshold,
                                      uint8_t *out) {
    const u8x64 t = (u8x64){0} + (uint8_t)threshold, one = (u8x64){0} + 1;
    u8x64 v, x, bright[16], dark[16];
    load_u8x64(&v, p, width);
    for (int c = 0; c < 16; c++) {
        load_u8x64(&x, p + ring[c], width);
        bright[c] = U8_SUBS(x, v);
        dark[c] = U8_SUBS(v, x);
    }
    const u8x64 maybe = ((u8x64)(U8_MIN(U8_MAX(bright[0], bright[8]), U8_MAX(bright[4], bright[12])) > t)) |
                        ((u8x64)(U8_MIN(U8_MAX(dark[0], dark[8]), U8_MAX(dark[4], dark[12])) > t));
    uint64_t lanes[8], any = 0;
    memcpy(lanes, &maybe, 64);
    for (int w = 0; w < 8; w++) any |= lanes[w];
    if (!any) return 0;
    u8x64 best = {0};
    for (int side = 0; side < 2; side++) {
        const u8x64 *d = side ? dark : bright;
        u8x64 m2[16], m4[16];
        for (int k = 0; k < 16; k++) m2[k] = U8_MIN(d[k], d[(k + 1) & 15]);
        for (int k = 0; k < 16; k++) m4[k] = U8_MIN(m2[k], m2[(k + 2) & 15]);
        for (int k = 0; k < 16; k++) {
            const u8x64 m8 = U8_MIN(m4[k], m4[(k + 4) & 15]);
            best = U8_MAX(best, U8_MIN(m8, d[(k + 8) & 15]));
        }
    }
    const u8x64 corner = (u8x64)(best > t), value = (best - one) & corner;
    memcpy(out, &value, (size_t)width);
    memcpy(lanes, &corner, 64);
    uint64_t bits = 0;
    for (int w = 0; w < 8; w++) /* the top bit of each byte, gathered into one byte */
        bits |= (((lanes[w] & 0x8080808080808080ULL) * 0x0002040810204081ULL) >> 56) << (8 * w);
    return width == 64 ? bits : bits & ((1ULL << width) - 1);
}

#if HAVE_DISPATCH
static __attribute__((target("avx512f,avx512bw"))) uint64_t block_corners_avx512(
        const uint8_t *p, const int32_t *ring, int64_t width, int threshold, uint8_t *out) {
    const __mmask64 inside = width == 64 ? ~(__mmask64)0 : (((__mmask64)1 << width) - 1);
    const __m512i t = _mm512_set1_epi8((char)threshold), one = _mm512_set1_epi8(1);
    const __m512i v = _mm512_maskz_loadu_epi8(inside, p);
    __m512i bright[16], dark[16];
    for (int c = 0; c < 16; c += 4) {
        const __m512i x = _mm512_maskz_loadu_epi8(inside, p + ring[c]);
        bright[c] = _mm512_subs_epu8(x, v);
        dark[c] = _mm512_subs_epu8(v, x);
    }
    const __mmask64 maybe =
        _mm512_cmpgt_epu8_mask(_mm512_min_epu8(_mm512_max_epu8(bright[0], bright[8]), _mm512_max_epu8(bright[4], bright[12])), t) |
        _mm512_cmpgt_epu8_mask(_mm512_min_epu8(_mm512_max_epu8(dark[0], dark[8]), _mm512_max_epu8(dark[4], dark[12])), t);
    if (!maybe) return 0;
    for (int c = 0; c < 16; c++) {
        if ((c & 3) == 0) continue;
        const __m512i x = _mm512_maskz_loadu_epi8(inside, p + ring[c]);
        bright[c] = _mm512_subs_epu8(x, v);
        dark[c] = _mm512_subs_epu8(v, x);
    }
    __m512i best = _mm512_setzero_si512();
    for (int side = 0; side < 2; side++) {
        const __m512i *d = side ? dark : bright;
        __m512i m2[16], m4[16];
        for (int k = 0; k < 16; k++) m2[k] = _mm512_min_epu8(d[k], d[(k + 1) & 15]);
        for (int k = 0; k < 16; k++) m4[k] = _mm512_min_epu8(m2[k], m2[(k + 2) & 15]);
        for (int k = 0; k < 16; k++)
            best = _mm512_max_epu8(best, _mm512_min_epu8(_mm512_min_epu8(m4[k], m4[(k + 4) & 15]), d[(k + 8) & 15]));
    }
    const __mmask64 corner = _mm512_cmpgt_epu8_mask(best, t) & inside;
    _mm512_mask_storeu_epi8(out, inside, _mm512_maskz_sub_epi8(corner, best, one));
    return corner;
}
#endif

/* FAST-9 corners of an rows x cols image (row stride `step`) kept by non-maximum suppression, as
 * OpenCV finds them (a corner kept when its score exceeds each of its 8 neighbours', 0 where no
 * corner), of those at least `border` (>= 4) pixels inside every edge, as ORB keeps them: only
 * they and their neighbours are searched. score (rows x cols) and cand_i, cand_j (rows x cols) are
 * scratch; xs, ys, scores receive the corners in row-major order. Returns their number. portable:
 * the GCC-vector form even where AVX-512BW runs. */
static int64_t fast9(const uint8_t *img, int64_t step, int64_t rows, int64_t cols, int threshold, int64_t border,
                     uint8_t *score, int32_t *cand_i, int32_t *cand_j, int32_t *xs, int32_t *ys, uint8_t *scores,
                     int portable) {
    block_corners_fn block_corners = block_corners_generic;
#if HAVE_DISPATCH
    if (!portable && __builtin_cpu_supports("avx512bw")) block_corners = block_corners_avx512;
#else
    (void)portable;
#endif
    int32_t ring[16];
    for (int k = 0; k < 16; k++) ring[k] = (int32_t)(fast_ring[k][0] + fast_ring[k][1] * step);
    memset(score, 0, (size_t)(rows * cols));
    /* the searched band: the kept corners' rows and columns and one more on each side */
    const int64_t lo = border - 1, hi_row = rows - border + 1, hi_col = cols - border + 1;
    int64_t n_cand = 0;
    for (int64_t i = lo; i < hi_row; i++) {
        for (int64_t j0 = lo; j0 < hi_col; j0 += 64) {
            const int64_t width = hi_col - j0 < 64 ? hi_col - j0 : 64;
            uint64_t bits = block_corners(img + i * step + j0, ring, width, threshold, score + i * cols + j0);
            while (bits) {
                cand_i[n_cand] = (int32_t)i;
                cand_j[n_cand++] = (int32_t)(j0 + __builtin_ctzll(bits));
                bits &= bits - 1;
            }
        }
    }
    int64_t n = 0;
    for (int64_t c = 0; c < n_cand; c++) {
        const int64_t i = cand_i[c], j = cand_j[c], at = i * cols + j;
        const uint8_t s = score[at];
        const uint8_t *up = score + at - cols, *down = score + at + cols;
        /* branch-free: whether a corner is kept is unpredictable */
        const int kept = (s > up[-1]) & (s > up[0]) & (s > up[1]) & (s > score[at - 1]) & (s > score[at + 1]) &
                         (s > down[-1]) & (s > down[0]) & (s > down[1]) & (i > lo) & (i < hi_row - 1) &
                         (j > lo) & (j < hi_col - 1);
        xs[n] = (int32_t)j;
        ys[n] = (int32_t)i;
        scores[n] = s;
        n += kept;
    }
    return n;
}

/* The k-th largest (k >= 1) of a[0 .. n - 1] (n >= k), reordering a (Hoare's selection). */
static float kth_largest(float *a, int64_t n, int64_t k) {
    int64_t lo = 0, hi = n - 1, want = k - 1;
    while (lo < hi) {
        const float pivot = a[lo + (hi - lo) / 2];
        int64_t i = lo, j = hi;
        while (i <= j) {
            while (a[i] > pivot) i++;
            while (a[j] < pivot) j--;
            if (i <= j) {
                const float swap = a[i];
                a[i] = a[j];
                a[j] = swap;
                i++;
                j--;
            }
        }
        if (want <= j) hi = j;
        else if (want >= i) lo = i;
        else break; /* a[want] equals the pivot */
    }
    return a[want];
}

/* atan2 in degrees [0, 360) as OpenCV's fastAtan2 computes it (a polynomial, float arithmetic). */
static float fast_atan2(float y, float x) {
    const float p1 = 0.9997878412794807f * (float)(180 / 3.14159265358979323846);
    const float p3 = -0.3258083974640975f * (float)(180 / 3.14159265358979323846);
    const float p5 = 0.1555786518463281f * (float)(180 / 3.14159265358979323846);
    const float p7 = -0.04432655554792128f * (float)(180 / 3.14159265358979323846);
    const float eps = (float)2.220446049250313080847e-16;
    const float ax = fabsf(x), ay = fabsf(y);
    float a, c, c2;
    if (ax >= ay) {
        c = ay / (ax + eps);
        c2 = c * c;
        a = (((p7 * c2 + p5) * c2 + p3) * c2 + p1) * c;
    } else {
        c = ax / (ay + eps);
        c2 = c * c;
        a = 90.f - (((p7 * c2 + p5) * c2 + p3) * c2 + p1) * c;
    }
    if (x < 0) a = 180.f - a;
    if (y < 0) a = 360.f - a;
    return a;
}

/* ORB's Harris response at a pixel (OpenCV's HarrisResponses: a 7 x 7 block of Sobel gradients,
 * k = 0.04, scaled by (4 * 7 * 255)^-4; integer sums, then float32 in OpenCV's order). */
static inline float harris_response(const uint8_t *center, int64_t step) {
    const float harris_k = 0.04f, scale = 1.f / ((1 << 2) * 7 * 255.f);
    const float scale_sq_sq = scale * scale * scale * scale;
    int a = 0, b = 0, c = 0;
    for (int r = -3; r <= 3; r++) {
        for (int q = -3; q <= 3; q++) {
            const uint8_t *p = center + r * step + q;
            const int ix = (p[1] - p[-1]) * 2 + (p[-step + 1] - p[-step - 1]) + (p[step + 1] - p[step - 1]);
            const int iy = (p[step] - p[-step]) * 2 + (p[step - 1] - p[-step - 1]) + (p[step + 1] - p[-step + 1]);
            a += ix * ix;
            b += iy * iy;
            c += ix * iy;
        }
    }
    const float fa = (float)a, fb = (float)b, fc = (float)c;
    const float det = fa * fb - fc * fc, sum = fa + fb;
    const float k_sum = harris_k * sum;
    return (det - k_sum * sum) * scale_sq_sq;
}

/* ORB's orientation at a pixel (OpenCV's ICAngles): the angle (degrees, fastAtan2) of the
 * intensity centroid over the disc of radius half_patch whose row v spans |u| <= umax[v]. */
static inline float centroid_angle(const uint8_t *center, int64_t step, int64_t half_patch, const int32_t *umax) {
    int m01 = 0, m10 = 0;
    for (int64_t u = -half_patch; u <= half_patch; u++) m10 += (int)u * center[u];
    for (int64_t v = 1; v <= half_patch; v++) {
        int v_sum = 0;
        const int64_t d = umax[v];
        for (int64_t u = -d; u <= d; u++) {
            const int plus = center[u + v * step], minus = center[u - v * step];
            v_sum += plus - minus;
            m10 += (int)u * (plus + minus);
        }
        m01 += (int)v * v_sum;
    }
    return fast_atan2((float)m01, (float)m10);
}

/* cv2.ORB's keypoints (Harris score) of each level of a pyramid, as a one-level cv2.ORB finds them
 * on the level's crop (features/orb_levels.py): FAST-9 corners (`fast9`) at least `edge` pixels
 * inside the crop; when more than 2 * budget, those scoring at least the 2 * budget-th score; their
 * Harris responses (7 x 7 block, k = 0.04, OpenCV's scaling); when more than budget, those at least
 * the budget-th response; their intensity-centroid angles over the disc of radius half_patch
 * (umax: the disc's half-width per row, half_patch + 1 rows). levels, steps, rows, cols: the
 * pyramid (uint8); crop: pixels left out at each edge of every level; budgets (n_levels,).
 * Out (capacity rows): x, y (int32, level pixels), response, angle (float32), level (int32).
 * portable: FAST's GCC-vector form even where its AVX-512BW form runs (tests compare them).
 * Returns the number of keypoints, -1 when out of memory, -2 when edge, crop, half_patch or umax
 * would read outside a level, -3 when more than capacity. */
#if HAVE_DISPATCH
__attribute__((target_clones("arch=x86-64-v4", "avx2", "default")))
#endif
API int64_t orb_keypoints(const intptr_t *levels, const int64_t *steps, const int64_t *rows, const int64_t *cols,
                          int64_t n_levels, int64_t crop, int64_t edge, int64_t threshold, const int64_t *budgets,
                          int64_t half_patch, const int32_t *umax, int64_t capacity, int32_t *out_x,
                          int32_t *out_y, float *out_response, float *out_angle, int32_t *out_level,
                          int64_t portable) {
    int64_t largest = 0;
    for (int64_t l = 0; l < n_levels; l++) {
        const int64_t area = (rows[l] - 2 * crop) * (cols[l] - 2 * crop);
        largest = area > largest ? area : largest;
    }
    /* every read stays inside the level: FAST's circle (3) and the Harris window (4) inside the
     * crop's edge, the orientation disc (half_patch) inside the level */
    if (edge < 4 || crop + edge < half_patch) return -2;
    for (int64_t v = 0; v <= half_patch; v++)
        if (umax[v] < 0 || umax[v] > half_patch) return -2;
    if (largest <= 0) return 0;
    uint8_t *score = (uint8_t *)malloc((size_t)largest), *fast_scores = (uint8_t *)malloc((size_t)largest);
    int32_t *cand_i = (int32_t *)malloc((size_t)largest * sizeof(int32_t)), *cand_j = (int32_t *)malloc((size_t)largest * sizeof(int32_t));
    int32_t *xs = (int32_t *)malloc((size_t)largest * sizeof(int32_t)), *ys = (int32_t *)malloc((size_t)largest * sizeof(int32_t));
    float *response = (float *)malloc((size_t)largest * sizeof(float)), *sorted = (float *)malloc((size_t)largest * sizeof(float));
    if (!score || !fast_scores || !cand_i || !cand_j || !xs || !ys || !response || !sorted) {
        free(score); free(fast_scores); free(cand_i); free(cand_j); free(xs); free(ys); free(response); free(sorted);
        return -1;
    }
    int64_t total = 0, status = 0;
    for (int64_t l = 0; l < n_levels && status == 0; l++) {
        const int64_t h = rows[l] - 2 * crop, w = cols[l] - 2 * crop, step = steps[l];
        if (h <= 0 || w <= 0 || h <= 2 * edge || w <= 2 * edge) continue;
        const uint8_t *img = (const uint8_t *)levels[l] + crop * step + crop;
        /* ORB's border: x in [edge, w - edge), y in [edge, h - edge) */
        int64_t n = fast9(img, step, h, w, (int)threshold, edge, score, cand_i, cand_j, xs, ys, fast_scores,
                          (int)portable);
        /* The best 2 * budget by FAST score, every tie at the last place kept (KeyPointsFilter::retainBest). */
        const int64_t keep_fast = 2 * budgets[l];
        if (n > keep_fast) {
            int64_t counts[256] = {0};
            for (int64_t i = 0; i < n; i++) counts[fast_scores[i]]++;
            int bar = 255;
            int64_t above = counts[255];
            while (above < keep_fast && bar > 0) above += counts[--bar];
            int64_t m = 0;
            if (keep_fast > 0) {
                for (int64_t i = 0; i < n; i++) {
                    if (fast_scores[i] >= bar) {
                        xs[m] = xs[i]; ys[m] = ys[i];
                        m++;
                    }
                }
            }
            n = m;
        }
        for (int64_t i = 0; i < n; i++) response[i] = harris_response(img + ys[i] * step + xs[i], step);
        /* The best `budget` by Harris response, ties at the last place kept. */
        const int64_t keep = budgets[l];
        if (n > keep) {
            int64_t m = 0;
            if (keep > 0) {
                memcpy(sorted, response, (size_t)n * sizeof(float));
                const float bar = kth_largest(sorted, n, keep);
                for (int64_t i = 0; i < n; i++) {
                    if (response[i] >= bar) {
                        xs[m] = xs[i]; ys[m] = ys[i]; response[m] = response[i];
                        m++;
                    }
                }
            }
            n = m;
        }
        if (total + n > capacity) {
            status = -3;
            break;
        }
        for (int64_t i = 0; i < n; i++) {
            const uint8_t *center = img + ys[i] * step + xs[i];
            out_x[total] = (int32_t)(xs[i] + crop);
            out_y[total] = (int32_t)(ys[i] + crop);
            out_response[total] = response[i];
            out_angle[total] = centroid_angle(center, step, half_patch, umax);
            out_level[total] = (int32_t)l;
            total++;
        }
    }
    free(score); free(fast_scores); free(cand_i); free(cand_j); free(xs); free(ys); free(response); free(sorted);
    return status ? status : total;
}

/* ---- ORB's pyramid: OpenCV's bit-exact bilinear resize (INTER_LINEAR_EXACT), level by level ---- */

/* Source index and 8-bit fixed-point weights of each destination index along one axis: the
 * source position (d + 0.5) * src / dst - 0.5 in double, clamped to the first and last pixel (weight
 * 0 on the neighbour), its fraction rounded to 1/256 (ties to even); the weights sum to 256. next:
 * the neighbour's index (the last pixel's is itself). */
static void linear_weights(int64_t src_n, int64_t dst_n, int32_t *index, int32_t *next, int32_t *w0, int32_t *w1) {
    const double scale = (double)src_n / (double)dst_n;
    for (int64_t d = 0; d < dst_n; d++) {
        const double pos = ((double)d + 0.5) * scale - 0.5;
        const double whole = floor(pos);
        int64_t s = (int64_t)whole;
        double frac = pos - whole;
        if (s < 0) { s = 0; frac = 0.0; }
        if (s >= src_n - 1) { s = src_n - 1; frac = 0.0; }
        const int32_t c1 = (int32_t)nearbyint(frac * 256.0);
        index[d] = (int32_t)s;
        next[d] = (int32_t)(s + 1 < src_n ? s + 1 : s);
        w1[d] = c1;
        w0[d] = 256 - c1;
    }
}

/* Level l (l >= 1) of `levels` resized from level l - 1: horizontal pass to 8 fractional bits,
 * vertical pass to 16, rounded half up. Level 0 is read only. Returns 0, or -1 out of memory. */
#if HAVE_DISPATCH
__attribute__((target_clones("avx512f", "avx2", "default")))
#endif
API int64_t resize_levels(const intptr_t *levels, const int64_t *steps, const int64_t *rows, const int64_t *cols,
                          int64_t n_levels) {
    if (n_levels < 2) return 0;
    /* One set of buffers for every level, sized for the largest. */
    int64_t max_dr = 0, max_dc = 0, max_hor = 0;
    for (int64_t l = 1; l < n_levels; l++) {
        if (rows[l] > max_dr) max_dr = rows[l];
        if (cols[l] > max_dc) max_dc = cols[l];
        if (rows[l - 1] * cols[l] > max_hor) max_hor = rows[l - 1] * cols[l];
    }
    int32_t *xw = malloc((size_t)max_dc * 4 * sizeof(int32_t)), *yw = malloc((size_t)max_dr * 4 * sizeof(int32_t));
    uint16_t *hor = malloc((size_t)max_hor * sizeof(uint16_t));
    if (!xw || !yw || !hor) {
        free(xw); free(yw); free(hor);
        return -1;
    }
    for (int64_t l = 1; l < n_levels; l++) {
        const uint8_t *src = (const uint8_t *)levels[l - 1];
        uint8_t *dst = (uint8_t *)levels[l];
        const int64_t sr = rows[l - 1], sc = cols[l - 1], sstep = steps[l - 1];
        const int64_t dr = rows[l], dc = cols[l], dstep = steps[l];
        int32_t *xi = xw, *xj = xw + dc, *x0 = xw + 2 * dc, *x1 = xw + 3 * dc;
        int32_t *yi = yw, *yj = yw + dr, *y0 = yw + 2 * dr, *y1 = yw + 3 * dr;
        linear_weights(sc, dc, xi, xj, x0, x1);
        linear_weights(sr, dr, yi, yj, y0, y1);
        /* Only the source rows some destination row reads: each is passed once. */
        int64_t done = -1;
        for (int64_t y = 0; y < dr; y++) {
            for (int64_t r = yi[y]; r <= yj[y]; r++) {
                if (r <= done) continue;
                const uint8_t *s = src + r * sstep;
                uint16_t *h = hor + r * dc;
                for (int64_t x = 0; x < dc; x++)
                    h[x] = (uint16_t)((int32_t)s[xi[x]] * x0[x] + (int32_t)s[xj[x]] * x1[x]);
                done = r;
            }
            const uint16_t *h0 = hor + (int64_t)yi[y] * dc, *h1 = hor + (int64_t)yj[y] * dc;
            const int32_t a = y0[y], b = y1[y];
            uint8_t *d = dst + y * dstep;
            for (int64_t x = 0; x < dc; x++) {
                const int32_t v = ((int32_t)h0[x] * a + (int32_t)h1[x] * b + (1 << 15)) >> 16;
                d[x] = (uint8_t)(v > 255 ? 255 : v);
            }
        }
    }
    free(xw); free(yw); free(hor);
    return 0;
}


/* ---- The learned ORB descriptor (features/learned_description.py) ---- */

/* One sample's value (the module's arithmetic): position (px, py) in float32, times 32 rounded to
 * nearest even, split into a pixel and 1/32 fractions, the bilinear mix rounded; clamp: indices
 * clamped to the level (its edge repeats), else the four pixels are known to lie inside. */
static inline int32_t learned_sample(const uint8_t *image, int64_t step, int64_t last_col, int64_t last_row,
                                     float px, float py, int clamp) {
    const int32_t ax = (int32_t)round_even(px * 32.0f), ay = (int32_t)round_even(py * 32.0f);
    const int32_t fx = ax & 31, fy = ay & 31, gx = 32 - fx, gy = 32 - fy;
    int64_t x0 = ax >> 5, y0 = ay >> 5, x1 = x0 + 1, y1 = y0 + 1;
    if (clamp) {
        x0 = x0 < 0 ? 0 : (x0 > last_col ? last_col : x0);
        x1 = x1 < 0 ? 0 : (x1 > last_col ? last_col : x1);
        y0 = y0 < 0 ? 0 : (y0 > last_row ? last_row : y0);
        y1 = y1 < 0 ? 0 : (y1 > last_row ? last_row : y1);
    }
    const uint8_t *r0 = image + y0 * step, *r1 = image + y1 * step;
    return (gx * gy * r0[x0] + fx * gy * r0[x1] + gx * fy * r1[x0] + fx * fy * r1[x1] + 512) >> 10;
}

/* dots (bits,) int32 = weights . patch, weights as pairs (samples / 2, bits, 2) int16 (pairs[k][b][t] =
 * w[b][2k + t]) and the patch as (samples / 2) int32, two int16 values each (low: sample 2k). */
static void learned_dots_plain(const int16_t *pairs, const int32_t *patch_pairs, int64_t half, int64_t bits,
                               int32_t *dots) {
    for (int64_t b = 0; b < bits; b++) dots[b] = 0;
    for (int64_t k = 0; k < half; k++) {
        const int32_t p0 = (int16_t)(patch_pairs[k] & 0xffff), p1 = (int16_t)(patch_pairs[k] >> 16);
        const int16_t *w = pairs + k * bits * 2;
        for (int64_t b = 0; b < bits; b++) dots[b] += (int32_t)w[2 * b] * p0 + (int32_t)w[2 * b + 1] * p1;
    }
}

#if HAVE_DISPATCH
/* dots (4, bits) int32 of four patches, each as (samples / 2) int32 pairs (learned_dots_plain), for
 * bits a multiple of 16: sixteen bits of all four at a time, each weight load used four times. */
__attribute__((target("avx2"))) static void learned_dots_avx2x4(const int16_t *pairs, const int32_t *patch_pairs,
                                                                int64_t half, int64_t bits, int32_t *dots) {
    for (int64_t b0 = 0; b0 < bits; b0 += 16) {
        __m256i acc[4][2];
        for (int i = 0; i < 4; i++) acc[i][0] = acc[i][1] = _mm256_setzero_si256();
        for (int64_t k = 0; k < half; k++) {
            const int16_t *w = pairs + (k * bits + b0) * 2;
            const __m256i w0 = _mm256_loadu_si256((const __m256i *)w), w1 = _mm256_loadu_si256((const __m256i *)(w + 16));
            for (int i = 0; i < 4; i++) {
                const __m256i p = _mm256_set1_epi32(patch_pairs[i * half + k]);
                acc[i][0] = _mm256_add_epi32(acc[i][0], _mm256_madd_epi16(w0, p));
                acc[i][1] = _mm256_add_epi32(acc[i][1], _mm256_madd_epi16(w1, p));
            }
        }
        for (int i = 0; i < 4; i++) {
            _mm256_storeu_si256((__m256i *)(dots + i * bits + b0), acc[i][0]);
            _mm256_storeu_si256((__m256i *)(dots + i * bits + b0 + 8), acc[i][1]);
        }
    }
}
#endif

/* The patch (samples,) uint8 of a keypoint at (cx, cy) on its level, turned by (c, s); returns its
 * sum. Sample k sits at (c u - s v + cx, s u + c v + cy) in float32, the operations in that order. */
static int64_t learned_patch(const uint8_t *image, int64_t step, int64_t last_col, int64_t last_row, float cx,
                             float cy, float c, float s, const float *grid_u, const float *grid_v, int64_t samples,
                             int clamp, uint8_t *patch) {
    int64_t sum = 0;
    for (int64_t k = 0; k < samples; k++) {
        const float u = grid_u[k], w = grid_v[k];
        const float px = (c * u - s * w) + cx, py = (s * u + c * w) + cy;
        const int32_t v = learned_sample(image, step, last_col, last_row, px, py, clamp);
        patch[k] = (uint8_t)v;
        sum += v;
    }
    return sum;
}

#if HAVE_DISPATCH
#define LEARNED_VNNI_TARGET __attribute__((target("avx512f,avx512bw,avx512dq,avx512vnni,avx2")))

/* learned_patch for samples a multiple of 16 and a keypoint whose every sample's four pixels and
 * the two bytes after them lie inside the level (no clamp; offsets fit int32): 16 samples at a time,
 * the same float32 operations (no fused multiply-add: -ffp-contract=off), rounding to nearest even
 * (as round_even below 2^22), and the same integer bilinear mix; each row's two pixels come from
 * one 4-byte gather. */
static LEARNED_VNNI_TARGET int64_t learned_patch_avx512(const uint8_t *image, int64_t step, float cx, float cy,
                                                        float c, float s, const float *grid_u, const float *grid_v,
                                                        int64_t samples, uint8_t *patch) {
    const __m512 vc = _mm512_set1_ps(c), vs = _mm512_set1_ps(s), vx = _mm512_set1_ps(cx), vy = _mm512_set1_ps(cy);
    const __m512 v32 = _mm512_set1_ps(32.0f);
    const __m512i vstep = _mm512_set1_epi32((int32_t)step), m31 = _mm512_set1_epi32(31), m255 = _mm512_set1_epi32(255);
    const __m512i full = _mm512_set1_epi32(32), half = _mm512_set1_epi32(512);
    __m512i total = _mm512_setzero_si512();
    for (int64_t k = 0; k < samples; k += 16) {
        const __m512 u = _mm512_loadu_ps(grid_u + k), w = _mm512_loadu_ps(grid_v + k);
        const __m512 px = _mm512_add_ps(_mm512_sub_ps(_mm512_mul_ps(vc, u), _mm512_mul_ps(vs, w)), vx);
        const __m512 py = _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(vs, u), _mm512_mul_ps(vc, w)), vy);
        const __m512i ax = _mm512_cvt_roundps_epi32(_mm512_mul_ps(px, v32), _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
        const __m512i ay = _mm512_cvt_roundps_epi32(_mm512_mul_ps(py, v32), _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
        const __m512i fx = _mm512_and_si512(ax, m31), fy = _mm512_and_si512(ay, m31);
        const __m512i gx = _mm512_sub_epi32(full, fx), gy = _mm512_sub_epi32(full, fy);
        const __m512i at = _mm512_add_epi32(_mm512_mullo_epi32(_mm512_srai_epi32(ay, 5), vstep), _mm512_srai_epi32(ax, 5));
        const __m512i r0 = _mm512_i32gather_epi32(at, (const void *)image, 1);
        const __m512i r1 = _mm512_i32gather_epi32(_mm512_add_epi32(at, vstep), (const void *)image, 1);
        const __m512i top = _mm512_add_epi32(_mm512_mullo_epi32(gx, _mm512_and_si512(r0, m255)),
                                             _mm512_mullo_epi32(fx, _mm512_and_si512(_mm512_srli_epi32(r0, 8), m255)));
        const __m512i bottom = _mm512_add_epi32(_mm512_mullo_epi32(gx, _mm512_and_si512(r1, m255)),
                                                _mm512_mullo_epi32(fx, _mm512_and_si512(_mm512_srli_epi32(r1, 8), m255)));
        const __m512i v = _mm512_srai_epi32(_mm512_add_epi32(_mm512_add_epi32(_mm512_mullo_epi32(gy, top),
                                                                              _mm512_mullo_epi32(fy, bottom)), half), 10);
        total = _mm512_add_epi32(total, v);
        _mm_storeu_si128((__m128i *)(patch + k), _mm512_cvtepi32_epi8(v));
    }
    return (int64_t)_mm512_reduce_add_epi32(total);
}

/* dots (4, bits) int32 of four patches (4, samples) uint8 with the weights as quads (samples / 4,
 * bits, 4) int8 (quads[k][b][t] = w[b][4k + t]), for bits a multiple of 64: 64 bits of all four at a
 * time in sixteen accumulators, each weight load used four times. Exact: each instruction adds four
 * uint8 x int8 products to an int32 without saturation. */
static LEARNED_VNNI_TARGET void learned_dots_vnni4(const int8_t *quads, const uint8_t *patches, int64_t samples,
                                                   int64_t bits, int32_t *dots) {
    for (int64_t b0 = 0; b0 < bits; b0 += 64) {
        __m512i acc[4][4];
        for (int i = 0; i < 4; i++)
            for (int j = 0; j < 4; j++) acc[i][j] = _mm512_setzero_si512();
        for (int64_t k = 0; k < samples / 4; k++) {
            const int8_t *w = quads + (k * bits + b0) * 4;
            __m512i wq[4];
            for (int j = 0; j < 4; j++) wq[j] = _mm512_loadu_si512((const void *)(w + 64 * j));
            for (int i = 0; i < 4; i++) {
                int32_t four;
                memcpy(&four, patches + i * samples + 4 * k, 4);
                const __m512i p = _mm512_set1_epi32(four);
                for (int j = 0; j < 4; j++) acc[i][j] = _mm512_dpbusd_epi32(acc[i][j], p, wq[j]);
            }
        }
        for (int i = 0; i < 4; i++)
            for (int j = 0; j < 4; j++) _mm512_storeu_si512((void *)(dots + i * bits + b0 + 16 * j), acc[i][j]);
    }
}

/* learned_bits (below) for bits a multiple of 8: eight comparisons in int64 give one byte. */
static LEARNED_VNNI_TARGET void learned_bits_avx512(const int32_t *dots, int64_t sum, const int64_t *row_sums,
                                                    int64_t samples, int64_t bits, uint8_t *d) {
    const __m512i vs = _mm512_set1_epi64(samples), vsum = _mm512_set1_epi64(sum);
    for (int64_t b = 0; b < bits; b += 8) {
        const __m512i left = _mm512_mullo_epi64(vs, _mm512_cvtepi32_epi64(_mm256_loadu_si256((const __m256i *)(dots + b))));
        const __m512i right = _mm512_mullo_epi64(vsum, _mm512_loadu_si512((const void *)(row_sums + b)));
        d[b >> 3] = (uint8_t)_mm512_cmpgt_epi64_mask(left, right);
    }
}
#endif

#if HAVE_DISPATCH
/* learned_patch_avx512 with AVX2 (8 samples at a time), for samples a multiple of 8; the same
 * conditions and arithmetic (rounding to nearest even by the instruction, not the CPU's mode). */
static __attribute__((target("avx2"))) int64_t learned_patch_avx2(const uint8_t *image, int64_t step, float cx,
                                                                  float cy, float c, float s, const float *grid_u,
                                                                  const float *grid_v, int64_t samples,
                                                                  uint8_t *patch) {
    const __m256 vc = _mm256_set1_ps(c), vs = _mm256_set1_ps(s), vx = _mm256_set1_ps(cx), vy = _mm256_set1_ps(cy);
    const __m256 v32 = _mm256_set1_ps(32.0f);
    const __m256i vstep = _mm256_set1_epi32((int32_t)step), m31 = _mm256_set1_epi32(31), m255 = _mm256_set1_epi32(255);
    const __m256i full = _mm256_set1_epi32(32), half = _mm256_set1_epi32(512);
    /* byte 0 of each 32-bit lane to the first four bytes of its 128-bit half */
    const __m256i low_bytes = _mm256_setr_epi8(0, 4, 8, 12, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1,
                                               0, 4, 8, 12, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1, -1);
    __m256i total = _mm256_setzero_si256();
    for (int64_t k = 0; k < samples; k += 8) {
        const __m256 u = _mm256_loadu_ps(grid_u + k), w = _mm256_loadu_ps(grid_v + k);
        const __m256 px = _mm256_add_ps(_mm256_sub_ps(_mm256_mul_ps(vc, u), _mm256_mul_ps(vs, w)), vx);
        const __m256 py = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(vs, u), _mm256_mul_ps(vc, w)), vy);
        const __m256i ax = _mm256_cvttps_epi32(_mm256_round_ps(_mm256_mul_ps(px, v32), _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC));
        const __m256i ay = _mm256_cvttps_epi32(_mm256_round_ps(_mm256_mul_ps(py, v32), _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC));
        const __m256i fx = _mm256_and_si256(ax, m31), fy = _mm256_and_si256(ay, m31);
        const __m256i gx = _mm256_sub_epi32(full, fx), gy = _mm256_sub_epi32(full, fy);
        const __m256i at = _mm256_add_epi32(_mm256_mullo_epi32(_mm256_srai_epi32(ay, 5), vstep), _mm256_srai_epi32(ax, 5));
        const __m256i r0 = _mm256_i32gather_epi32((const int *)image, at, 1);
        const __m256i r1 = _mm256_i32gather_epi32((const int *)image, _mm256_add_epi32(at, vstep), 1);
        const __m256i top = _mm256_add_epi32(_mm256_mullo_epi32(gx, _mm256_and_si256(r0, m255)),
                                             _mm256_mullo_epi32(fx, _mm256_and_si256(_mm256_srli_epi32(r0, 8), m255)));
        const __m256i bottom = _mm256_add_epi32(_mm256_mullo_epi32(gx, _mm256_and_si256(r1, m255)),
                                                _mm256_mullo_epi32(fx, _mm256_and_si256(_mm256_srli_epi32(r1, 8), m255)));
        const __m256i v = _mm256_srai_epi32(_mm256_add_epi32(_mm256_add_epi32(_mm256_mullo_epi32(gy, top),
                                                                              _mm256_mullo_epi32(fy, bottom)), half), 10);
        total = _mm256_add_epi32(total, v);
        const __m256i packed = _mm256_shuffle_epi8(v, low_bytes);
        const int32_t lo = _mm_cvtsi128_si32(_mm256_castsi256_si128(packed));
        const int32_t hi = _mm_cvtsi128_si32(_mm256_extracti128_si256(packed, 1));
        memcpy(patch + k, &lo, 4);
        memcpy(patch + k + 4, &hi, 4);
    }
    const __m128i t = _mm_add_epi32(_mm256_castsi256_si128(total), _mm256_extracti128_si256(total, 1));
    const __m128i t2 = _mm_add_epi32(t, _mm_shuffle_epi32(t, 0x4e));
    return (int64_t)_mm_cvtsi128_si32(_mm_add_epi32(t2, _mm_shuffle_epi32(t2, 0xb1)));
}
#endif

#if HAVE_DISPATCH
/* learned_dots_vnni4 with AVX-VNNI (256 bits, no AVX-512), for bits a multiple of 16: sixteen bits
 * of all four patches at a time in eight accumulators, each weight load used four times. */
static __attribute__((target("avxvnni,avx2"))) void learned_dots_avx_vnni4(const int8_t *quads,
                                                                            const uint8_t *patches, int64_t samples,
                                                                            int64_t bits, int32_t *dots) {
    for (int64_t b0 = 0; b0 < bits; b0 += 16) {
        __m256i acc[4][2];
        for (int i = 0; i < 4; i++) acc[i][0] = acc[i][1] = _mm256_setzero_si256();
        for (int64_t k = 0; k < samples / 4; k++) {
            const int8_t *w = quads + (k * bits + b0) * 4;
            const __m256i w0 = _mm256_loadu_si256((const __m256i *)w), w1 = _mm256_loadu_si256((const __m256i *)(w + 32));
            for (int i = 0; i < 4; i++) {
                int32_t four;
                memcpy(&four, patches + i * samples + 4 * k, 4);
                const __m256i p = _mm256_set1_epi32(four);
                acc[i][0] = _mm256_dpbusd_avx_epi32(acc[i][0], p, w0);
                acc[i][1] = _mm256_dpbusd_avx_epi32(acc[i][1], p, w1);
            }
        }
        for (int i = 0; i < 4; i++) {
            _mm256_storeu_si256((__m256i *)(dots + i * bits + b0), acc[i][0]);
            _mm256_storeu_si256((__m256i *)(dots + i * bits + b0 + 8), acc[i][1]);
        }
    }
}
#endif

/* Bits (bits / 8,) of one keypoint, bits a multiple of 8: bit b set when samples * (dots[b] + shift *
 * row_sums[b]) > sum * row_sums[b] (shift: what each sample's value was lowered by before its products). */
static void learned_bits(const int32_t *dots, int64_t sum, const int64_t *row_sums, int64_t samples, int64_t bits,
                         int64_t shift, uint8_t *d) {
    for (int64_t b = 0; b < bits; b += 8) {
        uint32_t byte = 0;
        for (int t = 0; t < 8; t++)
            byte |= (uint32_t)(samples * ((int64_t)dots[b + t] + shift * row_sums[b + t]) > sum * row_sums[b + t]) << t;
        d[b >> 3] = (uint8_t)byte;
    }
}

/* The keypoint's level and centre on it; 0, or -2 for an octave outside the levels. */
static int learned_level(const intptr_t *levels, const int64_t *steps, const int64_t *rows, const int64_t *cols,
                         int64_t n_levels, const float *inv_scale, float x, float y, int32_t o,
                         const uint8_t **image, int64_t *step, int64_t *last_col, int64_t *last_row, float *cx,
                         float *cy) {
    if (o < 0 || o >= n_levels) return -2;
    *image = (const uint8_t *)levels[o];
    *step = steps[o], *last_col = cols[o] - 1, *last_row = rows[o] - 1;
    *cx = x * inv_scale[o], *cy = y * inv_scale[o];
    return 0;
}

/* True when every sample of a keypoint at (cx, cy) within `reach` of it lies `margin` pixels inside. */
static inline int learned_inside(float cx, float cy, float reach, float margin, int64_t last_col, int64_t last_row) {
    return cx - reach - margin >= 0.0f && cy - reach - margin >= 0.0f
           && cx + reach + margin <= (float)last_col && cy + reach + margin <= (float)last_row;
}

#if HAVE_NEON
/* dots (4, bits) int32 of four patches (4, samples) int8 (each byte the patch's uint8 value minus
 * 128) with the weights as quads (learned_dots_vnni4), for bits a multiple of 8, less 128 times the
 * weights' row sums: eight bits of all four at a time. Each multiply gives eight int8 x int8
 * products in int16 (at most 128 x 128), each pairwise add two of them into int32: exact. With
 * `paired` (samples a multiple of 8, no weight -128) two steps' products are summed in int16
 * before the pairwise add, a quarter fewer instructions: two products of at most 127 x 128 fit.
 * Not inlined: inside the driver GCC lays the loop out less well. */
static __attribute__((noinline)) void learned_dots_neon4(const int8_t *quads, const int8_t *patches, int64_t samples,
                                                         int64_t bits, int paired, int32_t *dots) {
    for (int64_t b0 = 0; b0 < bits; b0 += 8) {
        int32x4_t acc[4][4];
        for (int i = 0; i < 4; i++)
            for (int j = 0; j < 4; j++) acc[i][j] = vdupq_n_s32(0);
        if (paired) {
            for (int64_t k = 0; k < samples / 4; k += 2) {
                const int8_t *w = quads + (k * bits + b0) * 4;
                const int8x16_t w0 = vld1q_s8(w), w1 = vld1q_s8(w + 16);
                const int8x16_t v0 = vld1q_s8(w + 4 * bits), v1 = vld1q_s8(w + 4 * bits + 16);
                for (int i = 0; i < 4; i++) {
                    int32_t four, next;
                    memcpy(&four, patches + i * samples + 4 * k, 4);
                    memcpy(&next, patches + i * samples + 4 * k + 4, 4);
                    const int8x16_t p = vreinterpretq_s8_s32(vdupq_n_s32(four));
                    const int8x16_t q = vreinterpretq_s8_s32(vdupq_n_s32(next));
                    acc[i][0] = vpadalq_s16(acc[i][0], vmlal_s8(vmull_s8(vget_low_s8(w0), vget_low_s8(p)),
                                                                vget_low_s8(v0), vget_low_s8(q)));
                    acc[i][1] = vpadalq_s16(acc[i][1], vmlal_high_s8(vmull_high_s8(w0, p), v0, q));
                    acc[i][2] = vpadalq_s16(acc[i][2], vmlal_s8(vmull_s8(vget_low_s8(w1), vget_low_s8(p)),
                                                                vget_low_s8(v1), vget_low_s8(q)));
                    acc[i][3] = vpadalq_s16(acc[i][3], vmlal_high_s8(vmull_high_s8(w1, p), v1, q));
                }
            }
        } else {
            for (int64_t k = 0; k < samples / 4; k++) {
                const int8_t *w = quads + (k * bits + b0) * 4;
                const int8x16_t w0 = vld1q_s8(w), w1 = vld1q_s8(w + 16);
                for (int i = 0; i < 4; i++) {
                    int32_t four;
                    memcpy(&four, patches + i * samples + 4 * k, 4);
                    const int8x16_t p = vreinterpretq_s8_s32(vdupq_n_s32(four));
                    acc[i][0] = vpadalq_s16(acc[i][0], vmull_s8(vget_low_s8(w0), vget_low_s8(p)));
                    acc[i][1] = vpadalq_s16(acc[i][1], vmull_high_s8(w0, p));
                    acc[i][2] = vpadalq_s16(acc[i][2], vmull_s8(vget_low_s8(w1), vget_low_s8(p)));
                    acc[i][3] = vpadalq_s16(acc[i][3], vmull_high_s8(w1, p));
                }
            }
        }
        /* Each accumulator holds two bits' halves: bit b's are lanes 2 (b - b0) and 2 (b - b0) + 1. */
        for (int i = 0; i < 4; i++) {
            vst1q_s32(dots + i * bits + b0, vpaddq_s32(acc[i][0], acc[i][1]));
            vst1q_s32(dots + i * bits + b0 + 4, vpaddq_s32(acc[i][2], acc[i][3]));
        }
    }
}

/* Whether none of the n int8 weights is -128 (learned_dots_neon4's paired steps). */
static int learned_weights_above_min(const int8_t *weights, int64_t n) {
    int8x16_t low = vdupq_n_s8(INT8_MAX);
    int64_t k = 0;
    for (; k + 16 <= n; k += 16) low = vminq_s8(low, vld1q_s8(weights + k));
    int8_t least = vminvq_s8(low);
    for (; k < n; k++) least = weights[k] < least ? weights[k] : least;
    return least > INT8_MIN;
}

#if HAVE_NEON_DOTPROD
/* learned_dots_neon4 with the dot-product instruction, for bits a multiple of 16 and samples of 16:
 * sixteen bits of all four patches at a time, each instruction adding four int8 x int8 products to
 * an int32; each patch load holds four steps' samples, taken by lane. */
static DOTPROD_TARGET void learned_dots_neon_dot4(const int8_t *quads, const int8_t *patches, int64_t samples,
                                                  int64_t bits, int32_t *dots) {
    for (int64_t b0 = 0; b0 < bits; b0 += 16) {
        int32x4_t acc[4][4];
        for (int i = 0; i < 4; i++)
            for (int j = 0; j < 4; j++) acc[i][j] = vdupq_n_s32(0);
        for (int64_t k0 = 0; k0 < samples / 4; k0 += 4) {
            int8x16_t p[4];
            for (int i = 0; i < 4; i++) p[i] = vld1q_s8(patches + i * samples + 4 * k0);
#define DOT_STEP(t)                                                                                   \
            {                                                                                         \
                const int8_t *w = quads + ((k0 + (t)) * bits + b0) * 4;                               \
                int8x16_t wq[4];                                                                      \
                for (int j = 0; j < 4; j++) wq[j] = vld1q_s8(w + 16 * j);                             \
                for (int i = 0; i < 4; i++)                                                           \
                    for (int j = 0; j < 4; j++) acc[i][j] = vdotq_laneq_s32(acc[i][j], wq[j], p[i], (t)); \
            }
            DOT_STEP(0) DOT_STEP(1) DOT_STEP(2) DOT_STEP(3)
#undef DOT_STEP
        }
        for (int i = 0; i < 4; i++)
            for (int j = 0; j < 4; j++) vst1q_s32(dots + i * bits + b0 + 4 * j, acc[i][j]);
    }
}
#endif
#endif

#if HAVE_NEON
/* learned_patch for samples a multiple of 4 and a keypoint whose every sample's four pixels lie
 * inside the level (no clamp; offsets fit int32): 4 samples at a time, the same float32 operations
 * (no fused multiply-add: -ffp-contract=off), rounding to nearest even by the conversion (as
 * round_even below 2^22) and the same integer bilinear mix; each row's two pixels read as one
 * 16-bit load. */
static int64_t learned_patch_neon(const uint8_t *image, int64_t step, float cx, float cy, float c, float s,
                                  const float *grid_u, const float *grid_v, int64_t samples, uint8_t *patch) {
    const float32x4_t vc = vdupq_n_f32(c), vs = vdupq_n_f32(s), vx = vdupq_n_f32(cx), vy = vdupq_n_f32(cy);
    const float32x4_t v32 = vdupq_n_f32(32.0f);
    const int32x4_t m31 = vdupq_n_s32(31), full = vdupq_n_s32(32), vstep = vdupq_n_s32((int32_t)step);
    uint32x4_t total = vdupq_n_u32(0);
    for (int64_t k = 0; k < samples; k += 4) {
        const float32x4_t u = vld1q_f32(grid_u + k), w = vld1q_f32(grid_v + k);
        const float32x4_t px = vaddq_f32(vsubq_f32(vmulq_f32(vc, u), vmulq_f32(vs, w)), vx);
        const float32x4_t py = vaddq_f32(vaddq_f32(vmulq_f32(vs, u), vmulq_f32(vc, w)), vy);
        const int32x4_t ax = vcvtnq_s32_f32(vmulq_f32(px, v32)), ay = vcvtnq_s32_f32(vmulq_f32(py, v32));
        const int32x4_t fx = vandq_s32(ax, m31), fy = vandq_s32(ay, m31);
        const int32x4_t gx = vsubq_s32(full, fx), gy = vsubq_s32(full, fy);
        int32_t at[4];
        vst1q_s32(at, vmlaq_s32(vshrq_n_s32(ax, 5), vshrq_n_s32(ay, 5), vstep));
        uint16_t top_pair[4], bottom_pair[4];
        for (int l = 0; l < 4; l++) {
            memcpy(top_pair + l, image + at[l], 2);
            memcpy(bottom_pair + l, image + at[l] + step, 2);
        }
        const uint16x4_t r0 = vld1_u16(top_pair), r1 = vld1_u16(bottom_pair);
        const uint16x4_t byte = vdup_n_u16(255);
        const int32x4_t p00 = vreinterpretq_s32_u32(vmovl_u16(vand_u16(r0, byte)));
        const int32x4_t p01 = vreinterpretq_s32_u32(vmovl_u16(vshr_n_u16(r0, 8)));
        const int32x4_t p10 = vreinterpretq_s32_u32(vmovl_u16(vand_u16(r1, byte)));
        const int32x4_t p11 = vreinterpretq_s32_u32(vmovl_u16(vshr_n_u16(r1, 8)));
        const int32x4_t top = vmlaq_s32(vmulq_s32(gx, p00), fx, p01);
        const int32x4_t bottom = vmlaq_s32(vmulq_s32(gx, p10), fx, p11);
        const int32x4_t v = vshrq_n_s32(vaddq_s32(vmlaq_s32(vmulq_s32(gy, top), fy, bottom), vdupq_n_s32(512)), 10);
        const uint32x4_t value = vreinterpretq_u32_s32(v);
        total = vaddq_u32(total, value);
        const uint8x8_t narrow = vmovn_u16(vcombine_u16(vmovn_u32(value), vdup_n_u16(0)));
        vst1_lane_u32((uint32_t *)(void *)(patch + k), vreinterpret_u32_u8(narrow), 0);
    }
    return (int64_t)vaddvq_u32(total);
}
#endif

enum { LEARNED_VNNI, LEARNED_AVX_VNNI, LEARNED_AVX2, LEARNED_NEON_DOT, LEARNED_NEON, LEARNED_PLAIN };

/* learned_describe in blocks of four keypoints (form: one of the enum above, run where the CPU has
 * it; the caller checks bits and samples fit it); the same bytes in every form. The SIMD forms take
 * a block's four patches at once, plain C one at a time. Patches are sampled 16 (AVX-512), 8
 * (AVX-VNNI, AVX2) or 4 (Advanced SIMD) samples at a time where a keypoint lies far enough inside
 * its level (x86-64: three pixels, as the gathers read four bytes from each sample's left pixel;
 * aarch64: two), else, and in plain C, one at a time. On aarch64 the patches' products are taken
 * as int8: each value lowered by 128, put back with 128 times the row's sum in learned_bits. */
static int64_t learned_describe_blocks(
        const intptr_t *levels, const int64_t *steps, const int64_t *rows, const int64_t *cols, int64_t n_levels,
        const float *inv_scale, const float *x, const float *y, const float *cosines, const float *sines,
        const int32_t *octave, int64_t n, const float *grid_u, const float *grid_v, int64_t samples,
        const int16_t *pairs, const int8_t *quads, const int64_t *row_sums, int64_t bits, float reach, int form,
        uint8_t *out) {
    const int64_t half = samples / 2;
    uint8_t *patches = (uint8_t *)calloc((size_t)(4 * samples), 1);
    int8_t *lowered = (int8_t *)calloc((size_t)(4 * samples), 1);
    int32_t *patch_pairs = (int32_t *)calloc((size_t)(4 * half), sizeof(int32_t));
    int32_t *dots = (int32_t *)malloc((size_t)(4 * bits) * sizeof(int32_t));
    if (!patches || !lowered || !patch_pairs || !dots) {
        free(patches); free(lowered); free(patch_pairs); free(dots);
        return -1;
    }
    const int64_t shift = form == LEARNED_NEON_DOT || form == LEARNED_NEON ? 128 : 0;
#if HAVE_NEON
    const int paired = form == LEARNED_NEON && samples % 8 == 0 && learned_weights_above_min(quads, samples * bits);
#endif
    int64_t status = 0;
    for (int64_t i0 = 0; i0 < n && status == 0; i0 += 4) {
        int64_t sums[4] = {0, 0, 0, 0};
        const int64_t m = n - i0 < 4 ? n - i0 : 4;
        for (int64_t j = 0; j < m; j++) {
            const uint8_t *image;
            int64_t step, last_col, last_row;
            float cx, cy;
            if (learned_level(levels, steps, rows, cols, n_levels, inv_scale, x[i0 + j], y[i0 + j], octave[i0 + j],
                              &image, &step, &last_col, &last_row, &cx, &cy)) {
                status = -2;
                break;
            }
            uint8_t *patch = patches + j * samples;
            const float c = cosines[i0 + j], s = sines[i0 + j];
            const int fits = (last_row + 1) * step < INT32_MAX;
            (void)fits;
#if HAVE_DISPATCH
            const int gather = fits && learned_inside(cx, cy, reach, 3.0f, last_col, last_row);
            if (gather && form == LEARNED_VNNI)
                sums[j] = learned_patch_avx512(image, step, cx, cy, c, s, grid_u, grid_v, samples, patch);
            else if (gather && (form == LEARNED_AVX_VNNI || form == LEARNED_AVX2))
                sums[j] = learned_patch_avx2(image, step, cx, cy, c, s, grid_u, grid_v, samples, patch);
            else
#endif
#if HAVE_NEON
            if (form != LEARNED_PLAIN && fits && learned_inside(cx, cy, reach, 2.0f, last_col, last_row))
                sums[j] = learned_patch_neon(image, step, cx, cy, c, s, grid_u, grid_v, samples, patch);
            else
#endif
                sums[j] = learned_patch(image, step, last_col, last_row, cx, cy, c, s, grid_u, grid_v, samples,
                                        !learned_inside(cx, cy, reach, 2.0f, last_col, last_row), patch);
            if (form == LEARNED_AVX2 || form == LEARNED_PLAIN)
                for (int64_t k = 0; k < half; k++)
                    patch_pairs[j * half + k] = (int32_t)((uint32_t)patch[2 * k] | ((uint32_t)patch[2 * k + 1] << 16));
            else if (shift)
                for (int64_t k = 0; k < samples; k++) lowered[j * samples + k] = (int8_t)(patch[k] ^ 0x80);
        }
        if (status) break;
        /* A block of fewer than four keypoints leaves the last block's patches in the unused slots:
         * their dots are computed and never read. */
        switch (form) {
#if HAVE_DISPATCH
        case LEARNED_VNNI:
            learned_dots_vnni4(quads, patches, samples, bits, dots);
            for (int64_t j = 0; j < m; j++)
                learned_bits_avx512(dots + j * bits, sums[j], row_sums, samples, bits, out + (i0 + j) * (bits / 8));
            continue;
        case LEARNED_AVX_VNNI:
            learned_dots_avx_vnni4(quads, patches, samples, bits, dots);
            break;
        case LEARNED_AVX2:
            learned_dots_avx2x4(pairs, patch_pairs, half, bits, dots);
            break;
#endif
#if HAVE_NEON_DOTPROD
        case LEARNED_NEON_DOT:
            learned_dots_neon_dot4(quads, lowered, samples, bits, dots);
            break;
#endif
#if HAVE_NEON
        case LEARNED_NEON:
            learned_dots_neon4(quads, lowered, samples, bits, paired, dots);
            break;
#endif
        case LEARNED_PLAIN:
            for (int64_t j = 0; j < m; j++) learned_dots_plain(pairs, patch_pairs + j * half, half, bits, dots + j * bits);
            break;
        default:
            status = -3;
            continue;
        }
        for (int64_t j = 0; j < m; j++)
            learned_bits(dots + j * bits, sums[j], row_sums, samples, bits, shift, out + (i0 + j) * (bits / 8));
    }
    free(patches); free(lowered); free(patch_pairs); free(dots);
    return status;
}

/* The form learned_describe runs: the most specialised from `form` down (the enum above) that the
 * CPU has and that fits bits and samples. */
static int learned_form(int64_t form, int64_t samples, int64_t bits) {
    if (samples <= 0 || bits <= 0) return LEARNED_PLAIN;
#if HAVE_DISPATCH
    __builtin_cpu_init();
    if (form <= LEARNED_VNNI && bits % 64 == 0 && samples % 16 == 0 && __builtin_cpu_supports("avx512f")
            && __builtin_cpu_supports("avx512bw") && __builtin_cpu_supports("avx512dq")
            && __builtin_cpu_supports("avx512vnni"))
        return LEARNED_VNNI;
    if (form <= LEARNED_AVX_VNNI && bits % 16 == 0 && samples % 8 == 0 && __builtin_cpu_supports("avx2")
            && __builtin_cpu_supports("avxvnni"))
        return LEARNED_AVX_VNNI;
    if (form <= LEARNED_AVX2 && bits % 16 == 0 && samples % 8 == 0 && __builtin_cpu_supports("avx2"))
        return LEARNED_AVX2;
#endif
#if HAVE_NEON_DOTPROD
    if (form <= LEARNED_NEON_DOT && bits % 16 == 0 && samples % 16 == 0 && (getauxval(AT_HWCAP) & HWCAP_ASIMDDP))
        return LEARNED_NEON_DOT;
#endif
#if HAVE_NEON
    if (form <= LEARNED_NEON && samples % 4 == 0) return LEARNED_NEON;
#endif
    (void)form; (void)samples; (void)bits;
    return LEARNED_PLAIN;
}

/* levels / steps / rows / cols / n_levels / inv_scale / x / y / octave: as orb_describe; cosines, sines
 * (n,) float32: each keypoint's turn; grid_u, grid_v (samples,) float32: the patch's sample offsets in
 * level pixels, samples even; pairs and quads: the weights (bits, samples) as (samples / 2, bits, 2)
 * int16 and as (samples / 4, bits, 4) int8 (quads: when samples is a multiple of 4, else unread);
 * row_sums (bits,) int64, each row's sum; out (n, bits / 8) uint8, bits a multiple of 8; form:
 * the most specialised form used, where the CPU runs it, else the next it runs: 0 AVX-512 VNNI,
 * 1 AVX-VNNI, 2 AVX2 (x86-64); 3 Advanced SIMD with dot products, 4 Advanced SIMD (aarch64); 5
 * plain C (the same bytes; tests compare them). Sample k of keypoint i sits at (c u - s v + cx, s u + c v + cy)
 * in float32, the operations in that order (learned_sample); bit b is set when samples * (w_b . patch) >
 * sum(patch) * row_sums[b]. Returns 0, -1 when out of memory, -2 for an octave outside the levels,
 * -3 for an odd number of samples or bits not a multiple of 8. */
API int64_t learned_describe(const intptr_t *levels, const int64_t *steps, const int64_t *rows, const int64_t *cols,
                             int64_t n_levels, const float *inv_scale, const float *x, const float *y,
                             const float *cosines, const float *sines, const int32_t *octave, int64_t n,
                             const float *grid_u, const float *grid_v, int64_t samples, const int16_t *pairs,
                             const int8_t *quads, const int64_t *row_sums, int64_t bits, uint8_t *out,
                             int64_t form) {
    if (samples % 2 || bits % 8) return -3;
    /* Every sample lies within the largest offset's length of the centre (a turn keeps lengths; the
     * float32 rounding of a turned offset is far below the margins added to it). */
    float reach = 0.0f;
    for (int64_t k = 0; k < samples; k++) {
        const float r = sqrtf(grid_u[k] * grid_u[k] + grid_v[k] * grid_v[k]);
        reach = r > reach ? r : reach;
    }
    return learned_describe_blocks(levels, steps, rows, cols, n_levels, inv_scale, x, y, cosines, sines, octave, n,
                                   grid_u, grid_v, samples, pairs, quads, row_sums, bits, reach,
                                   learned_form(form, samples, bits), out);
}
