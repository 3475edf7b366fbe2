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
API int64_t aefabmap_kernels_version(void) { return 2; }

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

#if HAVE_DISPATCH
/* Bits set in each byte of v (the nibble-table popcount: AVX2 has no vector popcount instruction). */
static AVX2_TARGET inline __m256i byte_counts(__m256i v) {
    const __m256i table = _mm256_setr_epi8(0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3, 3, 4,
                                           0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3, 3, 4);
    const __m256i nibble = _mm256_set1_epi8(0x0f);
    __m256i lo = _mm256_and_si256(v, nibble), hi = _mm256_and_si256(_mm256_srli_epi16(v, 4), nibble);
    return _mm256_add_epi8(_mm256_shuffle_epi8(table, lo), _mm256_shuffle_epi8(table, hi));
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
