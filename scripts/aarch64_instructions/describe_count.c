/* Describes 1000 keypoints, all inside a synthetic two-level pyramid, `repeats` times: with
 * learned_describe (256 bits of 16 x 16 samples, one orientation; form as in kernels.c) or with
 * orb_describe (ORB's 256 tests, oriented and upright in one call). Counting a run's instructions
 * at two repeat counts gives a call's. Usage: describe_count (learned FORM | orb) REPEATS */
#include <math.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

int64_t learned_describe(const intptr_t *levels, const int64_t *steps, const int64_t *rows, const int64_t *cols,
                         int64_t n_levels, const float *inv_scale, const float *x, const float *y,
                         const float *cosines, const float *sines, const int32_t *octave, int64_t n,
                         const float *grid_u, const float *grid_v, int64_t samples, const int16_t *pairs,
                         const int8_t *quads, const int64_t *row_sums, int64_t bits, uint8_t *out, int64_t form);
int64_t orb_describe(const intptr_t *levels, const int64_t *steps, const int64_t *rows, const int64_t *cols,
                     int64_t n_levels, const float *inv_scale, const float *x, const float *y, const float *angle,
                     const int32_t *octave, int64_t n, const int32_t *pattern, int64_t pairs, uint8_t *oriented,
                     uint8_t *upright);

enum { LEVELS = 2, SAMPLES = 256, BITS = 256, N = 1000 };

static uint32_t state = 12345;
static uint32_t next(void) { state = state * 1664525u + 1013904223u; return state >> 8; }

int main(int argc, char **argv) {
    if (argc != 4 && argc != 3) {
        fprintf(stderr, "usage: %s (learned FORM | orb) REPEATS\n", argv[0]);
        return 2;
    }
    const int orb = strcmp(argv[1], "orb") == 0;
    const int64_t form = orb ? 0 : atoi(argv[2]);
    const int repeats = atoi(argv[orb ? 2 : 3]);
    intptr_t levels[LEVELS];
    int64_t steps[LEVELS], rows[LEVELS], cols[LEVELS];
    float inv[LEVELS];
    for (int l = 0; l < LEVELS; l++) {
        rows[l] = 240 >> l, cols[l] = 320 >> l, steps[l] = cols[l], inv[l] = 1.0f / (float)(1 << l);
        uint8_t *image = malloc((size_t)(steps[l] * rows[l]));
        for (int64_t i = 0; i < steps[l] * rows[l]; i++) image[i] = (uint8_t)next();
        levels[l] = (intptr_t)image;
    }
    static float grid_u[SAMPLES], grid_v[SAMPLES], x[N], y[N], angle[N], cosines[N], sines[N];
    static int8_t weights[BITS][SAMPLES], quads[SAMPLES / 4][BITS][4];
    static int16_t pairs[SAMPLES / 2][BITS][2];
    static int64_t row_sums[BITS];
    static int32_t pattern[BITS * 4], octave[N];
    static uint8_t out[N * BITS / 8], upright[N * BITS / 8];
    for (int k = 0; k < SAMPLES; k++) grid_u[k] = ((k % 16) - 7.5f) * 2.0f, grid_v[k] = ((k / 16) - 7.5f) * 2.0f;
    for (int b = 0; b < BITS; b++)
        for (int k = 0; k < SAMPLES; k++) {
            weights[b][k] = (int8_t)((int)(next() % 255) - 127);
            row_sums[b] += weights[b][k];
            pairs[k / 2][b][k % 2] = weights[b][k];
            quads[k / 4][b][k % 4] = weights[b][k];
        }
    for (int i = 0; i < BITS * 4; i++) pattern[i] = (int32_t)(next() % 27) - 13;
    for (int i = 0; i < N; i++) {
        x[i] = 60.0f + (float)(next() % 20000) / 100.0f, y[i] = 60.0f + (float)(next() % 12000) / 100.0f;
        angle[i] = (float)(next() % 36000) / 100.0f;
        cosines[i] = cosf(angle[i] * 0.017453292f), sines[i] = sinf(angle[i] * 0.017453292f);
        octave[i] = (int32_t)(next() % LEVELS);
    }
    int64_t status = 0;
    for (int r = 0; r < repeats && status == 0; r++)
        status = orb ? orb_describe(levels, steps, rows, cols, LEVELS, inv, x, y, angle, octave, N, pattern, BITS, out,
                                    upright)
                     : learned_describe(levels, steps, rows, cols, LEVELS, inv, x, y, cosines, sines, octave, N, grid_u,
                                        grid_v, SAMPLES, &pairs[0][0][0], &quads[0][0][0], row_sums, BITS, out, form);
    uint64_t digest = 1469598103934665603ull;
    for (int i = 0; i < N * BITS / 8; i++) digest = (digest ^ out[i]) * 1099511628211ull;
    printf("status %lld digest %016llx\n", (long long)status, (unsigned long long)digest);
    return status != 0;
}
