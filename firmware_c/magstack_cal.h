/*
 * magstack_cal: the on-board calibration applier in C99, integer only.
 *
 * It applies a magstack calibration table, loaded from its binary image (docs/cal-table.md,
 * "Binary image"), with exactly the arithmetic of magstack's Python fixed-point applier
 * (magstack.firmware.fixed_point, docs/fixed-point.md): the same Q formats, rounding (half away
 * from zero), input clips, saturation and status bits.
 *
 * Units: field in nT (int32), temperature in centi-degC (int32), currents in mA (int32); output
 * in nT * 2^8 (Q23.8 nT, int32).
 *
 * No floating point, no heap, no division by a variable, no undefined behaviour for any input and
 * any image the loader accepts.
 *
 * Build options (preprocessor): MAGSTACK_CAL_COMPACT gives magstack_cal_apply_block a plain loop over
 * samples (smallest code, smallest stack; otherwise chunks of 32 samples go through branch-free kernels per
 * number of currents, with loops a compiler vectorises); MAGSTACK_CAL_TERMS_CACHE (a power of two, default 8)
 * is how many temperatures' terms magstack_cal_apply_block keeps on its stack (about 100 bytes each, 150 with
 * the kernels); MAGSTACK_CAL_VECTOR (hosts with 64-bit vector multiplies, -O3) lets a compiler vectorise
 * samples whose temperatures vary as well (3 KiB more stack; slower in scalar builds). A computer with the
 * memory can precompute the temperature terms of a range of temperatures (magstack_cal_precompute). The
 * functions keep no state: a table is read-only once loaded (to replace the active table, load the new image
 * into a second table, with storage of its own for precomputed terms, and swap the pointer between samples).
 */
#ifndef MAGSTACK_CAL_H
#define MAGSTACK_CAL_H

#include <stddef.h>
#include <stdint.h>

#ifdef __cplusplus
extern "C" {
#endif

/* ---- binary table image (little-endian, packed) ---- */
#define MAGSTACK_CAL_IMAGE_VERSION 2u
#define MAGSTACK_CAL_IMAGE_SIZE 336u
#define MAGSTACK_CAL_MAX_CURRENTS 4u
#define MAGSTACK_CAL_DEVICE_ID_BYTES 32u
#define MAGSTACK_CAL_CURRENT_NAME_BYTES 16u

/* term bits of the image's "terms" byte */
#define MAGSTACK_CAL_TERM_GAIN_MATRIX 0x01u
#define MAGSTACK_CAL_TERM_TEMPERATURE_GAIN 0x02u
#define MAGSTACK_CAL_TERM_TEMPERATURE_GAIN2 0x04u
#define MAGSTACK_CAL_TERM_OFFSET 0x08u
#define MAGSTACK_CAL_TERM_TEMPERATURE_OFFSET 0x10u
#define MAGSTACK_CAL_TERM_CURRENTS 0x20u

/* option bits of the image's "options" byte */
#define MAGSTACK_CAL_OPT_TEMP_RANGE 0x01u /* the validity region has a temperature range */
#define MAGSTACK_CAL_OPT_FIELD_AXES 0x02u /* per-axis field limits of their own (else each is field_limit_nT) */
#define MAGSTACK_CAL_OPT_FIELD_NORM 0x04u /* a limit on the calibrated field's magnitude */

/* ---- status bits of one sample (magstack.firmware.float_applier.ApplyFlag) ---- */
#define MAGSTACK_CAL_OUT_OF_VALIDITY 2u /* temperature, current or calibrated field outside the validity region */
#define MAGSTACK_CAL_SATURATED 4u       /* an input clipped or an output saturated */

/* ---- input clips and limits (magstack.firmware.fixed_point) ---- */
#define MAGSTACK_CAL_B_LIMIT_NT 16777216L  /* 2^24 nT */
#define MAGSTACK_CAL_T_LIMIT_CDEG 32768L   /* 2^15 centi-degC */
#define MAGSTACK_CAL_I_LIMIT_MA 1048576L   /* 2^20 mA */
#define MAGSTACK_CAL_K_S2_LIMIT 268435455L /* 2^28 - 1 */
#define MAGSTACK_CAL_B_NORM_LIMIT_NT 29058990L /* largest magnitude limit, nT (sqrt(3) 2^24, rounded down) */

/* ---- loader result codes ---- */
enum magstack_cal_result {
    MAGSTACK_CAL_OK = 0,
    MAGSTACK_CAL_E_SIZE = 1,       /* length or size field is not MAGSTACK_CAL_IMAGE_SIZE */
    MAGSTACK_CAL_E_MAGIC = 2,      /* not a magstack table image */
    MAGSTACK_CAL_E_VERSION = 3,    /* not format version 2 (a version-1 image included: re-export it) */
    MAGSTACK_CAL_E_CRC = 4,        /* CRC-32 mismatch: corrupt */
    MAGSTACK_CAL_E_RESERVED = 5,   /* a reserved byte or bit is set */
    MAGSTACK_CAL_E_TERMS = 6,      /* unknown term bit, no gain matrix, or a coefficient of an undeclared term */
    MAGSTACK_CAL_E_DEVICE_ID = 7,  /* device id empty or not NUL-padded */
    MAGSTACK_CAL_E_CURRENTS = 8,   /* more than 4 currents, a bad or repeated name, an unused slot not zero */
    MAGSTACK_CAL_E_T0 = 9,         /* |t0| > 2^15 centi-degC */
    MAGSTACK_CAL_E_K_S2 = 10,      /* |K_S2| > 2^28 - 1 */
    MAGSTACK_CAL_E_VALIDITY = 11,  /* a field, magnitude, temperature or current limit out of bounds */
    MAGSTACK_CAL_E_ARGUMENT = 12   /* a NULL pointer (or a bad argument of magstack_cal_precompute) */
};

/* The temperature terms of one temperature (storage for magstack_cal_precompute; 96 bytes, no fields to read). GCC
 * and Clang align it to 32 bytes, so that each lies in two cache lines of 64 bytes. */
#if defined(__GNUC__)
#define MAGSTACK_CAL_ALIGN32 __attribute__((aligned(32)))
#else
#define MAGSTACK_CAL_ALIGN32
#endif
typedef struct {
    int64_t g[3][3];
    uint64_t c[3];
} MAGSTACK_CAL_ALIGN32 magstack_cal_terms;

/* A loaded table (fill it with magstack_cal_load, optionally magstack_cal_precompute; do not edit it). */
typedef struct {
    uint32_t image_crc32;   /* CRC-32 of the image */
    uint32_t source_crc32;  /* crc32 of the JSON table the image was made from */
    uint8_t terms;          /* MAGSTACK_CAL_TERM_* bits */
    uint8_t n_currents;     /* 0..MAGSTACK_CAL_MAX_CURRENTS */
    uint8_t has_temp_range; /* 1: the validity region has a temperature range */
    uint8_t has_field_axes; /* 1: the table gives per-axis field limits (field_axes_nT; else each field_limit_nT) */
    uint8_t has_field_norm; /* 1: the validity region has a magnitude limit (field_norm_nT) */
    char device_id[MAGSTACK_CAL_DEVICE_ID_BYTES + 1u];
    char current_names[MAGSTACK_CAL_MAX_CURRENTS][MAGSTACK_CAL_CURRENT_NAME_BYTES + 1u];
    int32_t t0_cdeg;
    int32_t field_limit_nT;                 /* the table's field limit, nT */
    int32_t field_axes_nT[3];               /* validity: calibrated |B_i| <= this[i], nT (whole nT of the output) */
    int32_t field_norm_nT;                  /* validity: |B|^2 <= this^2, nT (when has_field_norm; else 0) */
    int32_t temp_lo_cdeg, temp_hi_cdeg;     /* validity (when has_temp_range) */
    int32_t S[3][3];                        /* Q4.27 */
    int32_t K_S[3][3];                      /* 2^-34 /degC */
    int32_t K_S2[3];                        /* 2^-40 /degC^2 */
    int32_t O[3];                           /* Q23.8 nT */
    int32_t K_O[3];                         /* Q15.16 nT/degC */
    int32_t D[MAGSTACK_CAL_MAX_CURRENTS][3]; /* Q11.20 nT/mA */
    int32_t current_lo_mA[MAGSTACK_CAL_MAX_CURRENTS], current_hi_mA[MAGSTACK_CAL_MAX_CURRENTS];
    const magstack_cal_terms *pre; /* precomputed terms of pre_lo_cdeg.. (magstack_cal_precompute), or NULL */
    int32_t pre_lo_cdeg;
    uint32_t pre_count;            /* temperatures with precomputed terms (0: none) */
    uint64_t pre_reach[2][3];      /* the precomputed terms' largest gain row sum and constant per axis (not with
                                      MAGSTACK_CAL_COMPACT) */
} magstack_cal_table;

/* CRC-32 (the zlib / IEEE 802.3 one). */
uint32_t magstack_cal_crc32(const uint8_t *data, size_t len);

/* Check an image (size, magic, version, CRC, every field's bounds) and decode it into *table.
 * Returns MAGSTACK_CAL_OK, or an error code with *table zeroed. */
int magstack_cal_load(magstack_cal_table *table, const uint8_t *image, size_t len);

/* Precompute the temperature terms of every temperature lo_cdeg..hi_cdeg (centi-degC, within
 * +-MAGSTACK_CAL_T_LIMIT_CDEG) into storage[0 .. hi_cdeg - lo_cdeg] (count entries available), for a loaded table:
 * its samples at these temperatures then cost no terms computation (for a computer with the memory: 96 bytes a
 * temperature, 1.2 MB for -40..85 degC). Call it after magstack_cal_load and before applying; storage (aligned as
 * magstack_cal_terms is) must stay while the table is used, and magstack_cal_load forgets it. storage NULL with
 * count 0: no precomputed terms.
 * Returns MAGSTACK_CAL_OK, or MAGSTACK_CAL_E_ARGUMENT (a NULL table, lo_cdeg > hi_cdeg, a temperature beyond the
 * clip, count too small) with no precomputed terms. The outputs are the same integers either way. */
int magstack_cal_precompute(magstack_cal_table *table, magstack_cal_terms *storage, size_t count, int32_t lo_cdeg,
                            int32_t hi_cdeg);

/* A short English name of a loader result code. */
const char *magstack_cal_result_name(int code);

/* One sample: b_nT[3], temperature, currents_mA[table->n_currents] (may be NULL when there are none)
 * -> out[3] in nT * 2^8; returns the status bits (MAGSTACK_CAL_OUT_OF_VALIDITY, MAGSTACK_CAL_SATURATED). */
unsigned magstack_cal_apply(const magstack_cal_table *table, const int32_t b_nT[3], int32_t temp_cdeg,
                            const int32_t *currents_mA, int32_t out[3]);

/* n samples: b_nT[3n], temp_cdeg[n], currents_mA[n * table->n_currents] (row-major; NULL when there are
 * none) -> out[3n], status[n]. The same integers as n calls of magstack_cal_apply; the temperature terms
 * are precomputed (magstack_cal_precompute) or computed once per temperature and kept for the last
 * MAGSTACK_CAL_TERMS_CACHE temperatures. */
void magstack_cal_apply_block(const magstack_cal_table *table, size_t n, const int32_t *b_nT,
                              const int32_t *temp_cdeg, const int32_t *currents_mA, int32_t *out,
                              uint8_t *status);

#ifdef __cplusplus
}
#endif

#endif /* MAGSTACK_CAL_H */
