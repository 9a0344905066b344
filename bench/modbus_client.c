/*
 * The libmodbus client the Modbus benchmark measures cellrt against, on the same
 * server in the same run.
 *
 *   modbus_client PORT seq N            N sequential reads of 10 holding registers;
 *                                       prints "rps R p50_us M p99_us P"
 *   modbus_client PORT poll N < PLAN    N polls, each the requests of PLAN (one a line:
 *                                       "FC ADDRESS COUNT", FC 1..4), one after the
 *                                       other; prints "requests Q p50_us M p99_us P"
 */
#include <modbus/modbus.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

static double now_us(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return t.tv_sec * 1e6 + t.tv_nsec / 1e3;
}

static int cmp(const void *a, const void *b) {
    double x = *(const double *)a, y = *(const double *)b;
    return x < y ? -1 : x > y;
}

/* Nearest-rank percentile, as cell_bench computes it. */
static double pct(double *v, int n, int p) {
    int rank = (int)((p / 100.0) * n + 0.999999);
    if (rank < 1) rank = 1;
    if (rank > n) rank = n;
    return v[rank - 1];
}

int main(int argc, char **argv) {
    if (argc < 4) { fprintf(stderr, "usage: modbus_client PORT seq|poll N\n"); return 2; }
    modbus_t *ctx = modbus_new_tcp("127.0.0.1", atoi(argv[1]));
    int n = atoi(argv[3]);
    if (!ctx || modbus_connect(ctx) < 0 || n < 1) { fprintf(stderr, "cannot connect\n"); return 1; }
    modbus_set_slave(ctx, 1);
    double *lat = calloc((size_t)n, sizeof *lat);
    static uint16_t regs[MODBUS_MAX_READ_REGISTERS];
    static uint8_t bits[MODBUS_MAX_READ_BITS];

    if (!strcmp(argv[2], "seq")) {
        double t0 = now_us();
        for (int i = 0; i < n; i++) {
            double s = now_us();
            if (modbus_read_registers(ctx, 0, 10, regs) != 10) { fprintf(stderr, "read failed\n"); return 1; }
            lat[i] = now_us() - s;
        }
        double total = now_us() - t0;
        qsort(lat, (size_t)n, sizeof *lat, cmp);
        printf("rps %.1f p50_us %.2f p99_us %.2f\n", n / (total / 1e6), pct(lat, n, 50), pct(lat, n, 99));
    } else {
        int fc[4096], addr[4096], count[4096], q = 0;
        while (q < 4096 && scanf("%d %d %d", &fc[q], &addr[q], &count[q]) == 3) q++;
        for (int i = 0; i < n; i++) {
            double s = now_us();
            for (int r = 0; r < q; r++) {
                int rc = fc[r] == 1 ? modbus_read_bits(ctx, addr[r], count[r], bits)
                       : fc[r] == 2 ? modbus_read_input_bits(ctx, addr[r], count[r], bits)
                       : fc[r] == 3 ? modbus_read_registers(ctx, addr[r], count[r], regs)
                       : modbus_read_input_registers(ctx, addr[r], count[r], regs);
                if (rc != count[r]) { fprintf(stderr, "read failed\n"); return 1; }
            }
            lat[i] = now_us() - s;
        }
        qsort(lat, (size_t)n, sizeof *lat, cmp);
        printf("requests %d p50_us %.2f p99_us %.2f\n", q, pct(lat, n, 50), pct(lat, n, 99));
    }
    modbus_close(ctx);
    modbus_free(ctx);
    return 0;
}
