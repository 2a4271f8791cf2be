/*
 * Test and benchmark harness of magstack_cal (host, sanitizers, ARM under qemu-user).
 *
 * stdin: records until EOF, each: u32 image length, the image, u32 n, then n samples of 8 int32
 * (Bx, By, Bz nT, T centi-degC, I_0..I_3 mA; the table's first n_currents currents are used).
 * All integers little-endian (the byte order of every target this runs on).
 *
 * "check" writes per record: int32 loader result, then (when 0) n x (3 int32 outputs, uint32 status)
 * from magstack_cal_apply, then uint32 count of samples where magstack_cal_apply_block differs.
 * "check pre" does the same with terms precomputed (magstack_cal_precompute) for the records' temperatures from the
 * lowest (clipped) to at most 4096 centi-degC above it.
 * "bench R" writes per record: int32 loader result, uint64 ns of R passes of magstack_cal_apply_block
 * over the n samples ("bench R pre": with terms precomputed for all the records' temperatures, clipped).
 */
#define _POSIX_C_SOURCE 200112L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "magstack_cal.h"

static int read_all(void *dst, size_t n)
{
    return fread(dst, 1, n, stdin) == n;
}

static void write_all(const void *src, size_t n)
{
    if (fwrite(src, 1, n, stdout) != n) {
        exit(3);
    }
}

int main(int argc, char **argv)
{
    int bench = argc >= 2 && strcmp(argv[1], "bench") == 0;
    int pre = (argc >= 3 && strcmp(argv[1], "check") == 0 && strcmp(argv[2], "pre") == 0) ||
              (argc >= 4 && bench && strcmp(argv[3], "pre") == 0);
    long repeat = bench && argc >= 3 ? strtol(argv[2], NULL, 10) : 1;
    uint32_t len, n;
    static uint8_t image[4096];
    if (repeat < 1) {
        repeat = 1;
    }
    while (read_all(&len, 4)) {
        magstack_cal_table table;
        int32_t *samples, *b, *t, *c, *out;
        uint8_t *status;
        int32_t rc;
        uint32_t i, k, differ = 0;
        if (len > sizeof image || !read_all(image, len) || !read_all(&n, 4)) {
            return 2;
        }
        samples = malloc((size_t)n * 8u * sizeof(int32_t) + 1u);
        b = malloc((size_t)n * 3u * sizeof(int32_t) + 1u);
        t = malloc((size_t)n * sizeof(int32_t) + 1u);
        c = malloc((size_t)n * 4u * sizeof(int32_t) + 1u);
        out = malloc((size_t)n * 3u * sizeof(int32_t) + 1u);
        status = malloc((size_t)n + 1u);
        if (!samples || !b || !t || !c || !out || !status) {
            return 4;
        }
        if (!read_all(samples, (size_t)n * 8u * sizeof(int32_t))) {
            return 2;
        }
        rc = magstack_cal_load(&table, image, len);
        write_all(&rc, 4);
        if (rc == 0) {
            for (i = 0; i < n; i++) {
                memcpy(b + 3u * i, samples + 8u * i, 3u * sizeof(int32_t));
                t[i] = samples[8u * i + 3u];
                for (k = 0; k < table.n_currents; k++) {
                    c[(size_t)table.n_currents * i + k] = samples[8u * i + 4u + k];
                }
            }
            void *storage = NULL;
            if (pre && n > 0u) {
                int32_t lo = MAGSTACK_CAL_T_LIMIT_CDEG, hi = -MAGSTACK_CAL_T_LIMIT_CDEG;
                for (i = 0; i < n; i++) {
                    lo = t[i] < lo ? t[i] : lo;
                    hi = t[i] > hi ? t[i] : hi;
                }
                lo = lo < -MAGSTACK_CAL_T_LIMIT_CDEG ? -MAGSTACK_CAL_T_LIMIT_CDEG : lo;
                hi = hi > MAGSTACK_CAL_T_LIMIT_CDEG ? MAGSTACK_CAL_T_LIMIT_CDEG : hi < lo ? lo : hi;
                if (!bench && hi - lo > 4096) {
                    hi = lo + 4096; /* check: some samples without precomputed terms */
                }
                if (posix_memalign(&storage, 64, (size_t)(hi - lo + 1) * sizeof(magstack_cal_terms)) != 0 ||
                    magstack_cal_precompute(&table, storage, (size_t)(hi - lo + 1), lo, hi) != MAGSTACK_CAL_OK) {
                    return 5;
                }
            }
            if (bench) {
                struct timespec t0, t1;
                uint64_t ns;
                long r;
                clock_gettime(CLOCK_MONOTONIC, &t0);
                for (r = 0; r < repeat; r++) {
                    magstack_cal_apply_block(&table, n, b, t, c, out, status);
                }
                clock_gettime(CLOCK_MONOTONIC, &t1);
                ns = (uint64_t)(t1.tv_sec - t0.tv_sec) * 1000000000u + (uint64_t)t1.tv_nsec - (uint64_t)t0.tv_nsec;
                write_all(&ns, 8);
            } else {
                magstack_cal_apply_block(&table, n, b, t, c, out, status);
                for (i = 0; i < n; i++) {
                    int32_t one[3];
                    uint32_t st = magstack_cal_apply(&table, samples + 8u * i, samples[8u * i + 3u],
                                                     samples + 8u * i + 4u, one);
                    write_all(one, sizeof one);
                    write_all(&st, 4);
                    if (memcmp(one, out + 3u * i, sizeof one) != 0 || st != status[i]) {
                        differ++;
                    }
                }
                write_all(&differ, 4);
            }
            free(storage);
        }
        free(samples);
        free(b);
        free(t);
        free(c);
        free(out);
        free(status);
    }
    return 0;
}
