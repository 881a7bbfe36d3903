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
 * A LUT with the scanner's height map (/height) also answers Z from the decoded projector
 * coordinate u_p: ptplut_has_height, ptplut_height_eval(lut, row, col, u_p, &z, &dz_du, &flags),
 * ptplut_height_eval_map, ptplut_height_quality, and ptplut_height_design (the projector's
 * pattern design, to decode u_p as the calibration did).
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
    PTPLUT_ERR_MEMORY = 5,    /* out of memory */
    PTPLUT_ERR_NO_HEIGHT = 6  /* a height-map function on a LUT without /height */
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

/* --------------------------------------------------------------------------------------------
 * The scanner's height map (optional /height, METHOD.md section 9): per camera pixel
 *     Z = (p_0 + p_1 s + ... + p_D s^D) / (1 + q_1 s),  s = (u_p - u_center) / u_scale,
 * u_p the projector coordinate the scanner decodes (projector px), Z in mm. Never extrapolated:
 * u_p is in range when u_min - tol <= u_p <= u_max + tol in double, tol = 1e-6 px + |bound| * 2^-23
 * (the bounds are float32 in the file), as ptpcore's HeightMap.evaluate. (ptplut_height above is the
 * camera's height in pixels; the height map's functions are ptplut_height_*.) */

/* Per-pixel flags of a height-map evaluation (the same bits as an XY evaluation's). */
#define PTPLUT_HEIGHT_VALID 1u     /* the pixel has a usable height map (/height/valid) */
#define PTPLUT_HEIGHT_IN_RANGE 2u  /* valid, u_p finite and within the pixel's calibrated range */

/* The height map's model and the projector's pattern design, so a scanner decodes u_p as the
 * calibration did (the /height attributes). Pointers stay valid until ptplut_close. Attributes the
 * file lacks (the Python writer stores them all) are NaN, 0 or NULL as noted. */
typedef struct {
    int degree;                   /* D, the numerator's degree (1 to 5) */
    char direction;               /* 'x': the map reads u_p; 'y': v_p */
    const char *chosen_by;        /* how the degree was chosen */
    int width, height;            /* the projector's pixels: the range of u_p (and v_p) */
    int n_periods;                /* entries of periods_px and steps */
    const double *periods_px;     /* fringe periods, projector px, coarsest first */
    const int *steps;             /* phase steps per period */
    double phase_origin_rad;      /* NaN if absent */
    int shift_sign;               /* +1 or -1; 0 if absent */
    const char *unwrap;           /* "periods" or "heterodyne"; NULL if absent */
    double offset, amplitude;     /* the patterns' grey levels (NaN if absent) */
    double gamma;                 /* the display gamma the patterns were pre-compensated for (NaN if absent) */
    double camera_noise_read_var; /* the sweep's camera noise, var = read_var + gain * level: DN^2 (NaN if absent) */
    double camera_noise_gain;     /* DN (NaN if absent) */
} ptplut_height_info;

/* 1 if the LUT has a height map (/height), 0 if not. */
int ptplut_has_height(const ptplut *lut);

/* The height map's model and design; PTPLUT_ERR_NO_HEIGHT without /height. */
int ptplut_height_design(const ptplut *lut, ptplut_height_info *info);

/* Z (mm) and dZ/du_p (mm per projector px) of pixel (row, col) at its decoded u_p.
 * flags gets PTPLUT_HEIGHT_VALID and PTPLUT_HEIGHT_IN_RANGE; z and dz_du are NaN unless
 * in range (never extrapolated). dz_du and flags may be NULL. */
int ptplut_height_eval(const ptplut *lut, int row, int col, double u_p, double *z, double *dz_du,
                       unsigned *flags);

/* The same for every pixel: u_p, z, dz_du are height * width doubles, row-major (NaN = no u_p);
 * flags height * width bytes. dz_du and flags may be NULL. */
int ptplut_height_eval_map(const ptplut *lut, const double *u_p, double *z, double *dz_du,
                           unsigned char *flags);

/* The pixel's calibrated u_p range (/height/quality/u_min, u_max, projector px) and the map's
 * predicted 1-sigma of Z (/height/quality/sigma_z, mm): NaN where the pixel has no map. */
int ptplut_height_quality(const ptplut *lut, int row, int col, double *u_min, double *u_max, double *sigma_z);

/* A short name of a status code ("ok", "open", "format", ...). */
const char *ptplut_status_name(int status);

#ifdef __cplusplus
}
#endif

#endif /* PTPLUT_H */
