/*
 * volpack_driver.c: VolPack (Lacroute's shear-warp, Debian libvolpack1-dev) as a benchmark peer.
 *
 * Loads a volume of unsigned 16-bit densities (x fastest), classifies it with an opacity table
 * and colours it with a lookup "shader" indexed by the same density (no lighting), sets the
 * complete object -> clip matrix given by the caller as VolPack's VP_MODEL matrix (VIEW and
 * PROJECT are identity), renders FRAMES frames with vpRenderClassifiedVolume and writes the last
 * image as raw RGBA bytes (VolPack's own layout: W*H pixels, scanline 0 first). Prints one line
 * of JSON with the times (seconds, CLOCK_MONOTONIC) and this process's peak RSS (VmHWM).
 *
 * Usage:
 *   volpack_driver VOLUME XLEN YLEN ZLEN FIELD_MAX TABLE MATRIX WIDTH HEIGHT FRAMES
 *                  MIN_VOXEL_OPACITY MAX_RAY_OPACITY OUT_RGBA
 *     VOLUME  XLEN*YLEN*ZLEN little-endian uint16 densities, x fastest, values <= FIELD_MAX
 *     TABLE   float32: FIELD_MAX+1 opacities, then (FIELD_MAX+1)*3 straight RGB colours
 *     MATRIX  float64: 16 values, row-major 4x4 VP_MODEL matrix (column vectors)
 *
 * Build: gcc -O2 -o volpack_driver volpack_driver.c -lvolpack -lm
 * VolPack itself is not part of this repository (Stanford licence; installed from Debian).
 */

#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <sys/resource.h>
#include <volpack.h>

static double now(void)
{
    struct timespec ts;
    clock_gettime(CLOCK_MONOTONIC, &ts);
    return ts.tv_sec + 1e-9 * ts.tv_nsec;
}

static void *read_file(const char *path, size_t expected)
{
    FILE *f = fopen(path, "rb");
    void *buf;
    if (f == NULL) {
        perror(path);
        exit(2);
    }
    buf = malloc(expected ? expected : 1);
    if (buf == NULL) {
        fprintf(stderr, "out of memory\n");
        exit(2);
    }
    if (fread(buf, 1, expected, f) != expected) {
        fprintf(stderr, "%s: expected %zu bytes\n", path, expected);
        exit(2);
    }
    fclose(f);
    return buf;
}

/* Peak resident set of this program (kB): VmHWM of /proc/self/status. getrusage's ru_maxrss
   is not used: on Linux it keeps the parent's peak across fork and execve. */
static long peak_rss_kb(void)
{
    char line[256];
    long kb = -1;
    FILE *f = fopen("/proc/self/status", "r");
    if (f != NULL) {
        while (fgets(line, sizeof line, f) != NULL)
            if (strncmp(line, "VmHWM:", 6) == 0) {
                kb = atol(line + 6);
                break;
            }
        fclose(f);
    }
    if (kb < 0) {
        struct rusage ru;
        getrusage(RUSAGE_SELF, &ru);
        kb = ru.ru_maxrss;
    }
    return kb;
}

static void check(vpContext *vpc, vpResult r, const char *what)
{
    if (r != VP_OK) {
        fprintf(stderr, "VolPack error in %s: %s\n", what, vpGetErrorString(vpGetError(vpc)));
        exit(3);
    }
}

int main(int argc, char **argv)
{
    vpContext *vpc;
    int xlen, ylen, zlen, field_max, width, height, frames, n, axis = 0, iw = 0, ih = 0;
    double min_voxel_opacity, max_ray_opacity, t0, classify_s, best = 1e30;
    size_t nvox;
    unsigned short *voxels;
    float *table, *opacity, *color;
    double *mvals;
    vpMatrix4 model;
    unsigned char *image;
    FILE *out;

    if (argc != 14) {
        fprintf(stderr, "usage: %s VOLUME XLEN YLEN ZLEN FIELD_MAX TABLE MATRIX WIDTH HEIGHT "
                "FRAMES MIN_VOXEL_OPACITY MAX_RAY_OPACITY OUT_RGBA\n", argv[0]);
        return 1;
    }
    xlen = atoi(argv[2]);
    ylen = atoi(argv[3]);
    zlen = atoi(argv[4]);
    field_max = atoi(argv[5]);
    width = atoi(argv[8]);
    height = atoi(argv[9]);
    frames = atoi(argv[10]);
    min_voxel_opacity = atof(argv[11]);
    max_ray_opacity = atof(argv[12]);
    if (xlen < 1 || ylen < 1 || zlen < 1 || field_max < 1 || field_max > 65535 || width < 1 ||
        height < 1 || frames < 1) {
        fprintf(stderr, "bad arguments\n");
        return 1;
    }
    nvox = (size_t)xlen * ylen * zlen;
    voxels = read_file(argv[1], nvox * sizeof(unsigned short));
    table = read_file(argv[6], (size_t)(field_max + 1) * 4 * sizeof(float));
    opacity = table;
    color = table + (field_max + 1);
    mvals = read_file(argv[7], 16 * sizeof(double));
    for (n = 0; n < 16; n++)
        model[n / 4][n % 4] = mvals[n];

    vpc = vpCreateContext();
    /* one field per voxel: the density; it is the classification and the shading index */
    check(vpc, vpSetVolumeSize(vpc, xlen, ylen, zlen), "vpSetVolumeSize");
    check(vpc, vpSetVoxelSize(vpc, sizeof(unsigned short), 1, 1, 1), "vpSetVoxelSize");
    check(vpc, vpSetVoxelField(vpc, 0, sizeof(unsigned short), 0, field_max), "vpSetVoxelField");
    check(vpc, vpSetRawVoxels(vpc, voxels, (int)(nvox * sizeof(unsigned short)),
                              sizeof(unsigned short), xlen * sizeof(unsigned short),
                              xlen * ylen * sizeof(unsigned short)), "vpSetRawVoxels");
    check(vpc, vpSetClassifierTable(vpc, 0, 0, opacity, (field_max + 1) * sizeof(float)),
          "vpSetClassifierTable");
    check(vpc, vpSetLookupShader(vpc, 3, 1, 0, color, (field_max + 1) * 3 * sizeof(float), 0,
                                 NULL, 0), "vpSetLookupShader");
    check(vpc, vpSetd(vpc, VP_MIN_VOXEL_OPACITY, min_voxel_opacity), "VP_MIN_VOXEL_OPACITY");
    check(vpc, vpSetd(vpc, VP_MAX_RAY_OPACITY, max_ray_opacity), "VP_MAX_RAY_OPACITY");

    /* classification: builds VolPack's run-length encoded volume (one copy per axis) */
    t0 = now();
    check(vpc, vpClassifyVolume(vpc), "vpClassifyVolume");
    classify_s = now() - t0;

    /* the whole object -> clip transform is the model matrix; view and projection identity */
    check(vpc, vpCurrentMatrix(vpc, VP_VIEW), "vpCurrentMatrix");
    check(vpc, vpIdentityMatrix(vpc), "vpIdentityMatrix");
    check(vpc, vpCurrentMatrix(vpc, VP_PROJECT), "vpCurrentMatrix");
    check(vpc, vpIdentityMatrix(vpc), "vpIdentityMatrix");
    check(vpc, vpCurrentMatrix(vpc, VP_MODEL), "vpCurrentMatrix");
    check(vpc, vpSetMatrix(vpc, model), "vpSetMatrix");

    image = calloc((size_t)width * height, 4);
    if (image == NULL) {
        fprintf(stderr, "out of memory\n");
        return 2;
    }
    check(vpc, vpSetImage(vpc, image, width, height, width * 4, VP_RGBA), "vpSetImage");

    printf("{\"classify_s\": %.9f, \"frames_s\": [", classify_s);
    for (n = 0; n < frames; n++) {
        double dt;
        t0 = now();
        check(vpc, vpRenderClassifiedVolume(vpc), "vpRenderClassifiedVolume");
        dt = now() - t0;
        if (dt < best)
            best = dt;
        printf("%s%.9f", n ? ", " : "", dt);
    }
    vpGeti(vpc, VP_VIEW_AXIS, &axis);
    vpGeti(vpc, VP_INTERMEDIATE_WIDTH, &iw);
    vpGeti(vpc, VP_INTERMEDIATE_HEIGHT, &ih);
    printf("], \"best_s\": %.9f, \"view_axis\": \"%c\", \"intermediate\": [%d, %d], "
           "\"max_rss_kb\": %ld}\n", best,
           axis == VP_X_AXIS ? 'x' : (axis == VP_Y_AXIS ? 'y' : 'z'), iw, ih, peak_rss_kb());

    out = fopen(argv[13], "wb");
    if (out == NULL || fwrite(image, 4, (size_t)width * height, out) != (size_t)width * height) {
        perror(argv[13]);
        return 2;
    }
    fclose(out);
    vpDestroyContext(vpc);
    return 0;
}
