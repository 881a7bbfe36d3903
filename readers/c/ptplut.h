/*
 * ptplut: read a PTP Studio look-up table (ptp-lut/1, HDF5) and evaluate it.
 *
 * C99, needs the HDF5 C library (build with h5cc). The contract is FORMATS.md,
 * "Look-up table, ptp-lut/1": every camera pixel (row, col) has its own table
 * Z -> (X, Y), in mm, as a polynomial in t = (Z - z_center) / z_scale ("poly")
 * or as values at calibrated heights interpolated over runs of finite nodes
 * ("linear", or "pchip" with the Fritsch-Carlson slopes of scipy's
 * PchipInterpolator). The results equal the Python engine's Lut.evaluate.
 *
 *     char msg[512];
 *     ptplut *lut;
 *     if (ptplut_open("rig.lut.h5", &lut, msg, sizeof msg) != PTPLUT_OK) {
 *         fprintf(stderr, "%s\n", msg);
 *         return 1;
 *     }
 *     double x, y;
 *     unsigned flags;
 *     ptplut_eval(lut, row, col, z_mm, 0, &x, &y, &flags);   (NaN unless flags has PTPLUT_IN_RANGE)
 *     ptplut_eval_map(lut, z_map, 1, 0, xs, ys, fl);          (z_map, xs, ys: height * width doubles)
 *     ptplut_close(lut);
 *
 * Every function returns PTPLUT_OK or an error code; none aborts or exits.
 * A LUT, once opened, is read-only: evaluating it from several threads is safe.
 */
#ifndef PTPLUT_H
#define PTPLUT_H

#include <stddef.h>

#ifdef __cplusplus
extern "C" {
#endif

#define PTPLUT_FORMAT "ptp-lut/1"

/* Status codes. */
enum {
    PTPLUT_OK = 0,
    PTPLUT_ERR_ARGUMENT = 1,  /* a NULL pointer, or a pixel outside the camera */
    PTPLUT_ERR_OPEN = 2,      /* missing or unreadable file, not HDF5, truncated or damaged */
    PTPLUT_ERR_FORMAT = 3,    /* an HDF5 file, but not ptp-lut/1 (another format or version) */
    PTPLUT_ERR_CONTENT = 4,   /* ptp-lut/1, but a dataset or attribute is missing, misshapen or wrong */
    PTPLUT_ERR_MEMORY = 5     /* out of memory */
};

/* Models (the /model "kind" attribute). */
enum { PTPLUT_POLY = 0, PTPLUT_LINEAR = 1, PTPLUT_PCHIP = 2 };

/* Per-pixel flags of an evaluation. */
#define PTPLUT_VALID 1u     /* the pixel has a usable LUT (/valid) */
#define PTPLUT_IN_RANGE 2u  /* valid, and Z within the pixel's calibrated range (/quality/z_min, z_max) */

typedef struct ptplut ptplut;

/* Open and check a ptp-lut/1 file; the whole table is read into memory.
 * On error *lut is NULL and msg (if not NULL) holds one line naming the file
 * and what is wrong. */
int ptplut_open(const char *path, ptplut **lut, char *msg, size_t msg_size);

/* Free everything; NULL is allowed. */
void ptplut_close(ptplut *lut);

int ptplut_width(const ptplut *lut);
int ptplut_height(const ptplut *lut);
int ptplut_kind(const ptplut *lut);        /* PTPLUT_POLY, PTPLUT_LINEAR or PTPLUT_PCHIP */
int ptplut_degree(const ptplut *lut);      /* poly degree, 0 for tables */
/* The calibrated range over all pixels (/model z_min, z_max), mm. */
void ptplut_z_range(const ptplut *lut, double *z_min, double *z_max);

/* X, Y (mm) of pixel (row, col) at height z (mm).
 * flags gets PTPLUT_VALID and PTPLUT_IN_RANGE bits. x and y are NaN where the
 * pixel is invalid, or outside its calibrated range unless extrapolate is
 * non-zero; tables never extrapolate beyond their nodes and give NaN between
 * NaN nodes. flags may be NULL. */
int ptplut_eval(const ptplut *lut, int row, int col, double z, int extrapolate,
                double *x, double *y, unsigned *flags);

/* The same for every pixel: z is one height (z_is_map = 0) or a height map of
 * height * width values, row-major (z_is_map = 1; NaN = no measurement).
 * x, y: height * width doubles; flags: height * width bytes, or NULL. */
int ptplut_eval_map(const ptplut *lut, const double *z, int z_is_map, int extrapolate,
                    double *x, double *y, unsigned char *flags);

/* The optional predicted 1-sigma uncertainty maps (/quality/sigma_x, sigma_y), mm.
 * Returns PTPLUT_OK with *has = 1 and the values, or *has = 0 if the file has none. */
int ptplut_sigma(const ptplut *lut, int row, int col, int *has, double *sigma_x, double *sigma_y);

/* A short name of a status code ("ok", "open", "format", ...). */
const char *ptplut_status_name(int status);

#ifdef __cplusplus
}
#endif

#endif /* PTPLUT_H */
