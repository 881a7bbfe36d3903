/*
 * ptplut_tool: a tiny driver of the ptplut library, used by `make test` and
 * handy for a first look at a LUT.
 *
 *   ptplut_tool info  FILE.lut.h5
 *   ptplut_tool pixel FILE.lut.h5 ROW COL Z [--extrapolate]
 *   ptplut_tool map   FILE.lut.h5 Z|ZMAP.f64 OUT.bin [--extrapolate]
 *   ptplut_tool height-info  FILE.lut.h5
 *   ptplut_tool height-pixel FILE.lut.h5 ROW COL U_P
 *   ptplut_tool height-map   FILE.lut.h5 UMAP.f64 OUT.bin
 *
 * `map` reads a height map of height * width little-endian doubles (raw, row
 * major) or takes one height, and writes X (H*W doubles), Y (H*W doubles) and
 * the flags (H*W bytes) to OUT.bin. `height-map` reads u_p (H*W doubles) and writes Z,
 * dZ/du_p (H*W doubles each), the flags (H*W bytes) and sigma_z (H*W doubles) of the
 * height map; `height-info` prints its design, one "key value" line each. Exit status: 0 done, 1 the LUT was refused
 * (one line on stderr: status name and message), 2 bad usage or I/O.
 */
#include "ptplut.h"

#include <stdio.h>
#include <stdlib.h>
#include <string.h>

static int usage(void)
{
    fprintf(stderr, "usage: ptplut_tool info FILE | pixel FILE ROW COL Z [--extrapolate] |"
                    " map FILE Z|ZMAP.f64 OUT.bin [--extrapolate] | height-info FILE |"
                    " height-pixel FILE ROW COL U_P | height-map FILE UMAP.f64 OUT.bin\n");
    return 2;
}

static int open_lut(const char *path, ptplut **lut)
{
    char msg[1024];
    int status = ptplut_open(path, lut, msg, sizeof msg);
    if (status != PTPLUT_OK) {
        fprintf(stderr, "ptplut: %s: %s\n", ptplut_status_name(status), msg);
        return 1;
    }
    return 0;
}

static int cmd_map(ptplut *lut, const char *zarg, const char *out, int extrapolate)
{
    size_t hw = (size_t)ptplut_width(lut) * (size_t)ptplut_height(lut);
    double *z = NULL, *x = malloc(hw * sizeof *x), *y = malloc(hw * sizeof *y);
    unsigned char *flags = malloc(hw);
    int is_map = 0, rc = 2;
    char *end;
    double zc = strtod(zarg, &end);
    if (!x || !y || !flags) goto done;
    if (*zarg && *end == '\0') {
        z = &zc;
    } else {
        FILE *f = fopen(zarg, "rb");
        if (!f) {
            fprintf(stderr, "ptplut_tool: %s: cannot open\n", zarg);
            goto done;
        }
        z = malloc(hw * sizeof *z);
        size_t got = z ? fread(z, sizeof *z, hw, f) : 0;
        fclose(f);
        if (got != hw) {
            fprintf(stderr, "ptplut_tool: %s: expected %zu doubles\n", zarg, hw);
            goto done;
        }
        is_map = 1;
    }
    if (ptplut_eval_map(lut, z, is_map, extrapolate, x, y, flags) != PTPLUT_OK) goto done;
    FILE *f = fopen(out, "wb");
    if (!f) goto done;
    int ok = fwrite(x, sizeof *x, hw, f) == hw && fwrite(y, sizeof *y, hw, f) == hw && fwrite(flags, 1, hw, f) == hw;
    if (fclose(f) == 0 && ok) rc = 0;
done:
    if (is_map) free(z);
    free(x);
    free(y);
    free(flags);
    return rc;
}

static int cmd_height_info(const ptplut *lut)
{
    ptplut_height_info in;
    int rc = ptplut_height_design(lut, &in);
    if (rc != PTPLUT_OK) {
        fprintf(stderr, "ptplut: %s: the LUT has no height map\n", ptplut_status_name(rc));
        return 1;
    }
    printf("degree %d\ndirection %c\nchosen_by %s\nwidth %d\nheight %d\nperiods_px", in.degree, in.direction,
           in.chosen_by, in.width, in.height);
    for (int i = 0; i < in.n_periods; i++) printf(" %.17g", in.periods_px[i]);
    printf("\nsteps");
    for (int i = 0; i < in.n_periods; i++) printf(" %d", in.steps[i]);
    printf("\nphase_origin_rad %.17g\nshift_sign %d\nunwrap %s\noffset %.17g\namplitude %.17g\ngamma %.17g\n"
           "camera_noise_read_var %.17g\ncamera_noise_gain %.17g\n", in.phase_origin_rad, in.shift_sign,
           in.unwrap ? in.unwrap : "-", in.offset, in.amplitude, in.gamma, in.camera_noise_read_var,
           in.camera_noise_gain);
    return 0;
}

static int cmd_height_map(const ptplut *lut, const char *uarg, const char *out)
{
    const int w = ptplut_width(lut), h = ptplut_height(lut);
    size_t hw = (size_t)w * (size_t)h;
    double *u = malloc(hw * sizeof *u), *z = malloc(hw * sizeof *z), *dz = malloc(hw * sizeof *dz);
    double *sig = malloc(hw * sizeof *sig);
    unsigned char *flags = malloc(hw);
    int rc = 2;
    if (!u || !z || !dz || !sig || !flags) goto done;
    FILE *f = fopen(uarg, "rb");
    if (!f) {
        fprintf(stderr, "ptplut_tool: %s: cannot open\n", uarg);
        goto done;
    }
    size_t got = fread(u, sizeof *u, hw, f);
    fclose(f);
    if (got != hw) {
        fprintf(stderr, "ptplut_tool: %s: expected %zu doubles\n", uarg, hw);
        goto done;
    }
    int status = ptplut_height_eval_map(lut, u, z, dz, flags);
    if (status != PTPLUT_OK) {
        fprintf(stderr, "ptplut: %s: no height map evaluated\n", ptplut_status_name(status));
        rc = 1;
        goto done;
    }
    for (int r = 0; r < h; r++)
        for (int c = 0; c < w; c++) {
            double lo, hi;
            ptplut_height_quality(lut, r, c, &lo, &hi, &sig[(size_t)r * (size_t)w + (size_t)c]);
        }
    f = fopen(out, "wb");
    if (!f) goto done;
    int ok = fwrite(z, sizeof *z, hw, f) == hw && fwrite(dz, sizeof *dz, hw, f) == hw && fwrite(flags, 1, hw, f) == hw
             && fwrite(sig, sizeof *sig, hw, f) == hw;
    if (fclose(f) == 0 && ok) rc = 0;
done:
    free(u);
    free(z);
    free(dz);
    free(sig);
    free(flags);
    return rc;
}

int main(int argc, char **argv)
{
    ptplut *lut = NULL;
    int rc;
    if (argc < 3) return usage();
    int extrapolate = strcmp(argv[argc - 1], "--extrapolate") == 0;
    int nargs = argc - extrapolate;
    if ((rc = open_lut(argv[2], &lut)) != 0) return rc;
    if (strcmp(argv[1], "info") == 0 && nargs == 3) {
        static const char *const kinds[] = {"poly", "linear", "pchip"};
        double lo, hi;
        ptplut_z_range(lut, &lo, &hi);
        printf("%s %d %dx%d z %.17g %.17g\n", kinds[ptplut_kind(lut)], ptplut_degree(lut), ptplut_width(lut),
               ptplut_height(lut), lo, hi);
    } else if (strcmp(argv[1], "pixel") == 0 && nargs == 6) {
        double x, y;
        unsigned flags;
        rc = ptplut_eval(lut, atoi(argv[3]), atoi(argv[4]), strtod(argv[5], NULL), extrapolate, &x, &y, &flags);
        if (rc == PTPLUT_OK)
            printf("%.17g %.17g %u\n", x, y, flags);
        else
            fprintf(stderr, "ptplut: %s: pixel outside the camera\n", ptplut_status_name(rc));
        rc = rc == PTPLUT_OK ? 0 : 2;
    } else if (strcmp(argv[1], "map") == 0 && nargs == 5) {
        rc = cmd_map(lut, argv[3], argv[4], extrapolate);
    } else if (strcmp(argv[1], "height-info") == 0 && argc == 3) {
        rc = cmd_height_info(lut);
    } else if (strcmp(argv[1], "height-pixel") == 0 && argc == 6) {
        double z, dz;
        unsigned flags;
        rc = ptplut_height_eval(lut, atoi(argv[3]), atoi(argv[4]), strtod(argv[5], NULL), &z, &dz, &flags);
        if (rc == PTPLUT_OK)
            printf("%.17g %.17g %u\n", z, dz, flags);
        else
            fprintf(stderr, "ptplut: %s: %s\n", ptplut_status_name(rc),
                    rc == PTPLUT_ERR_NO_HEIGHT ? "the LUT has no height map" : "pixel outside the camera");
        rc = rc == PTPLUT_OK ? 0 : rc == PTPLUT_ERR_NO_HEIGHT ? 1 : 2;
    } else if (strcmp(argv[1], "height-map") == 0 && argc == 5) {
        rc = cmd_height_map(lut, argv[3], argv[4]);
    } else {
        rc = usage();
    }
    ptplut_close(lut);
    return rc;
}
