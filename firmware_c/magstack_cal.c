/*
 * magstack_cal: the on-board calibration applier in C99, integer only (see magstack_cal.h).
 *
 * Per sample, with dTc = T - t0 (centi-degC) and an int64 accumulator in units of 2^-27 nT:
 *
 *   G_ij  = S_ij + rdiv(K_S,ij * dTc, 12800)
 *   G_ii += rdiv(rdiv(K_S2,i * dTc, 100) * dTc, 819200)
 *   acc_i = sum_j G_ij * B_j + O_i * 2^19 + rdiv(K_O,i * dTc * 2^11, 100) + sum_k D_k,i * I_k * 2^7
 *   out_i = sat_int32(rshift_round(acc_i, 19))
 *   OUT_OF_VALIDITY: n_i = rshift_round(out_i, 8) (whole nT), |n_i| > lim_i or n_0^2 + n_1^2 + n_2^2 > norm^2,
 *                    or the temperature or a current outside its range
 *
 * rdiv and rshift_round round half away from zero; they work in unsigned arithmetic (no shift or
 * division of a negative number). The accumulator bound |acc| < 2^61.3
 * holds for every image the loader accepts (|K_S2| < 2^28, |t0| <= 2^15, the input clips), so no
 * product or sum overflows; only the final int32 conversion can, and it saturates. |n_i| <= 2^23, so the
 * squares' sum is below 2^49.
 */
#include "magstack_cal.h"

/* ------------------------------------------------------------------ image layout (byte offsets) */
#define OFF_MAGIC 0u
#define OFF_VERSION 4u
#define OFF_SIZE 6u
#define OFF_SOURCE_CRC 8u
#define OFF_TERMS 12u
#define OFF_N_CURRENTS 13u
#define OFF_OPTIONS 14u
#define OFF_RESERVED 15u
#define OFF_DEVICE_ID 16u
#define OFF_T0 48u
#define OFF_FIELD_LIMIT 52u
#define OFF_FIELD_AXES 56u
#define OFF_FIELD_NORM 68u
#define OFF_TEMP_LO 72u
#define OFF_TEMP_HI 76u
#define OFF_S 80u
#define OFF_K_S 116u
#define OFF_K_S2 152u
#define OFF_O 164u
#define OFF_K_O 176u
#define OFF_D 188u
#define OFF_CURRENT_RANGES 236u
#define OFF_CURRENT_NAMES 268u
#define OFF_CRC 332u

#define KNOWN_TERMS 0x3Fu
#define KNOWN_OPTIONS 0x07u

static uint32_t rd_u16(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8);
}

static uint32_t rd_u32(const uint8_t *p)
{
    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);
}

/* two's complement int32 from its bytes, without an implementation-defined conversion */
static int32_t rd_i32(const uint8_t *p)
{
    uint32_t u = rd_u32(p);
    if (u <= 0x7FFFFFFFu) {
        return (int32_t)u;
    }
    return -(int32_t)(~u) - 1;
}

uint32_t magstack_cal_crc32(const uint8_t *data, size_t len)
{
    uint32_t c = 0xFFFFFFFFu;
    size_t i;
    unsigned k;
    for (i = 0; i < len; i++) {
        c ^= data[i];
        for (k = 0; k < 8u; k++) {
            c = (c >> 1) ^ (0xEDB88320u & (0u - (c & 1u)));
        }
    }
    return c ^ 0xFFFFFFFFu;
}

/* printable ASCII (0x20..0x7E), at least one character, then only NUL bytes; copied to out */
static int text_field(const uint8_t *p, unsigned n, char *out)
{
    unsigned i, len = 0;
    while (len < n && p[len] != 0u) {
        if (p[len] < 0x20u || p[len] > 0x7Eu) {
            return 0;
        }
        len++;
    }
    if (len == 0u) {
        return 0;
    }
    for (i = len; i < n; i++) {
        if (p[i] != 0u) {
            return 0;
        }
    }
    for (i = 0; i < len; i++) {
        out[i] = (char)p[i];
    }
    out[len] = '\0';
    return 1;
}

static int all_zero(const uint8_t *p, unsigned n)
{
    unsigned i;
    for (i = 0; i < n; i++) {
        if (p[i] != 0u) {
            return 0;
        }
    }
    return 1;
}

static int same_text(const char *a, const char *b)
{
    while (*a != '\0' && *a == *b) {
        a++;
        b++;
    }
    return *a == *b;
}

static int within(int32_t v, int32_t lim)
{
    return v >= -lim && v <= lim;
}

static int decode(magstack_cal_table *t, const uint8_t *img)
{
    unsigned i, j, k;
    int32_t lim;
    uint32_t options = img[OFF_OPTIONS];
    if (img[OFF_RESERVED] != 0u || (options & ~KNOWN_OPTIONS) != 0u) {
        return MAGSTACK_CAL_E_RESERVED;
    }
    t->terms = img[OFF_TERMS];
    if ((t->terms & ~KNOWN_TERMS) != 0u || (t->terms & MAGSTACK_CAL_TERM_GAIN_MATRIX) == 0u) {
        return MAGSTACK_CAL_E_TERMS;
    }
    if (!text_field(img + OFF_DEVICE_ID, MAGSTACK_CAL_DEVICE_ID_BYTES, t->device_id)) {
        return MAGSTACK_CAL_E_DEVICE_ID;
    }
    t->n_currents = img[OFF_N_CURRENTS];
    if (t->n_currents > MAGSTACK_CAL_MAX_CURRENTS ||
        (t->n_currents > 0u && (t->terms & MAGSTACK_CAL_TERM_CURRENTS) == 0u)) {
        return MAGSTACK_CAL_E_CURRENTS;
    }
    t->t0_cdeg = rd_i32(img + OFF_T0);
    if (!within(t->t0_cdeg, MAGSTACK_CAL_T_LIMIT_CDEG)) {
        return MAGSTACK_CAL_E_T0;
    }
    for (i = 0; i < 3u; i++) {
        for (j = 0; j < 3u; j++) {
            t->S[i][j] = rd_i32(img + OFF_S + 4u * (3u * i + j));
            t->K_S[i][j] = rd_i32(img + OFF_K_S + 4u * (3u * i + j));
        }
        t->K_S2[i] = rd_i32(img + OFF_K_S2 + 4u * i);
        t->O[i] = rd_i32(img + OFF_O + 4u * i);
        t->K_O[i] = rd_i32(img + OFF_K_O + 4u * i);
    }
    for (i = 0; i < 3u; i++) {
        if (!within(t->K_S2[i], MAGSTACK_CAL_K_S2_LIMIT)) {
            return MAGSTACK_CAL_E_K_S2;
        }
    }
    /* a coefficient of a term the table does not declare must be zero */
    for (i = 0; i < 3u; i++) {
        for (j = 0; j < 3u; j++) {
            if (t->K_S[i][j] != 0 && (t->terms & MAGSTACK_CAL_TERM_TEMPERATURE_GAIN) == 0u) {
                return MAGSTACK_CAL_E_TERMS;
            }
        }
        if ((t->K_S2[i] != 0 && (t->terms & MAGSTACK_CAL_TERM_TEMPERATURE_GAIN2) == 0u) ||
            (t->O[i] != 0 && (t->terms & MAGSTACK_CAL_TERM_OFFSET) == 0u) ||
            (t->K_O[i] != 0 && (t->terms & MAGSTACK_CAL_TERM_TEMPERATURE_OFFSET) == 0u)) {
            return MAGSTACK_CAL_E_TERMS;
        }
    }
    t->field_limit_nT = rd_i32(img + OFF_FIELD_LIMIT);
    t->field_norm_nT = rd_i32(img + OFF_FIELD_NORM);
    t->temp_lo_cdeg = rd_i32(img + OFF_TEMP_LO);
    t->temp_hi_cdeg = rd_i32(img + OFF_TEMP_HI);
    t->has_temp_range = (uint8_t)(options & MAGSTACK_CAL_OPT_TEMP_RANGE);
    t->has_field_axes = (uint8_t)((options & MAGSTACK_CAL_OPT_FIELD_AXES) != 0u);
    t->has_field_norm = (uint8_t)((options & MAGSTACK_CAL_OPT_FIELD_NORM) != 0u);
    if (t->field_limit_nT < 0 || t->field_limit_nT > MAGSTACK_CAL_B_LIMIT_NT) {
        return MAGSTACK_CAL_E_VALIDITY;
    }
    /* per-axis limits within 0..field_limit_nT, each equal to it without their option bit */
    for (i = 0; i < 3u; i++) {
        t->field_axes_nT[i] = rd_i32(img + OFF_FIELD_AXES + 4u * i);
        if (t->field_axes_nT[i] < 0 || t->field_axes_nT[i] > t->field_limit_nT ||
            (!t->has_field_axes && t->field_axes_nT[i] != t->field_limit_nT)) {
            return MAGSTACK_CAL_E_VALIDITY;
        }
    }
    /* magnitude limit within 0..MAGSTACK_CAL_B_NORM_LIMIT_NT, zero without its option bit */
    if (t->field_norm_nT < 0 || t->field_norm_nT > MAGSTACK_CAL_B_NORM_LIMIT_NT ||
        (!t->has_field_norm && t->field_norm_nT != 0)) {
        return MAGSTACK_CAL_E_VALIDITY;
    }
    if (t->has_temp_range) {
        if (!within(t->temp_lo_cdeg, MAGSTACK_CAL_T_LIMIT_CDEG) || !within(t->temp_hi_cdeg, MAGSTACK_CAL_T_LIMIT_CDEG) ||
            t->temp_lo_cdeg > t->temp_hi_cdeg) {
            return MAGSTACK_CAL_E_VALIDITY;
        }
    } else if (t->temp_lo_cdeg != 0 || t->temp_hi_cdeg != 0) {
        return MAGSTACK_CAL_E_VALIDITY;
    }
    for (k = 0; k < MAGSTACK_CAL_MAX_CURRENTS; k++) {
        const uint8_t *name = img + OFF_CURRENT_NAMES + MAGSTACK_CAL_CURRENT_NAME_BYTES * k;
        for (i = 0; i < 3u; i++) {
            t->D[k][i] = rd_i32(img + OFF_D + 4u * (3u * k + i));
        }
        t->current_lo_mA[k] = rd_i32(img + OFF_CURRENT_RANGES + 8u * k);
        t->current_hi_mA[k] = rd_i32(img + OFF_CURRENT_RANGES + 8u * k + 4u);
        if (k < t->n_currents) {
            if (!text_field(name, MAGSTACK_CAL_CURRENT_NAME_BYTES, t->current_names[k])) {
                return MAGSTACK_CAL_E_CURRENTS;
            }
            lim = MAGSTACK_CAL_I_LIMIT_MA;
            if (!within(t->current_lo_mA[k], lim) || !within(t->current_hi_mA[k], lim) ||
                t->current_lo_mA[k] > t->current_hi_mA[k]) {
                return MAGSTACK_CAL_E_VALIDITY;
            }
        } else if (!all_zero(name, MAGSTACK_CAL_CURRENT_NAME_BYTES) || t->D[k][0] != 0 || t->D[k][1] != 0 ||
                   t->D[k][2] != 0 || t->current_lo_mA[k] != 0 || t->current_hi_mA[k] != 0) {
            return MAGSTACK_CAL_E_CURRENTS;
        }
    }
    for (k = 0; k < t->n_currents; k++) {
        for (j = k + 1u; j < t->n_currents; j++) {
            if (same_text(t->current_names[k], t->current_names[j])) {
                return MAGSTACK_CAL_E_CURRENTS;
            }
        }
    }
    return MAGSTACK_CAL_OK;
}

int magstack_cal_load(magstack_cal_table *table, const uint8_t *image, size_t len)
{
    static const magstack_cal_table zero;
    int rc;
    if (table == NULL || image == NULL) {
        return MAGSTACK_CAL_E_ARGUMENT;
    }
    *table = zero;
    if (len < 4u) {
        return MAGSTACK_CAL_E_SIZE;
    }
    if (image[OFF_MAGIC] != 'M' || image[OFF_MAGIC + 1u] != 'C' || image[OFF_MAGIC + 2u] != 'A' ||
        image[OFF_MAGIC + 3u] != 'L') {
        return MAGSTACK_CAL_E_MAGIC;
    }
    if (len < 8u) {
        return MAGSTACK_CAL_E_SIZE;
    }
    if (rd_u16(image + OFF_VERSION) != MAGSTACK_CAL_IMAGE_VERSION) {
        return MAGSTACK_CAL_E_VERSION;
    }
    if (rd_u16(image + OFF_SIZE) != MAGSTACK_CAL_IMAGE_SIZE || len != MAGSTACK_CAL_IMAGE_SIZE) {
        return MAGSTACK_CAL_E_SIZE;
    }
    if (magstack_cal_crc32(image, OFF_CRC) != rd_u32(image + OFF_CRC)) {
        return MAGSTACK_CAL_E_CRC;
    }
    rc = decode(table, image);
    if (rc != MAGSTACK_CAL_OK) {
        *table = zero;
        return rc;
    }
    table->image_crc32 = rd_u32(image + OFF_CRC);
    table->source_crc32 = rd_u32(image + OFF_SOURCE_CRC);
    return MAGSTACK_CAL_OK;
}

const char *magstack_cal_result_name(int code)
{
    switch (code) {
    case MAGSTACK_CAL_OK: return "ok";
    case MAGSTACK_CAL_E_SIZE: return "wrong size";
    case MAGSTACK_CAL_E_MAGIC: return "not a table image";
    case MAGSTACK_CAL_E_VERSION: return "not image format version 2 (export the table again)";
    case MAGSTACK_CAL_E_CRC: return "CRC-32 mismatch";
    case MAGSTACK_CAL_E_RESERVED: return "reserved bits set";
    case MAGSTACK_CAL_E_TERMS: return "bad terms";
    case MAGSTACK_CAL_E_DEVICE_ID: return "bad device id";
    case MAGSTACK_CAL_E_CURRENTS: return "bad currents";
    case MAGSTACK_CAL_E_T0: return "t0 out of range";
    case MAGSTACK_CAL_E_K_S2: return "K_S2 out of range";
    case MAGSTACK_CAL_E_VALIDITY: return "validity box out of range";
    case MAGSTACK_CAL_E_ARGUMENT: return "null argument";
    default: return "unknown result";
    }
}

/* ------------------------------------------------------------------ arithmetic */
/* a / d rounded half away from zero (d > 0 even, |a| < 2^62), without a branch: floor((a + d/2 - [a < 0]) / d),
 * the floor taken on a + q0 d in unsigned arithmetic (q0 d, the largest multiple of d up to 2^63, keeps it
 * positive) */
static int64_t rdiv(int64_t a, uint64_t d)
{
    uint64_t q0 = ((uint64_t)1 << 63) / d;
    uint64_t u = (uint64_t)a + q0 * d + d / 2u - (uint64_t)(a < 0);
    return (int64_t)(u / d) - (int64_t)q0;
}

/* a / 2^19 rounded half away from zero (|a| < 2^62), without a branch: floor((a + 2^18 - [a < 0]) / 2^19),
 * the floor taken on a + 2^63 in unsigned arithmetic (2^63 is a multiple of 2^19) */
static int64_t rshift_round19(int64_t a)
{
    uint64_t u = (uint64_t)a + ((uint64_t)1 << 63) + ((uint64_t)1 << 18) - (uint64_t)(a < 0);
    return (int64_t)(u >> 19) - ((int64_t)1 << 44);
}

/* v clipped to [-lim, lim]; sets *hit when it was outside */
static int32_t clip(int32_t v, int32_t lim, unsigned *hit)
{
    *hit |= (unsigned)(v > lim) | (unsigned)(v < -lim);
    return v > lim ? lim : v < -lim ? -lim : v;
}

/* the temperature-dependent part of one dTc: the gain matrix (2^-27) and each axis' constant (2^-27 nT) */
typedef struct {
    int64_t g[3][3];
    int64_t c[3];
} temperature_terms;

static void make_terms(const magstack_cal_table *t, int64_t dtc, temperature_terms *tt)
{
    unsigned i, j;
    for (i = 0; i < 3u; i++) {
        for (j = 0; j < 3u; j++) {
            tt->g[i][j] = (int64_t)t->S[i][j] + rdiv((int64_t)t->K_S[i][j] * dtc, 12800u);
        }
        tt->g[i][i] += rdiv(rdiv((int64_t)t->K_S2[i] * dtc, 100u) * dtc, 819200u);
        tt->c[i] = (int64_t)t->O[i] * 524288 + rdiv((int64_t)t->K_O[i] * dtc * 2048, 100u);
    }
}

/* The squared magnitude limit (nT^2), or one above any output's square sum when the table has none. */
static int64_t norm2_limit(const magstack_cal_table *t)
{
    return t->has_field_norm ? (int64_t)t->field_norm_nT * t->field_norm_nT : INT64_MAX;
}

/* Validity of the calibrated field: 1 when an output (nT * 2^8, within int32) in whole nT, rounded half away from
 * zero, is beyond its axis' limit (l0, l1, l2), or the sum of their squares beyond nn (the squared magnitude
 * limit). Whole nT are at most 2^23, so the squares' sum is below 2^49; a difference below zero is outside. */
static unsigned field_outside(int64_t o0, int64_t o1, int64_t o2, int64_t l0, int64_t l1, int64_t l2, int64_t nn)
{
    int64_t n0 = ((o0 < 0 ? -o0 : o0) + 128) >> 8;
    int64_t n1 = ((o1 < 0 ? -o1 : o1) + 128) >> 8;
    int64_t n2 = ((o2 < 0 ? -o2 : o2) + 128) >> 8;
    return (unsigned)((uint64_t)((l0 - n0) | (l1 - n1) | (l2 - n2) | (nn - (n0 * n0 + n1 * n1 + n2 * n2))) >> 63);
}

/* One sample with the temperature terms of its dTc: the status bits. b_nT, cur_mA as given (clipped here). */
static unsigned sample(const magstack_cal_table *t, const temperature_terms *tt, const int32_t *b_nT,
                       int32_t tc, const int32_t *cur_mA, unsigned sat, int32_t out[3])
{
    unsigned oov = 0, i, k;
    int32_t bx = clip(b_nT[0], MAGSTACK_CAL_B_LIMIT_NT, &sat);
    int32_t by = clip(b_nT[1], MAGSTACK_CAL_B_LIMIT_NT, &sat);
    int32_t bz = clip(b_nT[2], MAGSTACK_CAL_B_LIMIT_NT, &sat);
    int64_t acc[3];
    oov |= (unsigned)t->has_temp_range & ((unsigned)(tc < t->temp_lo_cdeg) | (unsigned)(tc > t->temp_hi_cdeg));
    for (i = 0; i < 3u; i++) {
        acc[i] = tt->g[i][0] * bx + tt->g[i][1] * by + tt->g[i][2] * bz + tt->c[i];
    }
    for (k = 0; k < t->n_currents; k++) {
        int32_t c = clip(cur_mA[k], MAGSTACK_CAL_I_LIMIT_MA, &sat);
        oov |= (unsigned)(c < t->current_lo_mA[k]) | (unsigned)(c > t->current_hi_mA[k]);
        for (i = 0; i < 3u; i++) {
            acc[i] += (int64_t)t->D[k][i] * c * 128;
        }
    }
    for (i = 0; i < 3u; i++) {
        int64_t o = rshift_round19(acc[i]);
        sat |= (unsigned)(o > INT32_MAX) | (unsigned)(o < INT32_MIN);
        acc[i] = o > INT32_MAX ? INT32_MAX : o < INT32_MIN ? INT32_MIN : o;
        out[i] = (int32_t)acc[i];
    }
    oov |= field_outside(acc[0], acc[1], acc[2], t->field_axes_nT[0], t->field_axes_nT[1], t->field_axes_nT[2],
                         norm2_limit(t));
    return (sat ? MAGSTACK_CAL_SATURATED : 0u) | (oov ? MAGSTACK_CAL_OUT_OF_VALIDITY : 0u);
}

unsigned magstack_cal_apply(const magstack_cal_table *table, const int32_t b_nT[3], int32_t temp_cdeg,
                            const int32_t *currents_mA, int32_t out[3])
{
    unsigned sat = 0;
    int32_t tc = clip(temp_cdeg, MAGSTACK_CAL_T_LIMIT_CDEG, &sat);
    temperature_terms tt;
    make_terms(table, (int64_t)tc - table->t0_cdeg, &tt);
    return sample(table, &tt, b_nT, tc, currents_mA, sat, out);
}

/* ------------------------------------------------------------------ blocks */
/* Temperature terms kept for this many recent temperatures (direct-mapped on the temperature's low bits) by
 * magstack_cal_apply_block: a temperature that toggles between a few values, or steps by 0.01 degC now and then,
 * costs no recomputation. A power of two; the cache lives on the stack (about 100 bytes an entry). */
#ifndef MAGSTACK_CAL_TERMS_CACHE
#define MAGSTACK_CAL_TERMS_CACHE 8u
#endif

/* The terms of the last MAGSTACK_CAL_TERMS_CACHE clipped temperatures (a tag outside the clip range: empty). */
typedef struct {
    temperature_terms tt[MAGSTACK_CAL_TERMS_CACHE];
    int32_t tag[MAGSTACK_CAL_TERMS_CACHE];
} terms_cache;

static void cache_init(terms_cache *cache)
{
    unsigned i;
    for (i = 0; i < MAGSTACK_CAL_TERMS_CACHE; i++) {
        cache->tag[i] = INT32_MIN;
    }
}

/* The terms of clipped temperature tc from the cache (computed on a miss). */
static const temperature_terms *cached_terms(const magstack_cal_table *t, terms_cache *cache, int32_t tc)
{
    uint32_t slot = (uint32_t)tc & (MAGSTACK_CAL_TERMS_CACHE - 1u);
    if (cache->tag[slot] != tc) {
        make_terms(t, (int64_t)tc - t->t0_cdeg, &cache->tt[slot]);
        cache->tag[slot] = tc;
    }
    return &cache->tt[slot];
}

#ifndef MAGSTACK_CAL_COMPACT /* a kernel per number of currents, vectorisable over runs of one temperature */

/* What every sample of a block shares: the currents' coefficients (x 2^7) and ranges, the field limits, the
 * temperature range (the clip range without one); and, for a run of one temperature, its terms and the status
 * bits of the temperature itself. */
typedef struct {
    int64_t d[MAGSTACK_CAL_MAX_CURRENTS][3];
    int32_t lo[MAGSTACK_CAL_MAX_CURRENTS], hi[MAGSTACK_CAL_MAX_CURRENTS];
    int64_t lim[3], nn;
    int32_t t_lo, t_hi;
    const temperature_terms *tt;
    unsigned base;
} block_terms;

/* The kernels compute a sample on a fast path: every field input within +-2^23 nT and every current within
 * +-2^19 mA (inside the clips: nothing clips) and every output within int32 (nothing saturates). A sample off it
 * is marked SLOW in its status and computed again by sample() once the kernel's loop is done. */
#define FAST_B 0x800000u /* 2^23 */
#define FAST_I 0x80000u  /* 2^19 */
#define SLOW 0x80u
#define HALF32 ((int64_t)1 << 31) /* o is an int32 when o + 2^31 is within 0..2^32 - 1 */

#define OUTSIDE(v, lim) ((uint32_t)(v) + (uint32_t)(lim) > 2u * (uint32_t)(lim)) /* v < -lim or v > lim */

/* The coefficients every sample uses, in locals (registers). */
#define BLOCK_LOCALS                                                                                              \
    const int64_t l0 = bt->lim[0], l1 = bt->lim[1], l2 = bt->lim[2], nn = bt->nn;                                 \
    unsigned slow = 0;                                                                                            \
    int k

/* The terms of a run, in locals. */
#define RUN_LOCALS                                                                                                \
    const int64_t g00 = bt->tt->g[0][0], g01 = bt->tt->g[0][1], g02 = bt->tt->g[0][2];                            \
    const int64_t g10 = bt->tt->g[1][0], g11 = bt->tt->g[1][1], g12 = bt->tt->g[1][2];                            \
    const int64_t g20 = bt->tt->g[2][0], g21 = bt->tt->g[2][1], g22 = bt->tt->g[2][2];                            \
    const int64_t c0 = bt->tt->c[0], c1 = bt->tt->c[1], c2 = bt->tt->c[2];                                        \
    const unsigned base = bt->base

/* Sample r with K currents on the fast path, the terms g.., c.. and the temperature's status bits in base; without
 * a branch. Off the fast path the inputs are taken as zero and the outputs as zero (no overflow either way). */
#define SAMPLE(K, r)                                                                                              \
    do {                                                                                                          \
        int32_t x = b[3u * (r)], y = b[3u * (r) + 1u], z = b[3u * (r) + 2u], mask;                                \
        uint32_t wide = ((uint32_t)x + FAST_B) | ((uint32_t)y + FAST_B) | ((uint32_t)z + FAST_B), cwide = 0;      \
        unsigned oov = 0, fast;                                                                                   \
        int64_t a0, a1, a2, o0, o1, o2, m64;                                                                      \
        for (k = 0; k < (K); k++) {                                                                               \
            cwide |= (uint32_t)cur[(size_t)(K) * (r) + (size_t)k] + FAST_I;                                       \
        }                                                                                                         \
        fast = (unsigned)(((wide >> 23) | (cwide >> 19)) <= 1u);                                                  \
        mask = -(int32_t)fast;                                                                                    \
        x &= mask;                                                                                                \
        y &= mask;                                                                                                \
        z &= mask;                                                                                                \
        a0 = g00 * x + g01 * y + g02 * z + c0;                                                                    \
        a1 = g10 * x + g11 * y + g12 * z + c1;                                                                    \
        a2 = g20 * x + g21 * y + g22 * z + c2;                                                                    \
        for (k = 0; k < (K); k++) {                                                                               \
            int32_t c = cur[(size_t)(K) * (r) + (size_t)k] & mask;                                                \
            oov |= (unsigned)((uint32_t)c - (uint32_t)bt->lo[k] > (uint32_t)bt->hi[k] - (uint32_t)bt->lo[k]);     \
            a0 += bt->d[k][0] * c;                                                                                \
            a1 += bt->d[k][1] * c;                                                                                \
            a2 += bt->d[k][2] * c;                                                                                \
        }                                                                                                         \
        o0 = rshift_round19(a0);                                                                                  \
        o1 = rshift_round19(a1);                                                                                  \
        o2 = rshift_round19(a2);                                                                                  \
        fast &= (unsigned)((((uint64_t)(o0 + HALF32) | (uint64_t)(o1 + HALF32) | (uint64_t)(o2 + HALF32)) >> 32) == \
                           0u);                                                                                   \
        m64 = -(int64_t)fast;                                                                                     \
        o0 &= m64;                                                                                                \
        o1 &= m64;                                                                                                \
        o2 &= m64;                                                                                                \
        out[3u * (r)] = (int32_t)o0;                                                                              \
        out[3u * (r) + 1u] = (int32_t)o1;                                                                         \
        out[3u * (r) + 2u] = (int32_t)o2;                                                                         \
        oov |= field_outside(o0, o1, o2, l0, l1, l2, nn);                                                         \
        slow |= fast ^ 1u;                                                                                        \
        status[r] = (uint8_t)(base | (oov << 1) | ((fast ^ 1u) << 7));                                            \
    } while (0)

/* The samples of m marked SLOW, computed by sample(). */
static void slow_samples(const magstack_cal_table *t, terms_cache *cache, size_t m, const int32_t *b,
                         const int32_t *temp, const int32_t *cur, int32_t *out, uint8_t *status)
{
    size_t r, nk = t->n_currents;
    for (r = 0; r < m; r++) {
        if (status[r] & SLOW) {
            unsigned sat = 0;
            int32_t tc = clip(temp[r], MAGSTACK_CAL_T_LIMIT_CDEG, &sat);
            status[r] = (uint8_t)sample(t, cached_terms(t, cache, tc), b + 3u * r, tc, nk ? cur + nk * r : NULL, sat,
                                        out + 3u * r);
        }
    }
}

/* A run of at least RUN_MIN samples of one temperature goes to a run kernel; otherwise the next MIXED_CHUNK samples
 * go to a mixed kernel. */
#define RUN_MIN 8u
#define MIXED_CHUNK 32u

#ifndef MAGSTACK_CAL_VECTOR
/* m samples whose temperatures vary: each sample's terms from the cache (computed on a miss), in the loop. */
#define MIXED_LOOP(K)                                                                                             \
    do {                                                                                                          \
        const int32_t TL = MAGSTACK_CAL_T_LIMIT_CDEG, t_lo = bt->t_lo, t_hi = bt->t_hi;                           \
        for (r = 0; r < m; r++) {                                                                                 \
            int32_t tc = temp[r];                                                                                 \
            unsigned base = (unsigned)OUTSIDE(tc, TL) << 2;                                                       \
            const temperature_terms *tt;                                                                          \
            tc = tc > TL ? TL : tc < -TL ? -TL : tc;                                                              \
            base |= (unsigned)((uint32_t)tc - (uint32_t)t_lo > (uint32_t)t_hi - (uint32_t)t_lo) << 1;             \
            tt = cached_terms(t, cache, tc);                                                                      \
            {                                                                                                     \
                const int64_t g00 = tt->g[0][0], g01 = tt->g[0][1], g02 = tt->g[0][2];                            \
                const int64_t g10 = tt->g[1][0], g11 = tt->g[1][1], g12 = tt->g[1][2];                            \
                const int64_t g20 = tt->g[2][0], g21 = tt->g[2][1], g22 = tt->g[2][2];                            \
                const int64_t c0 = tt->c[0], c1 = tt->c[1], c2 = tt->c[2];                                        \
                SAMPLE(K, r);                                                                                     \
            }                                                                                                     \
        }                                                                                                         \
    } while (0)
#else
/* m samples whose temperatures vary: each sample's terms from the cache copied into arrays first, then a loop a
 * compiler may vectorise (MAGSTACK_CAL_VECTOR: for targets with 64-bit vector multiplies). */
#define MIXED_LOOP(K)                                                                                             \
    do {                                                                                                          \
        const int32_t TL = MAGSTACK_CAL_T_LIMIT_CDEG, t_lo = bt->t_lo, t_hi = bt->t_hi;                           \
        int64_t G[12][MIXED_CHUNK];                                                                               \
        uint8_t tbase[MIXED_CHUNK];                                                                               \
        for (r = 0; r < m; r++) {                                                                                 \
            int32_t tc = temp[r];                                                                                 \
            unsigned tb = (unsigned)OUTSIDE(tc, TL) << 2;                                                         \
            const temperature_terms *tt;                                                                          \
            tc = tc > TL ? TL : tc < -TL ? -TL : tc;                                                              \
            tb |= (unsigned)((uint32_t)tc - (uint32_t)t_lo > (uint32_t)t_hi - (uint32_t)t_lo) << 1;               \
            tbase[r] = (uint8_t)tb;                                                                               \
            tt = cached_terms(t, cache, tc);                                                                      \
            for (k = 0; k < 3; k++) {                                                                             \
                G[3 * k][r] = tt->g[k][0];                                                                        \
                G[3 * k + 1][r] = tt->g[k][1];                                                                    \
                G[3 * k + 2][r] = tt->g[k][2];                                                                    \
                G[9 + k][r] = tt->c[k];                                                                           \
            }                                                                                                     \
        }                                                                                                         \
        for (r = 0; r < m; r++) {                                                                                 \
            const unsigned base = tbase[r];                                                                       \
            const int64_t g00 = G[0][r], g01 = G[1][r], g02 = G[2][r], g10 = G[3][r], g11 = G[4][r];              \
            const int64_t g12 = G[5][r], g20 = G[6][r], g21 = G[7][r], g22 = G[8][r];                             \
            const int64_t c0 = G[9][r], c1 = G[10][r], c2 = G[11][r];                                             \
            SAMPLE(K, r);                                                                                         \
        }                                                                                                         \
    } while (0)
#endif

/* m samples at the temperature of bt->tt (a loop a compiler may vectorise), and m <= MIXED_CHUNK samples whose
 * temperatures vary; the samples off the fast path computed again by sample(). */
#define KERNELS(RUN, MIXED, K)                                                                                    \
    static void RUN(const magstack_cal_table *t, terms_cache *cache, const block_terms *bt, size_t m,             \
                    const int32_t *restrict b, const int32_t *restrict temp, const int32_t *restrict cur,         \
                    int32_t *restrict out, uint8_t *restrict status)                                               \
    {                                                                                                             \
        size_t r;                                                                                                 \
        BLOCK_LOCALS;                                                                                             \
        RUN_LOCALS;                                                                                               \
        for (r = 0; r < m; r++) {                                                                                 \
            SAMPLE(K, r);                                                                                         \
        }                                                                                                         \
        if (slow) {                                                                                               \
            slow_samples(t, cache, m, b, temp, cur, out, status);                                                 \
        }                                                                                                         \
    }                                                                                                             \
    static void MIXED(const magstack_cal_table *t, terms_cache *cache, const block_terms *bt, size_t m,           \
                      const int32_t *restrict b, const int32_t *restrict temp, const int32_t *restrict cur,       \
                      int32_t *restrict out, uint8_t *restrict status)                                             \
    {                                                                                                             \
        size_t r;                                                                                                 \
        BLOCK_LOCALS;                                                                                             \
        MIXED_LOOP(K);                                                                                            \
        if (slow) {                                                                                               \
            slow_samples(t, cache, m, b, temp, cur, out, status);                                                 \
        }                                                                                                         \
    }

KERNELS(run0, mixed0, 0)
KERNELS(run1, mixed1, 1)
KERNELS(run2, mixed2, 2)
KERNELS(run3, mixed3, 3)
KERNELS(run4, mixed4, 4)

/* The end of the run of one temperature that starts at r (eight samples a step, then one). */
static size_t run_end(const int32_t *temp, size_t r, size_t n)
{
    const int32_t v = temp[r];
    size_t e = r + 1u;
    while (n - e >= 8u && ((temp[e] ^ v) | (temp[e + 1u] ^ v) | (temp[e + 2u] ^ v) | (temp[e + 3u] ^ v) |
                           (temp[e + 4u] ^ v) | (temp[e + 5u] ^ v) | (temp[e + 6u] ^ v) | (temp[e + 7u] ^ v)) == 0) {
        e += 8u;
    }
    while (e < n && temp[e] == v) {
        e++;
    }
    return e;
}

void magstack_cal_apply_block(const magstack_cal_table *table, size_t n, const int32_t *b_nT,
                              const int32_t *temp_cdeg, const int32_t *currents_mA, int32_t *out,
                              uint8_t *status)
{
    block_terms bt;
    terms_cache cache;
    unsigned i, k, nk = table->n_currents;
    size_t r = 0, end;
    cache_init(&cache);
    for (k = 0; k < MAGSTACK_CAL_MAX_CURRENTS; k++) {
        for (i = 0; i < 3u; i++) {
            bt.d[k][i] = (int64_t)table->D[k][i] * 128;
        }
        bt.lo[k] = table->current_lo_mA[k];
        bt.hi[k] = table->current_hi_mA[k];
    }
    for (i = 0; i < 3u; i++) {
        bt.lim[i] = table->field_axes_nT[i];
    }
    bt.nn = norm2_limit(table);
    bt.t_lo = table->has_temp_range ? table->temp_lo_cdeg : -MAGSTACK_CAL_T_LIMIT_CDEG;
    bt.t_hi = table->has_temp_range ? table->temp_hi_cdeg : MAGSTACK_CAL_T_LIMIT_CDEG;
    bt.tt = NULL;
    bt.base = 0;
    while (r < n) {
        const int32_t *c = nk ? currents_mA + nk * r : NULL;
        const int32_t *b = b_nT + 3u * r, *t = temp_cdeg + r;
        end = run_end(temp_cdeg, r, n);
        if (end - r >= RUN_MIN) { /* a run of one temperature */
            unsigned sat = 0;
            int32_t tc = clip(temp_cdeg[r], MAGSTACK_CAL_T_LIMIT_CDEG, &sat);
            bt.tt = cached_terms(table, &cache, tc);
            bt.base = (sat ? MAGSTACK_CAL_SATURATED : 0u) |
                      ((unsigned)(tc < bt.t_lo) | (unsigned)(tc > bt.t_hi) ? MAGSTACK_CAL_OUT_OF_VALIDITY : 0u);
            switch (nk) {
            case 0: run0(table, &cache, &bt, end - r, b, t, c, out + 3u * r, status + r); break;
            case 1: run1(table, &cache, &bt, end - r, b, t, c, out + 3u * r, status + r); break;
            case 2: run2(table, &cache, &bt, end - r, b, t, c, out + 3u * r, status + r); break;
            case 3: run3(table, &cache, &bt, end - r, b, t, c, out + 3u * r, status + r); break;
            default: run4(table, &cache, &bt, end - r, b, t, c, out + 3u * r, status + r); break;
            }
        } else { /* a short run: the next MIXED_CHUNK samples */
            end = n - r > MIXED_CHUNK ? r + MIXED_CHUNK : n;
            switch (nk) {
            case 0: mixed0(table, &cache, &bt, end - r, b, t, c, out + 3u * r, status + r); break;
            case 1: mixed1(table, &cache, &bt, end - r, b, t, c, out + 3u * r, status + r); break;
            case 2: mixed2(table, &cache, &bt, end - r, b, t, c, out + 3u * r, status + r); break;
            case 3: mixed3(table, &cache, &bt, end - r, b, t, c, out + 3u * r, status + r); break;
            default: mixed4(table, &cache, &bt, end - r, b, t, c, out + 3u * r, status + r); break;
            }
        }
        r = end;
    }
}

#else /* MAGSTACK_CAL_COMPACT: one sample at a time (smallest code) */

void magstack_cal_apply_block(const magstack_cal_table *table, size_t n, const int32_t *b_nT,
                              const int32_t *temp_cdeg, const int32_t *currents_mA, int32_t *out,
                              uint8_t *status)
{
    terms_cache cache;
    size_t r, nk = table->n_currents;
    cache_init(&cache);
    for (r = 0; r < n; r++) {
        unsigned sat = 0;
        int32_t tc = clip(temp_cdeg[r], MAGSTACK_CAL_T_LIMIT_CDEG, &sat);
        status[r] = (uint8_t)sample(table, cached_terms(table, &cache, tc), b_nT + 3u * r, tc,
                                    nk ? currents_mA + nk * r : NULL, sat, out + 3u * r);
    }
}
#endif
