/*
 * magstack_cal: the on-board calibration applier in C99, integer only (see magstack_cal.h).
 *
 * Per sample, with dTc = T - t0 (centi-degC) and an int64 accumulator in units of 2^-27 nT:
 *
 *   G_ij  = S_ij + rdiv(K_S,ij * dTc, 12800)
 *   G_ii += rdiv(rdiv(K_S2,i * dTc, 100) * dTc, 819200)
 *   acc_i = sum_j G_ij * B_j + O_i * 2^19 + rdiv(K_O,i * dTc * 2^11, 100) + sum_k D_k,i * I_k * 2^7
 *   out_i = sat_int32(rshift_round(acc_i, 19))
 *
 * rdiv and rshift_round round half away from zero; they work on the magnitude in unsigned
 * arithmetic (no shift or division of a negative number). The accumulator bound |acc| < 2^61.3
 * holds for every image the loader accepts (|K_S2| < 2^28, |t0| <= 2^15, the input clips), so no
 * product or sum overflows; only the final int32 conversion can, and it saturates.
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
#define OFF_TEMP_LO 56u
#define OFF_TEMP_HI 60u
#define OFF_S 64u
#define OFF_K_S 100u
#define OFF_K_S2 136u
#define OFF_O 148u
#define OFF_K_O 160u
#define OFF_D 172u
#define OFF_CURRENT_RANGES 220u
#define OFF_CURRENT_NAMES 252u
#define OFF_CRC 316u

#define KNOWN_TERMS 0x3Fu
#define KNOWN_OPTIONS 0x01u

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
    t->temp_lo_cdeg = rd_i32(img + OFF_TEMP_LO);
    t->temp_hi_cdeg = rd_i32(img + OFF_TEMP_HI);
    t->has_temp_range = (uint8_t)(options & MAGSTACK_CAL_OPT_TEMP_RANGE);
    if (t->field_limit_nT < 0 || t->field_limit_nT > MAGSTACK_CAL_B_LIMIT_NT) {
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
    case MAGSTACK_CAL_E_VERSION: return "unknown format version";
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
/* a / d rounded half away from zero (d > 0, |a| < 2^63) */
static int64_t rdiv(int64_t a, uint64_t d)
{
    uint64_t m = a < 0 ? (uint64_t)0 - (uint64_t)a : (uint64_t)a;
    uint64_t q = (m + d / 2u) / d;
    return a < 0 ? -(int64_t)q : (int64_t)q;
}

/* a / 2^19 rounded half away from zero */
static int64_t rshift_round19(int64_t a)
{
    uint64_t m = a < 0 ? (uint64_t)0 - (uint64_t)a : (uint64_t)a;
    uint64_t q = (m + ((uint64_t)1 << 18)) >> 19;
    return a < 0 ? -(int64_t)q : (int64_t)q;
}

static int32_t clip(int32_t v, int32_t lim, unsigned *status)
{
    if (v > lim) {
        *status |= MAGSTACK_CAL_SATURATED;
        return lim;
    }
    if (v < -lim) {
        *status |= MAGSTACK_CAL_SATURATED;
        return -lim;
    }
    return v;
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

/* inputs clipped and checked against the validity box; returns dTc */
static int64_t prepare(const magstack_cal_table *t, const int32_t *b_nT, int32_t temp_cdeg, const int32_t *cur_mA,
                       int32_t bc[3], int32_t cc[MAGSTACK_CAL_MAX_CURRENTS], unsigned *status)
{
    unsigned j, k;
    int32_t tc;
    for (j = 0; j < 3u; j++) {
        bc[j] = clip(b_nT[j], MAGSTACK_CAL_B_LIMIT_NT, status);
        if (bc[j] > t->field_limit_nT || bc[j] < -t->field_limit_nT) {
            *status |= MAGSTACK_CAL_OUT_OF_VALIDITY;
        }
    }
    tc = clip(temp_cdeg, MAGSTACK_CAL_T_LIMIT_CDEG, status);
    if (t->has_temp_range && (tc < t->temp_lo_cdeg || tc > t->temp_hi_cdeg)) {
        *status |= MAGSTACK_CAL_OUT_OF_VALIDITY;
    }
    for (k = 0; k < t->n_currents; k++) {
        cc[k] = clip(cur_mA[k], MAGSTACK_CAL_I_LIMIT_MA, status);
        if (cc[k] < t->current_lo_mA[k] || cc[k] > t->current_hi_mA[k]) {
            *status |= MAGSTACK_CAL_OUT_OF_VALIDITY;
        }
    }
    return (int64_t)tc - (int64_t)t->t0_cdeg;
}

static void accumulate(const magstack_cal_table *t, const temperature_terms *tt, const int32_t bc[3],
                       const int32_t cc[MAGSTACK_CAL_MAX_CURRENTS], int32_t out[3], unsigned *status)
{
    unsigned i, k;
    for (i = 0; i < 3u; i++) {
        int64_t acc = tt->g[i][0] * bc[0] + tt->g[i][1] * bc[1] + tt->g[i][2] * bc[2] + tt->c[i];
        int64_t o;
        for (k = 0; k < t->n_currents; k++) {
            acc += (int64_t)t->D[k][i] * cc[k] * 128;
        }
        o = rshift_round19(acc);
        if (o > INT32_MAX) {
            out[i] = INT32_MAX;
            *status |= MAGSTACK_CAL_SATURATED;
        } else if (o < INT32_MIN) {
            out[i] = INT32_MIN;
            *status |= MAGSTACK_CAL_SATURATED;
        } else {
            out[i] = (int32_t)o;
        }
    }
}

unsigned magstack_cal_apply(const magstack_cal_table *table, const int32_t b_nT[3], int32_t temp_cdeg,
                            const int32_t *currents_mA, int32_t out[3])
{
    unsigned status = 0;
    int32_t bc[3], cc[MAGSTACK_CAL_MAX_CURRENTS] = {0, 0, 0, 0};
    temperature_terms tt;
    int64_t dtc = prepare(table, b_nT, temp_cdeg, currents_mA, bc, cc, &status);
    make_terms(table, dtc, &tt);
    accumulate(table, &tt, bc, cc, out, &status);
    return status;
}

void magstack_cal_apply_block(const magstack_cal_table *table, size_t n, const int32_t *b_nT,
                              const int32_t *temp_cdeg, const int32_t *currents_mA, int32_t *out,
                              uint8_t *status)
{
    size_t r;
    int32_t bc[3], cc[MAGSTACK_CAL_MAX_CURRENTS] = {0, 0, 0, 0};
    temperature_terms tt;
    int64_t last = 0;
    int have = 0;
    for (r = 0; r < n; r++) {
        unsigned st = 0;
        int64_t dtc = prepare(table, b_nT + 3u * r, temp_cdeg[r],
                              table->n_currents ? currents_mA + (size_t)table->n_currents * r : NULL, bc, cc, &st);
        if (!have || dtc != last) {
            make_terms(table, dtc, &tt);
            last = dtc;
            have = 1;
        }
        accumulate(table, &tt, bc, cc, out + 3u * r, &st);
        status[r] = (uint8_t)st;
    }
}
