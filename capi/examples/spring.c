/*
 * A spring at the application's own loop rate: the end-effector is pulled
 * towards a point 80 mm off where it starts, F = k (target - p), at most
 * F_MAX newtons. Prints the loop rate it achieved and the age of the
 * states it read, and one line per 20 loops of what the device rendered.
 *
 *   spring [PORT | --virtual] [--seconds S] [--heartbeat-ms MS]
 *
 * With --virtual (the default) the library starts a virtual device in this
 * process; --heartbeat-ms sets its heartbeat timeout (the firmware's is
 * 20 ms). Build (after `cargo build --release -p spidar-capi`):
 *
 *   cc -O2 -Icapi/include capi/examples/spring.c -Ltarget/release -lspidar_capi \
 *      -Wl,-rpath,$PWD/target/release -o spring
 *
 * Output lines are "key values..." (tests read them).
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "spidar.h"

#define K_N_PER_MM 0.02
#define F_MAX_N 3.0

static int fail(const char *what, int32_t rc) {
    fprintf(stderr, "spring: %s: %s: %s\n", what, spidar_error_name(rc), spidar_last_error());
    return 1;
}

static double now_s(void) {
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec + (double)t.tv_nsec * 1e-9;
}

static int cmp_u64(const void *a, const void *b) {
    uint64_t x = *(const uint64_t *)a, y = *(const uint64_t *)b;
    return (x > y) - (x < y);
}

/* Waits for a state that satisfies armed == want_armed (device time moves on). */
static int wait_armed(spidar_device *dev, int want, spidar_state *s) {
    for (int i = 0; i < 5000; i++) {
        int32_t rc = spidar_wait_state(dev, 2000, s);
        if (rc != SPIDAR_OK) return fail("wait_state", rc);
        if ((s->armed != 0) == want && (want || !s->motors_on)) return 0;
    }
    fprintf(stderr, "spring: the device never reported armed=%d\n", want);
    return 1;
}

int main(int argc, char **argv) {
    const char *port = NULL;
    double seconds = 2.0;
    spidar_virtual_options vopt;
    memset(&vopt, 0, sizeof vopt);
    for (int i = 1; i < argc; i++) {
        if (!strcmp(argv[i], "--virtual")) port = NULL;
        else if (!strcmp(argv[i], "--seconds") && i + 1 < argc) seconds = atof(argv[++i]);
        else if (!strcmp(argv[i], "--heartbeat-ms") && i + 1 < argc)
            vopt.heartbeat_timeout_ms = (uint32_t)atoi(argv[++i]);
        else port = argv[i];
    }
    if (spidar_api_version() != SPIDAR_API_VERSION) {
        fprintf(stderr, "spring: libspidar_capi is API %u, this program was built for %u\n",
                spidar_api_version(), SPIDAR_API_VERSION);
        return 1;
    }
    spidar_device *dev = NULL;
    int32_t rc = port ? spidar_open(port, &dev) : spidar_open_virtual(&vopt, &dev);
    if (rc != SPIDAR_OK) return fail("open", rc);
    spidar_info info;
    if ((rc = spidar_get_info(dev, &info)) != SPIDAR_OK) return fail("get_info", rc);
    printf("device %s firmware %u.%u.%u loop %u us\n", info.device_id, info.firmware_version[0],
           info.firmware_version[1], info.firmware_version[2], info.loop_period_us);

    spidar_state s;
    if ((rc = spidar_wait_state(dev, 5000, &s)) != SPIDAR_OK) return fail("wait_state", rc);
    double target[3] = {s.position_mm[0] + 80.0, s.position_mm[1], s.position_mm[2]};
    printf("target %.3f %.3f %.3f\n", target[0], target[1], target[2]);

    if ((rc = spidar_arm(dev)) != SPIDAR_OK) return fail("arm", rc);
    if ((rc = spidar_set_force(dev, 0, 0, 0)) != SPIDAR_OK) return fail("set_force", rc);
    if (wait_armed(dev, 1, &s)) return 1;
    printf("armed %d\n", s.armed);

    /* The loop: read the newest state (never waits), compute the spring,
       send it (this is the heartbeat). Runs for `seconds` of device time. */
    uint64_t t_end = s.time_us + (uint64_t)(seconds * 1e6);
    size_t cap = 1 << 20, n = 0;
    uint64_t *ages = malloc(cap * sizeof *ages);
    double t0 = now_s();
    for (;;) {
        if ((rc = spidar_get_state(dev, &s)) != SPIDAR_OK) return fail("get_state", rc);
        if (s.time_us >= t_end) break;
        double f[3], norm = 0;
        for (int k = 0; k < 3; k++) {
            f[k] = K_N_PER_MM * (target[k] - s.position_mm[k]);
            norm += f[k] * f[k];
        }
        norm = sqrt(norm);
        if (norm > F_MAX_N)
            for (int k = 0; k < 3; k++) f[k] *= F_MAX_N / norm;
        if ((rc = spidar_set_force(dev, f[0], f[1], f[2])) != SPIDAR_OK) return fail("set_force", rc);
        if (n < cap) ages[n] = s.age_us;
        n++;
        if (n % 20 == 0)
            printf("state %llu %d %.3f %.3f %.3f %.4f %.4f %.4f\n", (unsigned long long)s.time_us,
                   s.armed, s.position_mm[0], s.position_mm[1], s.position_mm[2],
                   s.rendered_force_n[0], s.rendered_force_n[1], s.rendered_force_n[2]);
    }
    double wall = now_s() - t0;
    size_t m = n < cap ? n : cap;
    qsort(ages, m, sizeof *ages, cmp_u64);
    printf("loop_hz %.1f\n", (double)n / wall);
    printf("state_age_us median %llu p99 %llu\n", (unsigned long long)(m ? ages[m / 2] : 0),
           (unsigned long long)(m ? ages[(m * 99) / 100] : 0));
    free(ages);

    if ((rc = spidar_set_force(dev, 0, 0, 0)) != SPIDAR_OK) return fail("set_force", rc);
    if ((rc = spidar_disarm(dev)) != SPIDAR_OK) return fail("disarm", rc);
    if (wait_armed(dev, 0, &s)) return 1;
    printf("disarmed %d\n", !s.armed && !s.motors_on);
    spidar_link_stats ls;
    if ((rc = spidar_get_link_stats(dev, &ls)) != SPIDAR_OK) return fail("get_link_stats", rc);
    printf("faults \"%s\"\n", s.fault_names);
    printf("link states %llu lost %llu device_dropped %llu rejected %llu\n",
           (unsigned long long)ls.states, (unsigned long long)ls.lost,
           (unsigned long long)ls.device_dropped, (unsigned long long)ls.rejected);
    if ((rc = spidar_close(dev)) != SPIDAR_OK) return fail("close", rc);
    return 0;
}
