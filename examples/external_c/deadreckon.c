/* deadreckon: planar dead reckoning of cumulative odometry, a program that does not know slamreplay.
 *
 * Reads CSV from standard input, a header line then `t_ns,x_m,y_m,yaw_rad` per odometry pose (what
 * `slamreplay export --what odometry_csv` writes), and writes a TUM trajectory (`t_s x y z qx qy qz qw`)
 * starting at its own origin to the file named by its argument. Each odometry increment, taken in the
 * previous odometry pose's frame, is scaled by 1 + SCALE_BIAS (0 unless built with -DSCALE_BIAS=...: a
 * deliberate regression for the comparison example) and composed onto the estimate.
 *
 * Exit status: 0 success, 1 bad input (a line that is not four numbers), 2 bad usage or output file.
 * `deadreckon --version` prints its version and the bias it was built with.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#ifndef SCALE_BIAS
#define SCALE_BIAS 0.0
#endif
#define VERSION "1.0"
#define PI 3.14159265358979323846

static double wrap(double a) {
    a = fmod(a + PI, 2.0 * PI);
    if (a < 0) a += 2.0 * PI;
    return a - PI;
}

int main(int argc, char **argv) {
    if (argc == 2 && strcmp(argv[1], "--version") == 0) {
        printf("deadreckon %s (scale bias %g)\n", VERSION, (double)SCALE_BIAS);
        return 0;
    }
    if (argc != 2) {
        fprintf(stderr, "usage: deadreckon OUT.tum < odometry.csv\n");
        return 2;
    }
    FILE *out = fopen(argv[1], "w");
    if (!out) {
        fprintf(stderr, "deadreckon: cannot write %s\n", argv[1]);
        return 2;
    }
    char line[512];
    long lineno = 0, poses = 0;
    double px = 0, py = 0, pth = 0;      /* previous odometry pose */
    double ex = 0, ey = 0, eth = 0;      /* estimate, in the frame of the first odometry pose */
    fprintf(out, "# timestamp x y z qx qy qz qw\n");
    while (fgets(line, sizeof line, stdin)) {
        lineno++;
        if (lineno == 1 && strncmp(line, "t_ns", 4) == 0) continue;   /* the header */
        long long t;
        double x, y, th;
        if (sscanf(line, "%lld,%lf,%lf,%lf", &t, &x, &y, &th) != 4) {
            fprintf(stderr, "deadreckon: line %ld is not t_ns,x_m,y_m,yaw_rad\n", lineno);
            fclose(out);
            return 1;
        }
        if (poses > 0) {
            double c = cos(pth), s = sin(pth);
            double dx = (c * (x - px) + s * (y - py)) * (1.0 + SCALE_BIAS);   /* increment in the previous frame */
            double dy = (-s * (x - px) + c * (y - py)) * (1.0 + SCALE_BIAS);
            ex += cos(eth) * dx - sin(eth) * dy;
            ey += sin(eth) * dx + cos(eth) * dy;
            eth = wrap(eth + wrap(th - pth));
        }
        px = x; py = y; pth = th;
        poses++;
        fprintf(out, "%lld.%09lld %.12g %.12g 0 0 0 %.12g %.12g\n", t / 1000000000LL, t % 1000000000LL, ex, ey,
                sin(eth / 2), cos(eth / 2));
    }
    fclose(out);
    fprintf(stderr, "deadreckon: %ld poses\n", poses);
    return 0;
}
