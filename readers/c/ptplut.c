/*
 * ptplut.c: ptp-lut/1 reader and evaluator (see ptplut.h and FORMATS.md).
 *
 * Reading: every dataset's rank, shape and type class is checked before any
 * memory is allocated for it; HDF5 converts the stored numbers to double.
 * The checks follow the Python reader (ptpcore load_lut): a file it refuses,
 * this refuses too, with a message naming the file and the dataset.
 *
 * Evaluation follows ptpcore's Lut.evaluate number for number:
 *  - range: valid and z_min - tol <= z <= z_max + tol in double, tol = 1e-9 mm +
 *    |bound| * 2^-23 (two float32 half-steps: a reading stored as float32 is in range);
 *  - poly: Horner's rule in t = (z - z_center) / z_scale;
 *  - tables: each of X and Y over the maximal run of consecutive finite nodes
 *    that contains z (within 1e-9 mm); a run of one node gives nothing; linear
 *    between neighbouring nodes; pchip with scipy's PchipInterpolator slopes
 *    (weighted harmonic mean inside, its three-point end slopes, a run of two
 *    nodes linear) and its cubic Hermite coefficients.
 *
 * The optional height map (/height) follows ptpcore's read_height_group and
 * HeightMap.evaluate the same way: Horner's rule with its derivative in
 * s = (u_p - u_center) / u_scale, the rational's quotient rule, in the same
 * order of operations; range u_min - tol <= u_p <= u_max + tol in double,
 * tol = 1e-6 px + |bound| * 2^-23.
 */
#include "ptplut.h"

#include <errno.h>
#include <limits.h>
#include <math.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include <hdf5.h>

struct hmap;
static void free_hmap(struct hmap *h);

#define RANGE_EPS 1e-9
#define RANGE_REL 0x1p-23
#define HEIGHT_RANGE_EPS 1e-6 /* projector px */
#define MAX_LIST 4096         /* entries of periods_px / steps */
#define MAX_DEGREE 5

struct ptplut {
    int width, height, kind, degree;
    int n_lead;                /* D + 1 coefficients, or K nodes */
    double z_center, z_scale, z_min, z_max;
    double *x, *y;             /* [n_lead][height][width] */
    double *z_nodes;           /* [K], tables only */
    unsigned char *valid;      /* [height][width], 0 or 1 */
    double *lo, *hi;           /* per-pixel range bounds, eps included */
    double *sigma_x, *sigma_y; /* optional */
    struct hmap *hmap;         /* optional /height */
};

/* The height map (/height): per-pixel arrays [height][width], p [degree + 1][height][width]. */
struct hmap {
    ptplut_height_info info;
    char *direction, *chosen_by, *unwrap; /* owned strings behind info */
    double *periods;
    int *steps;
    double *u_center, *u_scale, *p, *q;
    unsigned char *valid;
    double *u_min, *u_max;     /* as stored (float32 values) */
    double *lo, *hi;           /* range bounds, tol included */
    double *sigma_z;
};

/* --------------------------------------------------------------------------- errors */

typedef struct {
    const char *path;
    char *msg;
    size_t size;
} ctx_t;

static int fail(ctx_t *c, int status, const char *fmt, ...)
{
    if (c->msg && c->size) {
        va_list ap;
        int n = snprintf(c->msg, c->size, "%s: ", c->path);
        if (n >= 0 && (size_t)n < c->size) {
            va_start(ap, fmt);
            vsnprintf(c->msg + n, c->size - (size_t)n, fmt, ap);
            va_end(ap);
        }
    }
    return status;
}

const char *ptplut_status_name(int status)
{
    switch (status) {
    case PTPLUT_OK: return "ok";
    case PTPLUT_ERR_ARGUMENT: return "argument";
    case PTPLUT_ERR_OPEN: return "open";
    case PTPLUT_ERR_FORMAT: return "format";
    case PTPLUT_ERR_CONTENT: return "content";
    case PTPLUT_ERR_MEMORY: return "memory";
    case PTPLUT_ERR_NO_HEIGHT: return "no height";
    default: return "unknown";
    }
}

/* --------------------------------------------------------------------------- attributes */

/* Read a scalar text attribute (fixed or variable length) into a new string.
 * Returns PTPLUT_OK, or an error with the message set; *out is NULL if absent
 * and `required` is 0. */
static int read_text_attr(ctx_t *c, hid_t obj, const char *objname, const char *name, int required,
                          char **out)
{
    hid_t attr = -1, type = -1, space = -1, mem = -1;
    int status = PTPLUT_OK;
    *out = NULL;
    htri_t exists = H5Aexists(obj, name);
    if (exists <= 0) {
        if (!required && exists == 0) return PTPLUT_OK;
        return fail(c, exists < 0 ? PTPLUT_ERR_OPEN : PTPLUT_ERR_CONTENT,
                    exists < 0 ? "attributes of %s unreadable (truncated or damaged?)"
                               : "missing attribute '%s' of %s",
                    exists < 0 ? objname : name, objname);
    }
    if ((attr = H5Aopen(obj, name, H5P_DEFAULT)) < 0 || (type = H5Aget_type(attr)) < 0
        || (space = H5Aget_space(attr)) < 0) {
        status = fail(c, PTPLUT_ERR_OPEN, "attribute '%s' of %s unreadable", name, objname);
        goto done;
    }
    if (H5Tget_class(type) != H5T_STRING || H5Sget_simple_extent_npoints(space) != 1) {
        status = fail(c, PTPLUT_ERR_CONTENT, "attribute '%s' of %s must be text", name, objname);
        goto done;
    }
    if (H5Tis_variable_str(type) > 0) {
        char *s = NULL;
        if ((mem = H5Tcopy(H5T_C_S1)) < 0 || H5Tset_size(mem, H5T_VARIABLE) < 0
            || H5Tset_cset(mem, H5Tget_cset(type)) < 0 || H5Aread(attr, mem, &s) < 0 || s == NULL) {
            status = fail(c, PTPLUT_ERR_OPEN, "attribute '%s' of %s unreadable", name, objname);
            goto done;
        }
        *out = malloc(strlen(s) + 1);
        if (*out) strcpy(*out, s);
        H5free_memory(s);
    } else {
        size_t n = H5Tget_size(type);
        if (n == 0 || n > (1u << 20)) {
            status = fail(c, PTPLUT_ERR_CONTENT, "attribute '%s' of %s has a bad size", name, objname);
            goto done;
        }
        *out = calloc(n + 1, 1);
        if (*out && ((mem = H5Tcopy(type)) < 0 || H5Aread(attr, mem, *out) < 0)) {
            free(*out);
            *out = NULL;
            status = fail(c, PTPLUT_ERR_OPEN, "attribute '%s' of %s unreadable", name, objname);
            goto done;
        }
    }
    if (!*out) status = fail(c, PTPLUT_ERR_MEMORY, "out of memory");
done:
    if (mem >= 0) H5Tclose(mem);
    if (space >= 0) H5Sclose(space);
    if (type >= 0) H5Tclose(type);
    if (attr >= 0) H5Aclose(attr);
    return status;
}

/* Read a numeric attribute holding one value; integers must be whole. */
static int read_number_attr(ctx_t *c, hid_t obj, const char *objname, const char *name, int integer,
                            double *out)
{
    hid_t attr = -1, type = -1, space = -1;
    int status = PTPLUT_OK;
    htri_t exists = H5Aexists(obj, name);
    if (exists <= 0)
        return fail(c, exists < 0 ? PTPLUT_ERR_OPEN : PTPLUT_ERR_CONTENT, "missing attribute '%s' of %s",
                    name, objname);
    if ((attr = H5Aopen(obj, name, H5P_DEFAULT)) < 0 || (type = H5Aget_type(attr)) < 0
        || (space = H5Aget_space(attr)) < 0) {
        status = fail(c, PTPLUT_ERR_OPEN, "attribute '%s' of %s unreadable", name, objname);
        goto done;
    }
    H5T_class_t cls = H5Tget_class(type);
    if ((cls != H5T_INTEGER && cls != H5T_FLOAT) || H5Sget_simple_extent_npoints(space) != 1) {
        status = fail(c, PTPLUT_ERR_CONTENT, "attribute '%s' of %s must be a number", name, objname);
        goto done;
    }
    if (H5Aread(attr, H5T_NATIVE_DOUBLE, out) < 0) {
        status = fail(c, PTPLUT_ERR_OPEN, "attribute '%s' of %s unreadable", name, objname);
        goto done;
    }
    if (!isfinite(*out)) {
        status = fail(c, PTPLUT_ERR_CONTENT, "attribute '%s' of %s must be finite", name, objname);
    } else if (integer && (*out != floor(*out) || fabs(*out) > (double)INT_MAX)) {
        status = fail(c, PTPLUT_ERR_CONTENT, "attribute '%s' of %s must be an integer, got %g", name,
                      objname, *out);
    }
done:
    if (space >= 0) H5Sclose(space);
    if (type >= 0) H5Tclose(type);
    if (attr >= 0) H5Aclose(attr);
    return status;
}

/* --------------------------------------------------------------------------- datasets */

/* Is `path` (absolute, e.g. "/quality/z_min") a link in the file? Checks every
 * level, so a missing group is "no" rather than an HDF5 error. */
static int has_link(hid_t file, const char *path)
{
    char buf[256];
    size_t n = strlen(path);
    if (n >= sizeof buf) return 0;
    memcpy(buf, path, n + 1);
    for (size_t i = 1; i <= n; i++) {
        if (buf[i] == '/' || buf[i] == '\0') {
            char keep = buf[i];
            buf[i] = '\0';
            if (H5Lexists(file, buf, H5P_DEFAULT) <= 0) return 0;
            buf[i] = keep;
        }
    }
    return 1;
}

enum { NUM_FLOAT = 1, NUM_INT = 2 };

/* Open dataset `path`, check its rank, shape (`want`, -1 = any) and type class;
 * if `data` is not NULL read it as double into a new array. `is_f32` (may be
 * NULL) tells whether it is stored as a float of 4 bytes or fewer. */
static int read_dataset(ctx_t *c, hid_t file, const char *path, int rank, const long long *want,
                        int classes, double **data, hsize_t *dims, int *is_f32)
{
    hid_t ds = -1, space = -1, type = -1;
    int status = PTPLUT_OK;
    hsize_t d[8];
    if (data) *data = NULL;
    if (!has_link(file, path)) return fail(c, PTPLUT_ERR_CONTENT, "missing dataset %s", path);
    if ((ds = H5Dopen2(file, path, H5P_DEFAULT)) < 0) {
        status = fail(c, PTPLUT_ERR_CONTENT, "%s is not a dataset (or unreadable)", path);
        goto done;
    }
    if ((space = H5Dget_space(ds)) < 0 || (type = H5Dget_type(ds)) < 0) {
        status = fail(c, PTPLUT_ERR_OPEN, "%s unreadable (truncated or damaged?)", path);
        goto done;
    }
    H5T_class_t cls = H5Tget_class(type);
    if (!((cls == H5T_FLOAT && (classes & NUM_FLOAT)) || (cls == H5T_INTEGER && (classes & NUM_INT)))) {
        status = fail(c, PTPLUT_ERR_CONTENT, "%s has the wrong type, expected %s", path,
                      classes == NUM_FLOAT ? "floating point numbers"
                                           : classes == NUM_INT ? "integers" : "numbers");
        goto done;
    }
    if (is_f32) *is_f32 = cls == H5T_FLOAT && H5Tget_size(type) <= 4;
    int nd = H5Sget_simple_extent_ndims(space);
    if (nd != rank || H5Sget_simple_extent_type(space) != H5S_SIMPLE) {
        status = fail(c, PTPLUT_ERR_CONTENT, "%s has %d dimensions, expected %d", path, nd, rank);
        goto done;
    }
    H5Sget_simple_extent_dims(space, d, NULL);
    size_t count = 1;
    for (int i = 0; i < rank; i++) {
        if (want && want[i] >= 0 && d[i] != (hsize_t)want[i]) {
            char got[96] = "", exp[96] = "";
            for (int j = 0; j < rank; j++) {
                size_t gl = strlen(got), el = strlen(exp);
                snprintf(got + gl, sizeof got - gl, "%s%llu", j ? ", " : "", (unsigned long long)d[j]);
                if (want[j] >= 0)
                    snprintf(exp + el, sizeof exp - el, "%s%lld", j ? ", " : "", want[j]);
                else
                    snprintf(exp + el, sizeof exp - el, "%s*", j ? ", " : "");
            }
            status = fail(c, PTPLUT_ERR_CONTENT, "%s has shape (%s), expected (%s)", path, got, exp);
            goto done;
        }
        if (d[i] != 0 && count > SIZE_MAX / sizeof(double) / d[i]) {
            status = fail(c, PTPLUT_ERR_CONTENT, "%s is too large", path);
            goto done;
        }
        count *= (size_t)d[i];
        if (dims) dims[i] = d[i];
    }
    if (data) {
        *data = malloc(count ? count * sizeof(double) : 1);
        if (!*data) {
            status = fail(c, PTPLUT_ERR_MEMORY, "out of memory reading %s", path);
            goto done;
        }
        if (count && H5Dread(ds, H5T_NATIVE_DOUBLE, H5S_ALL, H5S_ALL, H5P_DEFAULT, *data) < 0) {
            free(*data);
            *data = NULL;
            status = fail(c, PTPLUT_ERR_OPEN, "%s unreadable (truncated or damaged?)", path);
            goto done;
        }
    }
done:
    if (type >= 0) H5Tclose(type);
    if (space >= 0) H5Sclose(space);
    if (ds >= 0) H5Dclose(ds);
    return status;
}

/* --------------------------------------------------------------------------- open */

static int is_hdf5_signature(const char *path)
{
    static const unsigned char sig[8] = {0x89, 'H', 'D', 'F', '\r', '\n', 0x1a, '\n'};
    unsigned char buf[8];
    FILE *f = fopen(path, "rb");
    int found = 0;
    if (!f) return 0;
    for (long off = 0; off <= 8192 && !found; off = off ? off * 2 : 512) {
        if (fseek(f, off, SEEK_SET) != 0 || fread(buf, 1, 8, f) != 8) break;
        found = memcmp(buf, sig, 8) == 0;
    }
    fclose(f);
    return found;
}

static int check_format(ctx_t *c, hid_t file)
{
    char *fmt = NULL;
    htri_t exists = H5Aexists(file, "format");
    if (exists < 0) return fail(c, PTPLUT_ERR_OPEN, "not a readable HDF5 file (truncated or damaged?)");
    if (exists == 0) return fail(c, PTPLUT_ERR_FORMAT, "attribute 'format' is missing, expected '%s'", PTPLUT_FORMAT);
    int status = read_text_attr(c, file, "/", "format", 1, &fmt);
    if (status == PTPLUT_ERR_CONTENT)
        return fail(c, PTPLUT_ERR_FORMAT, "attribute 'format' is not text, expected '%s'", PTPLUT_FORMAT);
    if (status != PTPLUT_OK) return status;
    if (strcmp(fmt, PTPLUT_FORMAT) != 0) {
        const char *fam = "ptp-lut/";
        size_t fl = strlen(fam);
        if (strncmp(fmt, fam, fl) == 0) {
            const char *v = fmt + fl;
            int digits = *v != '\0';
            for (const char *p = v; *p; p++) digits &= *p >= '0' && *p <= '9';
            if (digits && strtol(v, NULL, 10) > 1)
                status = fail(c, PTPLUT_ERR_FORMAT, "format '%.60s' is newer than this reader reads (%s)", fmt,
                              PTPLUT_FORMAT);
            else
                status = fail(c, PTPLUT_ERR_FORMAT, "format '%.60s' is not supported (this reader reads %s)", fmt,
                              PTPLUT_FORMAT);
        } else {
            status = fail(c, PTPLUT_ERR_FORMAT, "attribute 'format' is '%.60s', expected '%s'", fmt, PTPLUT_FORMAT);
        }
    }
    free(fmt);
    return status;
}

static int read_model(ctx_t *c, hid_t file, ptplut *lut)
{
    hid_t cam = -1, model = -1;
    char *kind = NULL;
    double v;
    int status;
    if (!has_link(file, "/camera")) return fail(c, PTPLUT_ERR_CONTENT, "missing group /camera");
    if (!has_link(file, "/model")) return fail(c, PTPLUT_ERR_CONTENT, "missing group /model");
    if ((cam = H5Oopen(file, "/camera", H5P_DEFAULT)) < 0) {
        status = fail(c, PTPLUT_ERR_OPEN, "/camera unreadable");
        goto done;
    }
    if ((status = read_number_attr(c, cam, "/camera", "height", 1, &v)) != PTPLUT_OK) goto done;
    lut->height = (int)v;
    if ((status = read_number_attr(c, cam, "/camera", "width", 1, &v)) != PTPLUT_OK) goto done;
    lut->width = (int)v;
    if (lut->width < 1 || lut->height < 1) {
        status = fail(c, PTPLUT_ERR_CONTENT, "/camera size %dx%d must be positive", lut->width, lut->height);
        goto done;
    }
    if ((model = H5Oopen(file, "/model", H5P_DEFAULT)) < 0) {
        status = fail(c, PTPLUT_ERR_OPEN, "/model unreadable");
        goto done;
    }
    if ((status = read_text_attr(c, model, "/model", "kind", 1, &kind)) != PTPLUT_OK) goto done;
    if (strcmp(kind, "poly") == 0) lut->kind = PTPLUT_POLY;
    else if (strcmp(kind, "linear") == 0) lut->kind = PTPLUT_LINEAR;
    else if (strcmp(kind, "pchip") == 0) lut->kind = PTPLUT_PCHIP;
    else {
        status = fail(c, PTPLUT_ERR_CONTENT, "attribute 'kind' of /model is '%.40s', not poly, pchip or linear", kind);
        goto done;
    }
    if (lut->kind == PTPLUT_POLY) {
        if ((status = read_number_attr(c, model, "/model", "degree", 1, &v)) != PTPLUT_OK) goto done;
        if (v < 1 || v > MAX_DEGREE) {
            status = fail(c, PTPLUT_ERR_CONTENT, "attribute 'degree' of /model must be 1 to %d, got %g", MAX_DEGREE, v);
            goto done;
        }
        lut->degree = (int)v;
    }
    if ((status = read_number_attr(c, model, "/model", "z_center", 0, &lut->z_center)) != PTPLUT_OK
        || (status = read_number_attr(c, model, "/model", "z_scale", 0, &lut->z_scale)) != PTPLUT_OK
        || (status = read_number_attr(c, model, "/model", "z_min", 0, &lut->z_min)) != PTPLUT_OK
        || (status = read_number_attr(c, model, "/model", "z_max", 0, &lut->z_max)) != PTPLUT_OK)
        goto done;
    if (!(lut->z_scale > 0)) {
        status = fail(c, PTPLUT_ERR_CONTENT, "attribute 'z_scale' of /model must be positive, got %g", lut->z_scale);
    } else if (lut->z_min > lut->z_max) {
        status = fail(c, PTPLUT_ERR_CONTENT, "attributes 'z_min' > 'z_max' of /model (%g > %g)", lut->z_min,
                      lut->z_max);
    }
done:
    free(kind);
    if (model >= 0) H5Oclose(model);
    if (cam >= 0) H5Oclose(cam);
    return status;
}

/* The per-pixel range bounds, as Lut.evaluate computes them (in double): the stored bound
 * widened by 1e-9 mm plus two float32 half-steps of it, so that a reading kept as float32
 * (0.1 mm stored as 0.10000000149) is itself in range. */
static double lower_bound(double v)
{
    return v - (RANGE_EPS + fabs(v) * RANGE_REL);
}

static double upper_bound(double v)
{
    return v + (RANGE_EPS + fabs(v) * RANGE_REL);
}

static int read_tables(ctx_t *c, hid_t file, ptplut *lut)
{
    const long long h = lut->height, w = lut->width;
    const size_t hw = (size_t)h * (size_t)w;
    hsize_t nd[1];
    double *valid = NULL, *npos = NULL;
    int status;

    if (lut->kind != PTPLUT_POLY) {
        if ((status = read_dataset(c, file, "/z_nodes", 1, NULL, NUM_FLOAT, &lut->z_nodes, nd, NULL)) != PTPLUT_OK)
            return status;
        if (nd[0] < 2 || nd[0] > 65535)
            return fail(c, PTPLUT_ERR_CONTENT, "/z_nodes must hold 2 to 65535 heights, got %llu",
                        (unsigned long long)nd[0]);
        for (hsize_t k = 0; k < nd[0]; k++)
            if (!isfinite(lut->z_nodes[k]) || (k && !(lut->z_nodes[k] > lut->z_nodes[k - 1])))
                return fail(c, PTPLUT_ERR_CONTENT, "/z_nodes must hold at least 2 finite, strictly ascending heights");
        lut->n_lead = (int)nd[0];
    } else {
        lut->n_lead = lut->degree + 1;
    }
    const long long shape3[3] = {lut->n_lead, h, w}, shape2[2] = {h, w};
    if ((status = read_dataset(c, file, "/x", 3, shape3, NUM_FLOAT, &lut->x, NULL, NULL)) != PTPLUT_OK
        || (status = read_dataset(c, file, "/y", 3, shape3, NUM_FLOAT, &lut->y, NULL, NULL)) != PTPLUT_OK
        || (status = read_dataset(c, file, "/valid", 2, shape2, NUM_INT, &valid, NULL, NULL)) != PTPLUT_OK)
        goto done;
    static const char *const others[] = {"/quality/rms_x", "/quality/rms_y", "/quality/loo_x", "/quality/loo_y"};
    for (size_t i = 0; i < sizeof others / sizeof *others; i++)
        if ((status = read_dataset(c, file, others[i], 2, shape2, NUM_FLOAT | NUM_INT, NULL, NULL, NULL)) != PTPLUT_OK)
            goto done;
    if ((status = read_dataset(c, file, "/quality/n_positions", 2, shape2, NUM_FLOAT | NUM_INT, &npos, NULL, NULL))
            != PTPLUT_OK
        || (status = read_dataset(c, file, "/quality/z_min", 2, shape2, NUM_FLOAT | NUM_INT, &lut->lo, NULL, NULL))
            != PTPLUT_OK
        || (status = read_dataset(c, file, "/quality/z_max", 2, shape2, NUM_FLOAT | NUM_INT, &lut->hi, NULL, NULL))
            != PTPLUT_OK)
        goto done;
    if (has_link(file, "/quality/sigma_x") && has_link(file, "/quality/sigma_y")) {
        if ((status = read_dataset(c, file, "/quality/sigma_x", 2, shape2, NUM_FLOAT, &lut->sigma_x, NULL, NULL))
                != PTPLUT_OK
            || (status = read_dataset(c, file, "/quality/sigma_y", 2, shape2, NUM_FLOAT, &lut->sigma_y, NULL, NULL))
                != PTPLUT_OK)
            goto done;
    }
    if (!(lut->valid = malloc(hw))) {
        status = fail(c, PTPLUT_ERR_MEMORY, "out of memory");
        goto done;
    }
    for (size_t p = 0; p < hw; p++) {
        if (valid[p] != 0.0 && valid[p] != 1.0) {
            status = fail(c, PTPLUT_ERR_CONTENT, "/valid must hold only 0 and 1");
            goto done;
        }
        lut->valid[p] = valid[p] == 1.0;
    }
    for (size_t p = 0; p < hw; p++) {
        const double *tabs[2] = {lut->x, lut->y};
        for (int a = 0; a < 2; a++) {
            int finite = 0;
            for (int k = 0; k < lut->n_lead; k++) {
                double v = tabs[a][(size_t)k * hw + p];
                if (lut->kind != PTPLUT_POLY && isinf(v)) {
                    status = fail(c, PTPLUT_ERR_CONTENT, "%s holds infinite values", a ? "/y" : "/x");
                    goto done;
                }
                finite += isfinite(v) != 0;
            }
            if (lut->valid[p] && lut->kind == PTPLUT_POLY && finite < lut->n_lead) {
                status = fail(c, PTPLUT_ERR_CONTENT, "%s holds NaN or infinite coefficients for pixels marked valid",
                              a ? "/y" : "/x");
                goto done;
            }
            if (lut->valid[p] && lut->kind != PTPLUT_POLY && finite < 2) {
                status = fail(c, PTPLUT_ERR_CONTENT, "%s has fewer than 2 finite nodes for pixels marked valid",
                              a ? "/y" : "/x");
                goto done;
            }
        }
        if (!lut->valid[p]) continue;
        if (!(npos[p] >= 1)) {
            status = fail(c, PTPLUT_ERR_CONTENT, "/quality/n_positions is 0 for pixels marked valid");
            goto done;
        }
        if (!isfinite(lut->lo[p]) || !isfinite(lut->hi[p])) {
            status = fail(c, PTPLUT_ERR_CONTENT, "/quality/z_min or /quality/z_max holds NaN for pixels marked valid");
            goto done;
        }
        if (lut->lo[p] > lut->hi[p]) {
            status = fail(c, PTPLUT_ERR_CONTENT, "/quality/z_min exceeds /quality/z_max for some valid pixels");
            goto done;
        }
    }
    for (size_t p = 0; p < hw; p++) {
        lut->lo[p] = lower_bound(lut->lo[p]);
        lut->hi[p] = upper_bound(lut->hi[p]);
    }
done:
    free(valid);
    free(npos);
    return status;
}

/* --------------------------------------------------------------------------- the height map */

static void free_hmap(struct hmap *h)
{
    if (!h) return;
    free(h->direction);
    free(h->chosen_by);
    free(h->unwrap);
    free(h->periods);
    free(h->steps);
    free(h->u_center);
    free(h->u_scale);
    free(h->p);
    free(h->q);
    free(h->valid);
    free(h->u_min);
    free(h->u_max);
    free(h->lo);
    free(h->hi);
    free(h->sigma_z);
    free(h);
}

/* A list attribute of numbers (rank 1, at least one entry, finite), read as double. */
static int read_list_attr(ctx_t *c, hid_t obj, const char *name, double **out, int *count)
{
    hid_t attr = -1, type = -1, space = -1;
    int status = PTPLUT_OK;
    *out = NULL;
    htri_t exists = H5Aexists(obj, name);
    if (exists <= 0)
        return fail(c, exists < 0 ? PTPLUT_ERR_OPEN : PTPLUT_ERR_CONTENT, "missing attribute '%s' of /height", name);
    if ((attr = H5Aopen(obj, name, H5P_DEFAULT)) < 0 || (type = H5Aget_type(attr)) < 0
        || (space = H5Aget_space(attr)) < 0) {
        status = fail(c, PTPLUT_ERR_OPEN, "attribute '%s' of /height unreadable", name);
        goto done;
    }
    H5T_class_t cls = H5Tget_class(type);
    hssize_t n = H5Sget_simple_extent_npoints(space);
    if ((cls != H5T_INTEGER && cls != H5T_FLOAT) || H5Sget_simple_extent_type(space) != H5S_SIMPLE
        || H5Sget_simple_extent_ndims(space) != 1 || n < 1 || n > MAX_LIST) {
        status = fail(c, PTPLUT_ERR_CONTENT, "attribute '%s' of /height must be a list of 1 to %d numbers", name,
                      MAX_LIST);
        goto done;
    }
    if (!(*out = malloc((size_t)n * sizeof **out))) {
        status = fail(c, PTPLUT_ERR_MEMORY, "out of memory");
        goto done;
    }
    if (H5Aread(attr, H5T_NATIVE_DOUBLE, *out) < 0) {
        status = fail(c, PTPLUT_ERR_OPEN, "attribute '%s' of /height unreadable", name);
        goto done;
    }
    for (hssize_t i = 0; i < n; i++)
        if (!isfinite((*out)[i])) {
            status = fail(c, PTPLUT_ERR_CONTENT, "attribute '%s' of /height must be a list of numbers", name);
            goto done;
        }
    *count = (int)n;
done:
    if (status != PTPLUT_OK) {
        free(*out);
        *out = NULL;
    }
    if (space >= 0) H5Sclose(space);
    if (type >= 0) H5Tclose(type);
    if (attr >= 0) H5Aclose(attr);
    return status;
}

/* An optional numeric attribute: *out stays `absent` when the file lacks it. */
static int read_optional_number(ctx_t *c, hid_t obj, const char *name, int integer, double absent, double *out)
{
    *out = absent;
    htri_t exists = H5Aexists(obj, name);
    if (exists < 0) return fail(c, PTPLUT_ERR_OPEN, "attributes of /height unreadable (truncated or damaged?)");
    return exists ? read_number_attr(c, obj, "/height", name, integer, out) : PTPLUT_OK;
}

/* The /height attributes: model, pattern design, camera noise (as ptpcore's read_height_group). */
static int read_height_attrs(ctx_t *c, hid_t g, struct hmap *h)
{
    ptplut_height_info *in = &h->info;
    char *kind = NULL, *prov = NULL;
    double v, *steps = NULL;
    int status, n_steps = 0;
    if ((status = read_text_attr(c, g, "/height", "kind", 1, &kind)) != PTPLUT_OK) goto done;
    if (strcmp(kind, "rational") != 0) {
        status = fail(c, PTPLUT_ERR_CONTENT, "attribute 'kind' of /height is '%.40s', expected 'rational'", kind);
        goto done;
    }
    if ((status = read_number_attr(c, g, "/height", "degree", 1, &v)) != PTPLUT_OK) goto done;
    if (v < 1 || v > MAX_DEGREE) {
        status = fail(c, PTPLUT_ERR_CONTENT, "attribute 'degree' of /height must be 1 to %d, got %g", MAX_DEGREE, v);
        goto done;
    }
    in->degree = (int)v;
    if ((status = read_text_attr(c, g, "/height", "direction", 1, &h->direction)) != PTPLUT_OK) goto done;
    if (strcmp(h->direction, "x") != 0 && strcmp(h->direction, "y") != 0) {
        status = fail(c, PTPLUT_ERR_CONTENT, "attribute 'direction' of /height must be 'x' or 'y', got '%.40s'",
                      h->direction);
        goto done;
    }
    in->direction = h->direction[0];
    if ((status = read_number_attr(c, g, "/height", "width", 1, &v)) != PTPLUT_OK) goto done;
    in->width = (int)v;
    if ((status = read_number_attr(c, g, "/height", "height", 1, &v)) != PTPLUT_OK) goto done;
    in->height = (int)v;
    if ((status = read_list_attr(c, g, "periods_px", &h->periods, &in->n_periods)) != PTPLUT_OK
        || (status = read_list_attr(c, g, "steps", &steps, &n_steps)) != PTPLUT_OK)
        goto done;
    if (n_steps != in->n_periods) {
        status = fail(c, PTPLUT_ERR_CONTENT, "attributes 'periods_px' and 'steps' of /height differ in length"
                      " (%d and %d)", in->n_periods, n_steps);
        goto done;
    }
    if (!(h->steps = malloc((size_t)n_steps * sizeof *h->steps))) {
        status = fail(c, PTPLUT_ERR_MEMORY, "out of memory");
        goto done;
    }
    for (int i = 0; i < n_steps; i++) {
        if (steps[i] != floor(steps[i]) || fabs(steps[i]) > (double)INT_MAX) {
            status = fail(c, PTPLUT_ERR_CONTENT, "attribute 'steps' of /height must hold whole numbers, got %g",
                          steps[i]);
            goto done;
        }
        h->steps[i] = (int)steps[i];
    }
    in->periods_px = h->periods;
    in->steps = h->steps;
    if ((status = read_optional_number(c, g, "phase_origin_rad", 0, NAN, &in->phase_origin_rad)) != PTPLUT_OK
        || (status = read_optional_number(c, g, "shift_sign", 1, 0.0, &v)) != PTPLUT_OK)
        goto done;
    in->shift_sign = (int)v;
    if ((status = read_text_attr(c, g, "/height", "unwrap", 0, &h->unwrap)) != PTPLUT_OK
        || (status = read_text_attr(c, g, "/height", "chosen_by", 1, &h->chosen_by)) != PTPLUT_OK
        || (status = read_text_attr(c, g, "/height", "provenance", 0, &prov)) != PTPLUT_OK
        || (status = read_optional_number(c, g, "offset", 0, NAN, &in->offset)) != PTPLUT_OK
        || (status = read_optional_number(c, g, "amplitude", 0, NAN, &in->amplitude)) != PTPLUT_OK
        || (status = read_optional_number(c, g, "gamma", 0, NAN, &in->gamma)) != PTPLUT_OK)
        goto done;
    in->unwrap = h->unwrap;
    in->chosen_by = h->chosen_by;
    in->camera_noise_read_var = in->camera_noise_gain = NAN;
    if ((status = read_optional_number(c, g, "camera_noise_read_var", 0, NAN, &in->camera_noise_read_var))
        != PTPLUT_OK)
        goto done;
    if (!isnan(in->camera_noise_read_var)) {  /* the gain goes with it (read only then, as in Python) */
        if ((status = read_number_attr(c, g, "/height", "camera_noise_gain", 0, &in->camera_noise_gain)) != PTPLUT_OK)
            goto done;
        if (in->camera_noise_read_var < 0 || in->camera_noise_gain < 0)
            status = fail(c, PTPLUT_ERR_CONTENT, "attributes 'camera_noise_read_var' and 'camera_noise_gain' of"
                          " /height must not be negative");
    }
done:
    free(kind);
    free(prov);
    free(steps);
    return status;
}

/* The /height datasets, checked as ptpcore's _check_height: shapes against the camera; where the
 * map is valid, finite coefficients and normalisation, u_scale > 0 and |q_1| < 1. */
static int read_height_arrays(ctx_t *c, hid_t file, const ptplut *lut, struct hmap *h)
{
    const long long hh = lut->height, ww = lut->width;
    const size_t hw = (size_t)hh * (size_t)ww;
    const long long shape2[2] = {hh, ww}, shape_p[3] = {h->info.degree + 1, hh, ww}, shape_q[3] = {1, hh, ww};
    double *valid = NULL;
    int status;
    if ((status = read_dataset(c, file, "/height/u_center", 2, shape2, NUM_FLOAT | NUM_INT, &h->u_center, NULL, NULL))
            != PTPLUT_OK
        || (status = read_dataset(c, file, "/height/u_scale", 2, shape2, NUM_FLOAT | NUM_INT, &h->u_scale, NULL, NULL))
            != PTPLUT_OK
        || (status = read_dataset(c, file, "/height/p", 3, shape_p, NUM_FLOAT | NUM_INT, &h->p, NULL, NULL))
            != PTPLUT_OK
        || (status = read_dataset(c, file, "/height/q", 3, shape_q, NUM_FLOAT | NUM_INT, &h->q, NULL, NULL))
            != PTPLUT_OK
        || (status = read_dataset(c, file, "/height/valid", 2, shape2, NUM_FLOAT | NUM_INT, &valid, NULL, NULL))
            != PTPLUT_OK
        || (status = read_dataset(c, file, "/height/quality/u_min", 2, shape2, NUM_FLOAT | NUM_INT, &h->u_min, NULL,
                                  NULL)) != PTPLUT_OK
        || (status = read_dataset(c, file, "/height/quality/u_max", 2, shape2, NUM_FLOAT | NUM_INT, &h->u_max, NULL,
                                  NULL)) != PTPLUT_OK
        || (status = read_dataset(c, file, "/height/quality/sigma_z", 2, shape2, NUM_FLOAT | NUM_INT, &h->sigma_z,
                                  NULL, NULL)) != PTPLUT_OK)
        goto done;
    static const char *const others[] = {"/height/quality/rms_z", "/height/quality/loo_z",
                                         "/height/quality/n_positions"};
    for (size_t i = 0; i < sizeof others / sizeof *others; i++)
        if ((status = read_dataset(c, file, others[i], 2, shape2, NUM_FLOAT | NUM_INT, NULL, NULL, NULL)) != PTPLUT_OK)
            goto done;
    if (!(h->valid = malloc(hw)) || !(h->lo = malloc(hw * sizeof *h->lo)) || !(h->hi = malloc(hw * sizeof *h->hi))) {
        status = fail(c, PTPLUT_ERR_MEMORY, "out of memory");
        goto done;
    }
    for (size_t px = 0; px < hw; px++) {
        if (valid[px] != 0.0 && valid[px] != 1.0) {
            status = fail(c, PTPLUT_ERR_CONTENT, "/height/valid must hold only 0 and 1");
            goto done;
        }
        h->valid[px] = valid[px] == 1.0;
        /* The rule of ptpcore's HeightMap.evaluate, in double. */
        h->lo[px] = h->u_min[px] - (HEIGHT_RANGE_EPS + fabs(h->u_min[px]) * RANGE_REL);
        h->hi[px] = h->u_max[px] + (HEIGHT_RANGE_EPS + fabs(h->u_max[px]) * RANGE_REL);
        if (!h->valid[px]) continue;
        int finite = isfinite(h->q[px]) && isfinite(h->u_center[px]) && isfinite(h->u_scale[px]);
        for (int i = 0; i <= h->info.degree; i++) finite &= isfinite(h->p[(size_t)i * hw + px]) != 0;
        if (!finite) {
            status = fail(c, PTPLUT_ERR_CONTENT, "/height/p, q, u_center or u_scale holds NaN or infinite values"
                          " at valid pixels");
            goto done;
        }
        if (!(h->u_scale[px] > 0)) {
            status = fail(c, PTPLUT_ERR_CONTENT, "/height/u_scale must be positive at valid pixels");
            goto done;
        }
        if (!(fabs(h->q[px]) < 1.0)) {
            status = fail(c, PTPLUT_ERR_CONTENT, "/height/q: the denominator 1 + q_1 s vanishes within a valid"
                          " pixel's range (|q_1| >= 1)");
            goto done;
        }
    }
done:
    free(valid);
    return status;
}

static int read_height(ctx_t *c, hid_t file, ptplut *lut)
{
    hid_t g = -1;
    int status;
    struct hmap *h = calloc(1, sizeof *h);
    if (!h) return fail(c, PTPLUT_ERR_MEMORY, "out of memory");
    H5O_info_t oinfo;
    if ((g = H5Oopen(file, "/height", H5P_DEFAULT)) < 0
#if H5_VERSION_GE(1, 12, 0)
        || H5Oget_info3(g, &oinfo, H5O_INFO_BASIC) < 0
#else
        || H5Oget_info(g, &oinfo) < 0
#endif
    ) {
        status = fail(c, PTPLUT_ERR_OPEN, "/height unreadable (truncated or damaged?)");
        goto done;
    }
    if (oinfo.type != H5O_TYPE_GROUP) {
        status = fail(c, PTPLUT_ERR_CONTENT, "/height is not a group");
        goto done;
    }
    if ((status = read_height_attrs(c, g, h)) != PTPLUT_OK) goto done;
    status = read_height_arrays(c, file, lut, h);
done:
    if (g >= 0) H5Oclose(g);
    if (status != PTPLUT_OK) {
        free_hmap(h);
        return status;
    }
    lut->hmap = h;
    return PTPLUT_OK;
}

int ptplut_open(const char *path, ptplut **out, char *msg, size_t msg_size)
{
    ctx_t c = {path ? path : "(null)", msg, msg_size};
    H5E_auto2_t old_func = NULL;
    void *old_data = NULL;
    hid_t fapl = -1, file = -1;
    int status;
    ptplut *lut = NULL;

    if (msg && msg_size) msg[0] = '\0';
    if (!out) return fail(&c, PTPLUT_ERR_ARGUMENT, "no place for the LUT (NULL)");
    *out = NULL;
    if (!path) return fail(&c, PTPLUT_ERR_ARGUMENT, "no file name (NULL)");
    FILE *probe = fopen(path, "rb");
    if (!probe) return fail(&c, PTPLUT_ERR_OPEN, "cannot open (%s)", strerror(errno));
    fclose(probe);

    if (H5open() < 0) return fail(&c, PTPLUT_ERR_OPEN, "the HDF5 library did not initialise");
    /* HDF5 prints its error stack by default: silence it while we read, restore after. */
    H5Eget_auto2(H5E_DEFAULT, &old_func, &old_data);
    H5Eset_auto2(H5E_DEFAULT, NULL, NULL);

    if (!(lut = calloc(1, sizeof *lut))) {
        status = fail(&c, PTPLUT_ERR_MEMORY, "out of memory");
        goto done;
    }
    if ((fapl = H5Pcreate(H5P_FILE_ACCESS)) < 0 || H5Pset_fclose_degree(fapl, H5F_CLOSE_STRONG) < 0) {
        status = fail(&c, PTPLUT_ERR_OPEN, "the HDF5 library refused a file-access property list");
        goto done;
    }
    if ((file = H5Fopen(path, H5F_ACC_RDONLY, fapl)) < 0) {
        status = is_hdf5_signature(path)
                     ? fail(&c, PTPLUT_ERR_OPEN, "not a readable HDF5 file (truncated or damaged?)")
                     : fail(&c, PTPLUT_ERR_OPEN, "not an HDF5 file");
        goto done;
    }
    if ((status = check_format(&c, file)) != PTPLUT_OK) goto done;
    if ((status = read_model(&c, file, lut)) != PTPLUT_OK) goto done;
    if ((status = read_tables(&c, file, lut)) != PTPLUT_OK) goto done;
    if (has_link(file, "/height")) status = read_height(&c, file, lut);
done:
    if (file >= 0) H5Fclose(file);
    if (fapl >= 0) H5Pclose(fapl);
    H5Eset_auto2(H5E_DEFAULT, old_func, old_data);
    if (status != PTPLUT_OK) {
        ptplut_close(lut);
        return status;
    }
    *out = lut;
    return PTPLUT_OK;
}

void ptplut_close(ptplut *lut)
{
    if (!lut) return;
    free(lut->x);
    free(lut->y);
    free(lut->z_nodes);
    free(lut->valid);
    free(lut->lo);
    free(lut->hi);
    free(lut->sigma_x);
    free(lut->sigma_y);
    free_hmap(lut->hmap);
    free(lut);
}

int ptplut_width(const ptplut *lut) { return lut ? lut->width : 0; }
int ptplut_height(const ptplut *lut) { return lut ? lut->height : 0; }
int ptplut_kind(const ptplut *lut) { return lut ? lut->kind : -1; }
int ptplut_degree(const ptplut *lut) { return lut && lut->kind == PTPLUT_POLY ? lut->degree : 0; }

void ptplut_z_range(const ptplut *lut, double *z_min, double *z_max)
{
    if (z_min) *z_min = lut ? lut->z_min : NAN;
    if (z_max) *z_max = lut ? lut->z_max : NAN;
}

/* --------------------------------------------------------------------------- evaluation */

static int sgn(double v) { return (v > 0) - (v < 0); }

/* scipy's PchipInterpolator._edge_case: one-sided three-point slope, shape-preserving. */
static double pchip_edge(double h0, double h1, double m0, double m1)
{
    double d = ((2 * h0 + h1) * m0 - h0 * m1) / (h0 + h1);
    if (sgn(d) != sgn(m0)) return 0.0;
    if (sgn(m0) != sgn(m1) && fabs(d) > 3.0 * fabs(m0)) return 3.0 * m0;
    return d;
}

/* Slope at node k of a run of n >= 3 nodes zn[0..n-1], values v(j) = tab[j * stride]. */
static double pchip_slope(const double *zn, const double *tab, size_t stride, int n, int k)
{
#define V(j) tab[(size_t)(j) * stride]
#define H(j) (zn[(j) + 1] - zn[(j)])
#define M(j) ((V((j) + 1) - V(j)) / H(j))
    if (k == 0) return pchip_edge(H(0), H(1), M(0), M(1));
    if (k == n - 1) return pchip_edge(H(n - 2), H(n - 3), M(n - 2), M(n - 3));
    double m0 = M(k - 1), m1 = M(k);
    if (sgn(m0) != sgn(m1) || m0 == 0.0 || m1 == 0.0) return 0.0;
    double w1 = 2 * H(k) + H(k - 1), w2 = H(k) + 2 * H(k - 1);
    return 1.0 / ((w1 / m0 + w2 / m1) / (w1 + w2));
#undef M
#undef H
#undef V
}

/* One pixel's table (values tab[k * stride], k < K) at z: NaN outside every run. */
static double interp_table(const ptplut *lut, const double *tab, size_t stride, double z)
{
    const double *zn = lut->z_nodes;
    const int kk = lut->n_lead;
    double out = NAN;
    int a = 0;
    while (a < kk) {
        while (a < kk && !isfinite(tab[(size_t)a * stride])) a++;
        int b = a;
        while (b < kk && isfinite(tab[(size_t)b * stride])) b++;
        int n = b - a;
        if (n >= 2 && z >= zn[a] - RANGE_EPS && z <= zn[b - 1] + RANGE_EPS) {
            const double *rz = zn + a, *rv = tab + (size_t)a * stride;
            double zc = z < rz[0] ? rz[0] : (z > rz[n - 1] ? rz[n - 1] : z);
            int i = 0; /* searchsorted(zn, zc, side="right") - 1, clipped to [0, n - 2] */
            while (i + 1 < n && rz[i + 1] <= zc) i++;
            if (i > n - 2) i = n - 2;
            double v0 = rv[(size_t)i * stride], v1 = rv[(size_t)(i + 1) * stride];
            if (lut->kind == PTPLUT_LINEAR || n == 2) {
                double wgt = (zc - rz[i]) / (rz[i + 1] - rz[i]);
                out = (1 - wgt) * v0 + wgt * v1;
            } else {
                double dx = rz[i + 1] - rz[i];
                double d0 = pchip_slope(rz, rv, stride, n, i), d1 = pchip_slope(rz, rv, stride, n, i + 1);
                double slope = (v1 - v0) / dx;
                double t = (d0 + d1 - 2 * slope) / dx;
                double c0 = t / dx, c1 = (slope - d0) / dx - t, c2 = d0, c3 = v0;
                double s = zc - rz[i];
                out = ((c0 * s + c1) * s + c2) * s + c3;
            }
        }
        a = b;
    }
    return out;
}

static void eval_pixel(const ptplut *lut, size_t p, double z, int extrapolate, double *x, double *y,
                       unsigned *flags)
{
    const size_t hw = (size_t)lut->width * (size_t)lut->height;
    unsigned f = 0;
    if (lut->valid[p]) {
        f |= PTPLUT_VALID;
        if (z >= lut->lo[p] && z <= lut->hi[p]) f |= PTPLUT_IN_RANGE;
    }
    if (flags) *flags = f;
    if (!(f & (extrapolate ? PTPLUT_VALID : PTPLUT_IN_RANGE))) {
        *x = NAN;
        *y = NAN;
        return;
    }
    if (lut->kind == PTPLUT_POLY) {
        const double t = (z - lut->z_center) / lut->z_scale;
        const int d = lut->degree;
        double vx = lut->x[(size_t)d * hw + p], vy = lut->y[(size_t)d * hw + p];
        for (int i = d - 1; i >= 0; i--) {
            vx = vx * t + lut->x[(size_t)i * hw + p];
            vy = vy * t + lut->y[(size_t)i * hw + p];
        }
        *x = vx;
        *y = vy;
    } else {
        *x = interp_table(lut, lut->x + p, hw, z);
        *y = interp_table(lut, lut->y + p, hw, z);
    }
}

int ptplut_eval(const ptplut *lut, int row, int col, double z, int extrapolate, double *x, double *y,
                unsigned *flags)
{
    if (!lut || !x || !y) return PTPLUT_ERR_ARGUMENT;
    if (row < 0 || row >= lut->height || col < 0 || col >= lut->width) {
        *x = *y = NAN;
        if (flags) *flags = 0;
        return PTPLUT_ERR_ARGUMENT;
    }
    eval_pixel(lut, (size_t)row * (size_t)lut->width + (size_t)col, z, extrapolate, x, y, flags);
    return PTPLUT_OK;
}

int ptplut_eval_map(const ptplut *lut, const double *z, int z_is_map, int extrapolate, double *x, double *y,
                    unsigned char *flags)
{
    if (!lut || !z || !x || !y) return PTPLUT_ERR_ARGUMENT;
    const size_t hw = (size_t)lut->width * (size_t)lut->height;
    for (size_t p = 0; p < hw; p++) {
        unsigned f;
        eval_pixel(lut, p, z_is_map ? z[p] : z[0], extrapolate, x + p, y + p, &f);
        if (flags) flags[p] = (unsigned char)f;
    }
    return PTPLUT_OK;
}

int ptplut_sigma(const ptplut *lut, int row, int col, int *has, double *sigma_x, double *sigma_y)
{
    if (!lut || !has || !sigma_x || !sigma_y) return PTPLUT_ERR_ARGUMENT;
    if (row < 0 || row >= lut->height || col < 0 || col >= lut->width) return PTPLUT_ERR_ARGUMENT;
    size_t p = (size_t)row * (size_t)lut->width + (size_t)col;
    *has = lut->sigma_x != NULL;
    *sigma_x = *has ? lut->sigma_x[p] : NAN;
    *sigma_y = *has ? lut->sigma_y[p] : NAN;
    return PTPLUT_OK;
}

/* --------------------------------------------------------------------------- height-map evaluation */

int ptplut_has_height(const ptplut *lut) { return lut && lut->hmap; }

int ptplut_height_design(const ptplut *lut, ptplut_height_info *info)
{
    if (!lut || !info) return PTPLUT_ERR_ARGUMENT;
    if (!lut->hmap) return PTPLUT_ERR_NO_HEIGHT;
    *info = lut->hmap->info;
    return PTPLUT_OK;
}

/* Z and dZ/du_p of pixel px at u, exactly as HeightMap.evaluate: Horner's rule with the derivative,
 * the same operations in the same order. */
static unsigned height_pixel(const struct hmap *h, size_t hw, size_t px, double u, double *z, double *dz_du)
{
    unsigned f = 0;
    if (h->valid[px]) {
        f |= PTPLUT_HEIGHT_VALID;
        if (isfinite(u) && u >= h->lo[px] && u <= h->hi[px]) f |= PTPLUT_HEIGHT_IN_RANGE;
    }
    if (!(f & PTPLUT_HEIGHT_IN_RANGE)) {
        *z = NAN;
        if (dz_du) *dz_du = NAN;
        return f;
    }
    const double s = (u - h->u_center[px]) / h->u_scale[px];
    double num = 0.0, dnum = 0.0;
    for (int i = h->info.degree; i >= 0; i--) {
        dnum = dnum * s + num;
        num = num * s + h->p[(size_t)i * hw + px];
    }
    const double q = h->q[px], den = 1.0 + q * s;
    *z = num / den;
    if (dz_du) *dz_du = (dnum * den - num * q) / (den * den) / h->u_scale[px];
    return f;
}

int ptplut_height_eval(const ptplut *lut, int row, int col, double u_p, double *z, double *dz_du,
                       unsigned *flags)
{
    if (!lut || !z) return PTPLUT_ERR_ARGUMENT;
    *z = NAN;
    if (dz_du) *dz_du = NAN;
    if (flags) *flags = 0;
    if (!lut->hmap) return PTPLUT_ERR_NO_HEIGHT;
    if (row < 0 || row >= lut->height || col < 0 || col >= lut->width) return PTPLUT_ERR_ARGUMENT;
    const size_t hw = (size_t)lut->width * (size_t)lut->height;
    unsigned f = height_pixel(lut->hmap, hw, (size_t)row * (size_t)lut->width + (size_t)col, u_p, z, dz_du);
    if (flags) *flags = f;
    return PTPLUT_OK;
}

int ptplut_height_eval_map(const ptplut *lut, const double *u_p, double *z, double *dz_du, unsigned char *flags)
{
    if (!lut || !u_p || !z) return PTPLUT_ERR_ARGUMENT;
    if (!lut->hmap) return PTPLUT_ERR_NO_HEIGHT;
    const size_t hw = (size_t)lut->width * (size_t)lut->height;
    for (size_t px = 0; px < hw; px++) {
        unsigned f = height_pixel(lut->hmap, hw, px, u_p[px], z + px, dz_du ? dz_du + px : NULL);
        if (flags) flags[px] = (unsigned char)f;
    }
    return PTPLUT_OK;
}

int ptplut_height_quality(const ptplut *lut, int row, int col, double *u_min, double *u_max, double *sigma_z)
{
    if (!lut || !u_min || !u_max || !sigma_z) return PTPLUT_ERR_ARGUMENT;
    *u_min = *u_max = *sigma_z = NAN;
    if (!lut->hmap) return PTPLUT_ERR_NO_HEIGHT;
    if (row < 0 || row >= lut->height || col < 0 || col >= lut->width) return PTPLUT_ERR_ARGUMENT;
    const struct hmap *h = lut->hmap;
    size_t px = (size_t)row * (size_t)lut->width + (size_t)col;
    if (h->valid[px]) {
        *u_min = h->u_min[px];
        *u_max = h->u_max[px];
        *sigma_z = h->sigma_z[px];
    }
    return PTPLUT_OK;
}
