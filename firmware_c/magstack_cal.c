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
 * division of a negative number): the accumulator is kept as acc + ROUND_BIAS modulo 2^64 (round19). The
 * accumulator bound |acc| < 2^61.3 holds for every image the loader accepts (|K_S2| < 2^28, |t0| <= 2^15, the
 * input clips), so the modular sum is the exact one; only the final int32 conversion can overflow, and it
 * saturates. |n_i| <= 2^23, so the squares' sum is below 2^49.
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

/* An axis' accumulator is kept as u = acc + ROUND_BIAS in unsigned (modulo 2^64) arithmetic, so no product or sum
 * can overflow whatever the operands; for the inputs of a sample (|acc| < 2^62) u lies in (2^62, 3 * 2^62). */
#define ROUND_BIAS (((uint64_t)1 << 63) + ((uint64_t)1 << 18) - 1u)

/* From u = acc + ROUND_BIAS (|acc| < 2^62): acc / 2^19 rounded half away from zero, plus 2^44, without a branch.
 * Rounded half away from zero is floor((a2 + [acc >= 0]) / 2^19) with a2 = acc + 2^18 - 1; [acc >= 0] is replaced by
 * [a2 >= 0], bit 63 of u = a2 + 2^63 (the two differ only for -2^18 < acc < 0, where a2 + 1 < 2^19 keeps the
 * quotient 0), and 2^63 / 2^19 = 2^44 keeps the floor on a positive number. */
static inline uint64_t round19(uint64_t u)
{
    return (u + (u >> 63)) >> 19;
}

/* v clipped to [-lim, lim]; sets *hit when it was outside */
static int32_t clip(int32_t v, int32_t lim, unsigned *hit)
{
    *hit |= (unsigned)(v > lim) | (unsigned)(v < -lim);
    return v > lim ? lim : v < -lim ? -lim : v;
}

/* the terms of dTc: the gain matrix (2^-27) and each axis' constant (2^-27 nT) plus ROUND_BIAS */
static void make_terms(const magstack_cal_table *t, int64_t dtc, magstack_cal_terms *tt)
{
    unsigned i, j;
    for (i = 0; i < 3u; i++) {
        for (j = 0; j < 3u; j++) {
            tt->g[i][j] = (int64_t)t->S[i][j] + rdiv((int64_t)t->K_S[i][j] * dtc, 12800u);
        }
        tt->g[i][i] += rdiv(rdiv((int64_t)t->K_S2[i] * dtc, 100u) * dtc, 819200u);
        tt->c[i] = (uint64_t)((int64_t)t->O[i] * 524288 + rdiv((int64_t)t->K_O[i] * dtc * 2048, 100u)) + ROUND_BIAS;
    }
}

#ifndef MAGSTACK_CAL_COMPACT
/* |v| of an int64 as uint64 */
static uint64_t mag64(int64_t v)
{
    return v < 0 ? 0u - (uint64_t)v : (uint64_t)v;
}

/* How far the accumulators of terms p reach, per axis: reach[0][i] = sum_j |G_ij|, reach[1][i] = |constant_i|
 * (below 2^36.4 and 2^52). */
static void reach_of(const magstack_cal_terms *p, uint64_t reach[2][3])
{
    unsigned i;
    for (i = 0; i < 3u; i++) {
        const uint64_t c = p->c[i] - ROUND_BIAS;
        reach[0][i] = mag64(p->g[i][0]) + mag64(p->g[i][1]) + mag64(p->g[i][2]);
        reach[1][i] = c >> 63 ? 0u - c : c;
    }
}
#endif

/* The precomputed terms of clipped temperature tc (magstack_cal_precompute), or NULL. */
static inline const magstack_cal_terms *precomputed_terms(const magstack_cal_table *t, int32_t tc)
{
    uint32_t i = (uint32_t)tc - (uint32_t)t->pre_lo_cdeg;
    return i < t->pre_count ? t->pre + i : NULL;
}

int magstack_cal_precompute(magstack_cal_table *table, magstack_cal_terms *storage, size_t count, int32_t lo_cdeg,
                            int32_t hi_cdeg)
{
    uint32_t k, m;
    if (table == NULL) {
        return MAGSTACK_CAL_E_ARGUMENT;
    }
    table->pre = NULL;
    table->pre_lo_cdeg = 0;
    table->pre_count = 0;
    for (k = 0; k < 3u; k++) {
        table->pre_reach[0][k] = 0;
        table->pre_reach[1][k] = 0;
    }
    if (storage == NULL && count == 0u) {
        return MAGSTACK_CAL_OK;
    }
    if (storage == NULL || lo_cdeg > hi_cdeg || lo_cdeg < -MAGSTACK_CAL_T_LIMIT_CDEG ||
        hi_cdeg > MAGSTACK_CAL_T_LIMIT_CDEG) {
        return MAGSTACK_CAL_E_ARGUMENT;
    }
    m = (uint32_t)(hi_cdeg - lo_cdeg) + 1u; /* at most 2^16 + 1 */
    if (count < m) {
        return MAGSTACK_CAL_E_ARGUMENT;
    }
    for (k = 0; k < m; k++) {
        make_terms(table, (int64_t)lo_cdeg + (int64_t)k - table->t0_cdeg, &storage[k]);
#ifndef MAGSTACK_CAL_COMPACT /* the kernels' no-saturation bound */
        {
            uint64_t reach[2][3];
            unsigned i, j;
            reach_of(&storage[k], reach);
            for (i = 0; i < 2u; i++) {
                for (j = 0; j < 3u; j++) {
                    table->pre_reach[i][j] = reach[i][j] > table->pre_reach[i][j] ? reach[i][j]
                                                                                  : table->pre_reach[i][j];
                }
            }
        }
#endif
    }
    table->pre = storage;
    table->pre_lo_cdeg = lo_cdeg;
    table->pre_count = m;
    return MAGSTACK_CAL_OK;
}

/* The squared magnitude limit (nT^2, below 2^50), or 2^62, above any outputs' square sum, when the table has none. */
static uint64_t norm2_limit(const magstack_cal_table *t)
{
    return t->has_field_norm ? (uint64_t)t->field_norm_nT * (uint64_t)t->field_norm_nT : (uint64_t)1 << 62;
}

/* An output (nT * 2^8) in whole nT, rounded half away from zero: |o| + 2^7 (at most 2^31 + 2^7), then / 2^8. */
static inline uint32_t whole_nT(int32_t o)
{
    uint32_t a = (uint32_t)o, s = 0u - (a >> 31);
    return (((a ^ s) - s) + 128u) >> 8;
}

/* One sample with the terms of its temperature: the status bits. b_nT, cur_mA as given (clipped here). */
static unsigned sample(const magstack_cal_table *t, const magstack_cal_terms *tt, const int32_t *b_nT, int32_t tc,
                       const int32_t *cur_mA, unsigned sat, int32_t out[3])
{
    unsigned oov = 0, i, k;
    uint32_t n[3];
    uint64_t b[3], u[3];
    for (i = 0; i < 3u; i++) {
        b[i] = (uint64_t)(int64_t)clip(b_nT[i], MAGSTACK_CAL_B_LIMIT_NT, &sat);
    }
    oov |= (unsigned)t->has_temp_range & ((unsigned)(tc < t->temp_lo_cdeg) | (unsigned)(tc > t->temp_hi_cdeg));
    for (i = 0; i < 3u; i++) {
        u[i] = tt->c[i] + (uint64_t)tt->g[i][0] * b[0] + (uint64_t)tt->g[i][1] * b[1] + (uint64_t)tt->g[i][2] * b[2];
    }
    for (k = 0; k < t->n_currents; k++) {
        int32_t c = clip(cur_mA[k], MAGSTACK_CAL_I_LIMIT_MA, &sat);
        oov |= (unsigned)(c < t->current_lo_mA[k]) | (unsigned)(c > t->current_hi_mA[k]);
        for (i = 0; i < 3u; i++) {
            u[i] += (uint64_t)t->D[k][i] * 128u * (uint64_t)(int64_t)c;
        }
    }
    for (i = 0; i < 3u; i++) {
        int64_t o = (int64_t)round19(u[i]) - ((int64_t)1 << 44);
        sat |= (unsigned)(o > INT32_MAX) | (unsigned)(o < INT32_MIN);
        out[i] = (int32_t)(o > INT32_MAX ? INT32_MAX : o < INT32_MIN ? INT32_MIN : o);
        n[i] = whole_nT(out[i]);
        oov |= (unsigned)(n[i] > (uint32_t)t->field_axes_nT[i]);
    }
    /* whole nT are at most 2^23: the squares' sum is below 2^48 */
    oov |= (unsigned)((uint64_t)n[0] * n[0] + (uint64_t)n[1] * n[1] + (uint64_t)n[2] * n[2] > norm2_limit(t));
    return (sat ? MAGSTACK_CAL_SATURATED : 0u) | (oov ? MAGSTACK_CAL_OUT_OF_VALIDITY : 0u);
}

unsigned magstack_cal_apply(const magstack_cal_table *table, const int32_t b_nT[3], int32_t temp_cdeg,
                            const int32_t *currents_mA, int32_t out[3])
{
    unsigned sat = 0;
    int32_t tc = clip(temp_cdeg, MAGSTACK_CAL_T_LIMIT_CDEG, &sat);
    magstack_cal_terms tt;
    const magstack_cal_terms *p = precomputed_terms(table, tc);
    if (p == NULL) {
        make_terms(table, (int64_t)tc - table->t0_cdeg, &tt);
        p = &tt;
    }
    return sample(table, p, b_nT, tc, currents_mA, sat, out);
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
    magstack_cal_terms tt[MAGSTACK_CAL_TERMS_CACHE];
#ifndef MAGSTACK_CAL_COMPACT
    uint64_t reach[MAGSTACK_CAL_TERMS_CACHE][2][3]; /* reach_of(tt[i]) */
#endif
    int32_t tag[MAGSTACK_CAL_TERMS_CACHE];
} terms_cache;

static void cache_init(terms_cache *cache)
{
    unsigned i;
    for (i = 0; i < MAGSTACK_CAL_TERMS_CACHE; i++) {
        cache->tag[i] = INT32_MIN;
    }
}

#ifndef MAGSTACK_CAL_COMPACT
/* The terms of clipped temperature tc: precomputed, or from the cache (computed on a miss); *reach: how far they
 * reach (reach_of; for precomputed terms, the largest of them all). */
static inline const magstack_cal_terms *terms_reach(const magstack_cal_table *t, terms_cache *cache, int32_t tc,
                                                    const uint64_t (**reach)[3])
{
    const magstack_cal_terms *p = precomputed_terms(t, tc);
    uint32_t slot = (uint32_t)tc & (MAGSTACK_CAL_TERMS_CACHE - 1u);
    if (p != NULL) {
        *reach = t->pre_reach;
        return p;
    }
    if (cache->tag[slot] != tc) {
        make_terms(t, (int64_t)tc - t->t0_cdeg, &cache->tt[slot]);
        reach_of(&cache->tt[slot], cache->reach[slot]);
        cache->tag[slot] = tc;
    }
    *reach = (const uint64_t(*)[3])cache->reach[slot];
    return &cache->tt[slot];
}

/* The terms of clipped temperature tc: precomputed, or from the cache (computed on a miss). */
static inline const magstack_cal_terms *terms_of(const magstack_cal_table *t, terms_cache *cache, int32_t tc)
{
    const uint64_t(*reach)[3];
    return terms_reach(t, cache, tc, &reach);
}
#else
/* The terms of clipped temperature tc: precomputed, or from the cache (computed on a miss). */
static const magstack_cal_terms *terms_of(const magstack_cal_table *t, terms_cache *cache, int32_t tc)
{
    const magstack_cal_terms *p = precomputed_terms(t, tc);
    uint32_t slot = (uint32_t)tc & (MAGSTACK_CAL_TERMS_CACHE - 1u);
    if (p != NULL) {
        return p;
    }
    if (cache->tag[slot] != tc) {
        make_terms(t, (int64_t)tc - t->t0_cdeg, &cache->tt[slot]);
        cache->tag[slot] = tc;
    }
    return &cache->tt[slot];
}
#endif

/* m samples of a block, one at a time. */
static void samples(const magstack_cal_table *t, terms_cache *cache, size_t m, const int32_t *b, const int32_t *temp,
                    const int32_t *cur, int32_t *out, uint8_t *status)
{
    size_t r, nk = t->n_currents;
    for (r = 0; r < m; r++) {
        unsigned sat = 0;
        int32_t tc = clip(temp[r], MAGSTACK_CAL_T_LIMIT_CDEG, &sat);
        status[r] = (uint8_t)sample(t, terms_of(t, cache, tc), b + 3u * r, tc, nk ? cur + nk * r : NULL, sat,
                                    out + 3u * r);
    }
}

#ifndef MAGSTACK_CAL_COMPACT /* chunks of samples through kernels per number of currents */

/* What every sample of a block shares: the currents' coefficients (x 2^7, modulo 2^64) and ranges (lower end, width),
 * the field limits, the temperature range (lower end, width; the clip range without one), how far the currents
 * reach. */
typedef struct {
    uint64_t d[MAGSTACK_CAL_MAX_CURRENTS][3];
    uint32_t c_lo[MAGSTACK_CAL_MAX_CURRENTS], c_span[MAGSTACK_CAL_MAX_CURRENTS];
    uint32_t lim[3];
    uint64_t nn;
    uint32_t t_lo, t_span;
    uint64_t dsum[3]; /* sum_k |D_k,i| 2^7 */
} block_terms;

/* A block goes in chunks of CHUNK samples. A chunk whose inputs all lie inside the kernel bounds (fields
 * -2^23..2^23-1 nT, temperatures -2^15..2^15-1 centi-degC, currents -2^19..2^19-1 mA: nothing clips) goes to a kernel,
 * which computes the outputs and, when every output is an int32 (nothing saturates), the status bits (STATUS_LOOPS);
 * any other chunk is computed a sample at a time. */
#define CHUNK 32u
#define FAST_T 0x8000u   /* 2^15 */
/* round19(u) - OUT_OFFSET is out + 2^31: within 0..2^32 - 1 when out is an int32 */
#define OUT_OFFSET (((uint64_t)1 << 44) - ((uint64_t)1 << 31))
/* precomputed terms are read ahead of their use when a chunk's temperatures are more than FAR entries apart */
#define FAR 64u

/* Targets with a vector unit get the status bits in loops of their own, which a compiler vectorises (x86-64 has SSE2,
 * AArch64 NEON); elsewhere each sample's bits are found with its outputs. */
#if defined(__SSE2__) || defined(__ARM_NEON) || defined(__ARM_NEON__) || defined(__aarch64__) || defined(__ALTIVEC__)
#define STATUS_LOOPS 1
#else
#define STATUS_LOOPS 0
#endif

/* 1 when the outputs o0..o2 (nT * 2^8) in whole nT are beyond an axis limit or, in all, beyond the magnitude limit */
static inline uint32_t field_outside(const block_terms *bt, int32_t o0, int32_t o1, int32_t o2)
{
    const uint32_t n0 = whole_nT(o0), n1 = whole_nT(o1), n2 = whole_nT(o2);
    return (uint32_t)(n0 > bt->lim[0]) | (uint32_t)(n1 > bt->lim[1]) | (uint32_t)(n2 > bt->lim[2]) |
           (uint32_t)((uint64_t)n0 * n0 + (uint64_t)n1 * n1 + (uint64_t)n2 * n2 > bt->nn);
}

/* The int32 whose two's complement is the low 32 bits of v (v = out + 2^44: out, as 2^44 is a multiple of 2^32) */
static inline int32_t low_int32(uint64_t v)
{
    return (int32_t)((int64_t)((v + 0x80000000u) & 0xFFFFFFFFu) - ((int64_t)1 << 31));
}

/* 1 when no output can leave int32 for terms of this reach (reach_of), currents of reach dsum, fields of magnitude at
 * most bmag + 1 and currents of magnitude at most cmag + 1: |acc_i| <= 2^50 - 2^19 on every axis (the bound is below
 * 2^61). Then a kernel need not check its outputs. */
static inline unsigned cannot_saturate(const uint64_t reach[2][3], const uint64_t dsum[3], uint32_t bmag, uint32_t cmag)
{
    const uint64_t lim = ((uint64_t)1 << 50) - ((uint64_t)1 << 19), bm = (uint64_t)bmag + 1u, cm = (uint64_t)cmag + 1u;
    return (unsigned)(reach[1][0] + reach[0][0] * bm + dsum[0] * cm <= lim) &
           (unsigned)(reach[1][1] + reach[0][1] * bm + dsum[1] * cm <= lim) &
           (unsigned)(reach[1][2] + reach[0][2] * bm + dsum[2] * cm <= lim);
}

/* The terms of p in locals. */
#define TERMS_LOCALS(p)                                                                                           \
    const uint64_t g00 = (uint64_t)(int64_t)(p)->g[0][0], g01 = (uint64_t)(int64_t)(p)->g[0][1];                 \
    const uint64_t g02 = (uint64_t)(int64_t)(p)->g[0][2], g10 = (uint64_t)(int64_t)(p)->g[1][0];                 \
    const uint64_t g11 = (uint64_t)(int64_t)(p)->g[1][1], g12 = (uint64_t)(int64_t)(p)->g[1][2];                 \
    const uint64_t g20 = (uint64_t)(int64_t)(p)->g[2][0], g21 = (uint64_t)(int64_t)(p)->g[2][1];                 \
    const uint64_t g22 = (uint64_t)(int64_t)(p)->g[2][2], c0 = (p)->c[0], c1 = (p)->c[1], c2 = (p)->c[2]

/* The outputs of sample r with K currents, inputs inside the kernel bounds, from the terms g.., c..; without a branch.
 * With CHK, chk collects out + 2^31 of every output (an int32 output: below 2^32). o[] keeps the outputs by axis for
 * the status loops, or the status bits are found here. */
#define OUTPUTS(K, r, CHK)                                                                                        \
    do {                                                                                                          \
        const uint64_t x = (uint64_t)(int64_t)b[3u * (r)], y = (uint64_t)(int64_t)b[3u * (r) + 1u];               \
        const uint64_t z = (uint64_t)(int64_t)b[3u * (r) + 2u];                                                   \
        uint64_t u0 = c0 + g00 * x + g01 * y + g02 * z;                                                           \
        uint64_t u1 = c1 + g10 * x + g11 * y + g12 * z;                                                           \
        uint64_t u2 = c2 + g20 * x + g21 * y + g22 * z;                                                           \
        for (k = 0; k < (K); k++) {                                                                               \
            const uint64_t c = (uint64_t)(int64_t)cur[(size_t)(K) * (r) + (size_t)k];                             \
            u0 += bt->d[k][0] * c;                                                                                \
            u1 += bt->d[k][1] * c;                                                                                \
            u2 += bt->d[k][2] * c;                                                                                \
        }                                                                                                         \
        u0 = round19(u0);                                                                                         \
        u1 = round19(u1);                                                                                         \
        u2 = round19(u2);                                                                                         \
        if (CHK) {                                                                                                \
            chk |= (u0 - OUT_OFFSET) | (u1 - OUT_OFFSET) | (u2 - OUT_OFFSET);                                     \
        }                                                                                                         \
        {                                                                                                         \
            const int32_t o0 = low_int32(u0), o1 = low_int32(u1), o2 = low_int32(u2);                             \
            out[3u * (r)] = o0;                                                                                   \
            out[3u * (r) + 1u] = o1;                                                                              \
            out[3u * (r) + 2u] = o2;                                                                              \
            if (STATUS_LOOPS) {                                                                                   \
                o[0][r] = o0;                                                                                     \
                o[1][r] = o1;                                                                                     \
                o[2][r] = o2;                                                                                     \
            } else {                                                                                              \
                uint32_t oov = (uint32_t)((uint32_t)temp[r] - bt->t_lo > bt->t_span);                             \
                for (k = 0; k < (K); k++) {                                                                       \
                    oov |= (uint32_t)((uint32_t)cur[(size_t)(K) * (r) + (size_t)k] - bt->c_lo[k] > bt->c_span[k]); \
                }                                                                                                 \
                status[r] = (uint8_t)((oov | field_outside(bt, o0, o1, o2)) << 1);                                \
            }                                                                                                     \
        }                                                                                                         \
    } while (0)

#if defined(__OPTIMIZE_SIZE__) /* -Os: one sample a step, and every output checked (no second copy of a loop) */
/* The outputs of samples 0..m-1; TERMS(R) declares the terms of sample R in locals. */
#define OUTPUTS_LOOP(K, TERMS, CHK)                                                                               \
    do {                                                                                                          \
        for (r = 0; r < m; r++) {                                                                                 \
            TERMS(r)                                                                                              \
            OUTPUTS(K, r, 1);                                                                                     \
        }                                                                                                         \
    } while (0)
#define CANNOT_SATURATE(REACH) 0
#else
/* The outputs of samples 0..m-1, two a step (one when every output is checked: the rarer, shorter loop); TERMS(R)
 * declares the terms of sample R in locals. */
#define OUTPUTS_LOOP(K, TERMS, CHK)                                                                               \
    do {                                                                                                          \
        for (r = 0; r + 1u < m && !(CHK); r += 2u) {                                                              \
            {                                                                                                     \
                TERMS(r)                                                                                          \
                OUTPUTS(K, r, CHK);                                                                               \
            }                                                                                                     \
            {                                                                                                     \
                TERMS(r + 1u)                                                                                     \
                OUTPUTS(K, r + 1u, CHK);                                                                          \
            }                                                                                                     \
        }                                                                                                         \
        for (; r < m; r++) {                                                                                      \
            TERMS(r)                                                                                              \
            OUTPUTS(K, r, CHK);                                                                                   \
        }                                                                                                         \
    } while (0)
#define CANNOT_SATURATE(REACH) cannot_saturate(REACH, bt->dsum, bmag, cmag)
#endif
/* The outputs of samples 0..m-1 at one temperature (a loop a compiler with wide vectors vectorises; elsewhere two
 * samples a step). */
#if defined(__AVX2__) || defined(__OPTIMIZE_SIZE__)
#define RUN_LOOP(K, CHK)                                                                                          \
    do {                                                                                                          \
        for (r = 0; r < m; r++) {                                                                                 \
            OUTPUTS(K, r, CHK);                                                                                   \
        }                                                                                                         \
    } while (0)
#else
#define RUN_LOOP(K, CHK) OUTPUTS_LOOP(K, RUN_TERMS, CHK)
#endif
#define RUN_TERMS(R) /* the terms of the one temperature: in locals before the loop */
#define TEMP_OUTSIDE(R) (uint32_t)((uint32_t)temp[R] - t_lo > t_span)
#define RUN_OUTSIDE(R) t_out /* one temperature */
#define PRE_AT(R) ((const magstack_cal_terms *)(pre_bytes + idx[R])) /* idx: byte offsets */
#define PRE_TERMS(R) TERMS_LOCALS(PRE_AT(R));
#define CACHED_TERMS(R) TERMS_LOCALS(terms_of(t, cache, temp[R]));

/* The largest field and current magnitude of m samples, less one at most (bmag, cmag: the OR of each input's ones'
 * complement magnitude, x or -x - 1), whether their temperatures are inside +-(2^15 - 1) (twide below 2^16), and
 * whether they are all one (diff 0); loops a compiler may vectorise when M is a constant. */
#define INSIDE(M, K)                                                                                              \
    do {                                                                                                          \
        for (r = 0; r < 3u * (M); r++) {                                                                          \
            bmag |= (uint32_t)b[r] ^ (0u - ((uint32_t)b[r] >> 31));                                               \
        }                                                                                                         \
        for (r = 0; r < (M); r++) {                                                                               \
            twide |= (uint32_t)temp[r] + FAST_T;                                                                  \
            diff |= (uint32_t)temp[r] ^ (uint32_t)temp[0];                                                        \
        }                                                                                                         \
        for (k = 0; k < (K) * (int)(M); k++) {                                                                    \
            cmag |= (uint32_t)cur[k] ^ (0u - ((uint32_t)cur[k] >> 31));                                           \
        }                                                                                                         \
    } while (0)

/* The byte offset of each of m samples' precomputed terms (0 where it has none: missing not 0), and whether two of
 * them are more than FAR entries apart (far / 2^7 not 0); a loop a compiler may vectorise when M is a constant. */
#define PRECOMPUTED(M)                                                                                            \
    do {                                                                                                          \
        const uint32_t lo = (uint32_t)t->pre_lo_cdeg, count = t->pre_count, i0 = (uint32_t)temp[0] - lo;         \
        for (r = 0; r < (M); r++) {                                                                               \
            const uint32_t i = (uint32_t)temp[r] - lo, in = (uint32_t)(i < count);                                \
            idx[r] = (i & (0u - in)) * (uint32_t)sizeof(magstack_cal_terms); /* below 2^23 */                   \
            missing |= in ^ 1u;                                                                                   \
            far |= i - i0 + FAR;                                                                                  \
        }                                                                                                         \
    } while (0)

/* The status bits of m samples from their outputs o[], currents and OUTSIDE(r), 1 when sample r's temperature is
 * outside its range; loops a compiler may vectorise when M is a constant. Whole nT (at most 2^23) and the axis limits
 * (at most 2^24) are compared as int32. */
#define STATUS(M, K, OUTSIDE)                                                                                     \
    do {                                                                                                          \
        const int32_t l0 = (int32_t)bt->lim[0], l1 = (int32_t)bt->lim[1], l2 = (int32_t)bt->lim[2];              \
        const uint64_t nn = bt->nn;                                                                               \
        for (r = 0; r < (M); r++) {                                                                               \
            const uint32_t n0 = whole_nT(o[0][r]), n1 = whole_nT(o[1][r]), n2 = whole_nT(o[2][r]);                \
            uint32_t oov = (uint32_t)((int32_t)n0 > l0) | (uint32_t)((int32_t)n1 > l1) | (uint32_t)((int32_t)n2 > l2); \
            oov |= (uint32_t)((nn - ((uint64_t)n0 * n0 + (uint64_t)n1 * n1 + (uint64_t)n2 * n2)) >> 63);          \
            oov |= OUTSIDE(r);                                                                                    \
            for (k = 0; k < (K); k++) {                                                                           \
                oov |= (uint32_t)((uint32_t)cur[(size_t)(K) * r + (size_t)k] - bt->c_lo[k] > bt->c_span[k]);     \
            }                                                                                                     \
            flag[r] = oov << 1;                                                                                   \
        }                                                                                                         \
        for (r = 0; r < (M); r++) {                                                                               \
            status[r] = (uint8_t)flag[r];                                                                         \
        }                                                                                                         \
    } while (0)

#ifndef MAGSTACK_CAL_VECTOR
/* m samples whose temperatures vary: from their precomputed terms when all have them (read first when far apart, so
 * that they arrive while the loop works: a read of each entry, a C99 way to prefetch), else from the cache. */
#define MIXED_LOOP(K)                                                                                             \
    do {                                                                                                          \
        const unsigned char *pre_bytes = (const unsigned char *)t->pre;                                           \
        uint32_t idx[CHUNK], missing = 1, far = 0;                                                                \
        if (t->pre_count != 0u) {                                                                                 \
            missing = 0;                                                                                          \
            if (m == CHUNK) {                                                                                     \
                PRECOMPUTED(CHUNK);                                                                               \
            } else {                                                                                              \
                PRECOMPUTED(m);                                                                                   \
            }                                                                                                     \
        }                                                                                                         \
        if (missing == 0u) {                                                                                      \
            if (far >> 7) {                                                                                       \
                for (r = 0; r < m; r++) {                                                                         \
                    (void)*(const volatile int64_t *)&PRE_AT(r)->g[0][0];                                         \
                    (void)*(const volatile uint64_t *)&PRE_AT(r)->c[2];                                           \
                }                                                                                                 \
            }                                                                                                     \
            if (CANNOT_SATURATE(t->pre_reach)) {                                            \
                OUTPUTS_LOOP(K, PRE_TERMS, 0);                                                                    \
            } else {                                                                                              \
                OUTPUTS_LOOP(K, PRE_TERMS, 1);                                                                    \
            }                                                                                                     \
        } else {                                                                                                  \
            OUTPUTS_LOOP(K, CACHED_TERMS, 1);                                                                     \
        }                                                                                                         \
    } while (0)
#else
/* m samples whose temperatures vary: each sample's terms copied into arrays first, then a loop a compiler may
 * vectorise (MAGSTACK_CAL_VECTOR: for targets with 64-bit vector multiplies). */
#define MIXED_LOOP(K)                                                                                             \
    do {                                                                                                          \
        uint64_t G[12][CHUNK];                                                                                    \
        for (r = 0; r < m; r++) {                                                                                 \
            const magstack_cal_terms *p = terms_of(t, cache, temp[r]);                                            \
            for (k = 0; k < 3; k++) {                                                                             \
                G[3 * k][r] = (uint64_t)p->g[k][0];                                                               \
                G[3 * k + 1][r] = (uint64_t)p->g[k][1];                                                           \
                G[3 * k + 2][r] = (uint64_t)p->g[k][2];                                                           \
                G[9 + k][r] = p->c[k];                                                                            \
            }                                                                                                     \
        }                                                                                                         \
        for (r = 0; r < m; r++) {                                                                                 \
            const uint64_t g00 = G[0][r], g01 = G[1][r], g02 = G[2][r], g10 = G[3][r], g11 = G[4][r];             \
            const uint64_t g12 = G[5][r], g20 = G[6][r], g21 = G[7][r], g22 = G[8][r];                            \
            const uint64_t c0 = G[9][r], c1 = G[10][r], c2 = G[11][r];                                            \
            OUTPUTS(K, r, 1);                                                                                     \
        }                                                                                                         \
    } while (0)
#endif

/* m <= CHUNK samples with K currents: through a kernel when their inputs are inside the kernel bounds (one
 * temperature: its terms in locals, a loop a compiler may vectorise; else each sample's own terms) and every output is
 * an int32; else a sample at a time. */
#define CHUNK_KERNEL(NAME, K)                                                                                     \
    static void NAME(const magstack_cal_table *t, terms_cache *cache, const block_terms *bt, size_t m,            \
                     const int32_t *restrict b, const int32_t *restrict temp, const int32_t *restrict cur,         \
                     int32_t *restrict out, uint8_t *restrict status)                                              \
    {                                                                                                             \
        uint32_t bmag = 0, twide = 0, cmag = 0, diff = 0, flag[CHUNK];                                            \
        int32_t o[3][CHUNK];                                                                                      \
        uint64_t chk = 0;                                                                                         \
        size_t r;                                                                                                 \
        int k;                                                                                                    \
        if (m == CHUNK) {                                                                                         \
            INSIDE(CHUNK, K);                                                                                     \
        } else {                                                                                                  \
            INSIDE(m, K);                                                                                         \
        }                                                                                                         \
        if (((bmag >> 23) | (twide >> 16) | (cmag >> 19)) == 0u) { /* nothing clips */                           \
            if (diff == 0u) {                                                                                     \
                const uint64_t(*reach)[3];                                                                        \
                const magstack_cal_terms *tt = terms_reach(t, cache, temp[0], &reach);                            \
                TERMS_LOCALS(tt);                                                                                 \
                if (CANNOT_SATURATE(reach)) {                                               \
                    RUN_LOOP(K, 0);                                                                               \
                } else {                                                                                          \
                    RUN_LOOP(K, 1);                                                                               \
                }                                                                                                 \
            } else {                                                                                              \
                MIXED_LOOP(K);                                                                                    \
            }                                                                                                     \
            if (chk >> 32 == 0u) {                                                                                \
                const uint32_t t_lo = bt->t_lo, t_span = bt->t_span, t_out = TEMP_OUTSIDE(0);                     \
                if (!STATUS_LOOPS) {                                                                              \
                    (void)t_out;                                                                                  \
                } else if (diff == 0u && m == CHUNK) {                                                            \
                    STATUS(CHUNK, K, RUN_OUTSIDE);                                                                \
                } else if (m == CHUNK) {                                                                          \
                    STATUS(CHUNK, K, TEMP_OUTSIDE);                                                               \
                } else {                                                                                          \
                    STATUS(m, K, TEMP_OUTSIDE);                                                                   \
                }                                                                                                 \
                return;                                                                                           \
            }                                                                                                     \
        }                                                                                                         \
        samples(t, cache, m, b, temp, cur, out, status);                                                          \
    }

CHUNK_KERNEL(chunk0, 0)
CHUNK_KERNEL(chunk1, 1)
CHUNK_KERNEL(chunk2, 2)
CHUNK_KERNEL(chunk3, 3)
CHUNK_KERNEL(chunk4, 4)

void magstack_cal_apply_block(const magstack_cal_table *table, size_t n, const int32_t *b_nT,
                              const int32_t *temp_cdeg, const int32_t *currents_mA, int32_t *out,
                              uint8_t *status)
{
    block_terms bt;
    terms_cache cache;
    unsigned i, k;
    size_t r, nk = table->n_currents;
    cache_init(&cache);
    for (k = 0; k < MAGSTACK_CAL_MAX_CURRENTS; k++) {
        for (i = 0; i < 3u; i++) {
            bt.d[k][i] = (uint64_t)table->D[k][i] * 128u;
        }
        bt.c_lo[k] = (uint32_t)table->current_lo_mA[k];
        bt.c_span[k] = (uint32_t)table->current_hi_mA[k] - (uint32_t)table->current_lo_mA[k];
    }
    for (i = 0; i < 3u; i++) {
        bt.lim[i] = (uint32_t)table->field_axes_nT[i];
        bt.dsum[i] = 0;
        for (k = 0; k < table->n_currents; k++) {
            bt.dsum[i] += mag64(table->D[k][i]) * 128u;
        }
    }
    bt.nn = norm2_limit(table);
    bt.t_lo = (uint32_t)(table->has_temp_range ? table->temp_lo_cdeg : -MAGSTACK_CAL_T_LIMIT_CDEG);
    bt.t_span = (uint32_t)(table->has_temp_range ? table->temp_hi_cdeg : MAGSTACK_CAL_T_LIMIT_CDEG) - bt.t_lo;
    for (r = 0; r < n; r += CHUNK) {
        const size_t m = n - r < CHUNK ? n - r : CHUNK;
        const int32_t *b = b_nT + 3u * r, *t = temp_cdeg + r, *c = nk ? currents_mA + nk * r : NULL;
        switch (nk) {
        case 0: chunk0(table, &cache, &bt, m, b, t, c, out + 3u * r, status + r); break;
        case 1: chunk1(table, &cache, &bt, m, b, t, c, out + 3u * r, status + r); break;
        case 2: chunk2(table, &cache, &bt, m, b, t, c, out + 3u * r, status + r); break;
        case 3: chunk3(table, &cache, &bt, m, b, t, c, out + 3u * r, status + r); break;
        default: chunk4(table, &cache, &bt, m, b, t, c, out + 3u * r, status + r); break;
        }
    }
}

#else /* MAGSTACK_CAL_COMPACT: one sample at a time (smallest code) */

void magstack_cal_apply_block(const magstack_cal_table *table, size_t n, const int32_t *b_nT,
                              const int32_t *temp_cdeg, const int32_t *currents_mA, int32_t *out,
                              uint8_t *status)
{
    terms_cache cache;
    cache_init(&cache);
    samples(table, &cache, n, b_nT, temp_cdeg, currents_mA, out, status);
}
#endif
