/*
 * A horizontal virtual wall rendered through hgcd from C: the counterpart of
 * examples/virtual_wall.rs. Below the plane z = height the handle is pushed up with
 * F_z = k (height - z); above it, no force. Gravity compensation comes from the daemon.
 *
 * Build and run (from the repository; see docs/app-protocol.md, "From C"):
 *
 *   cargo build --release -p hgcd-c
 *   cc -std=c99 -Wall -Iclients/c/include clients/c/examples/virtual_wall.c \
 *      -Ltarget/release -lhgcd_c -Wl,-rpath,"$PWD/target/release" -o virtual_wall
 *   ./virtual_wall --socket /tmp/hgcd.sock --stiffness 1.0 --height 0 --duration 5
 *
 * It prints the mean penetration over the last second: with exact compensation and a probe
 * mass m_p it tends to m_p g / k (0.29 mm for 30 g on 1 N/mm, paper section 5).
 */
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "hgcd.h"

/* How long to wait for a state sample before deciding the daemon has stalled, ms. */
#define STATE_WAIT_MS 2000

static const char *usage =
    "usage: virtual_wall [--socket PATH | --device SPEC] [--stiffness N_PER_MM] [--height MM]\n"
    "                    [--duration S]\n";

/* Parse the value of option `name` as a number; exit with one line saying what was wrong. */
static double number(const char *name, const char *text) {
    char *end = NULL;
    double value = text ? strtod(text, &end) : 0.0;
    if (!text || end == text || *end != '\0') {
        fprintf(stderr, "virtual_wall: %s needs a number, got '%s'\n%s", name,
                text ? text : "", usage);
        exit(2);
    }
    return value;
}

/* Print what failed with the library's message, close the connection, return the exit code. */
static int fail(hgcd_client *client, const char *doing) {
    fprintf(stderr, "virtual_wall: %s: %s\n", doing, hgcd_last_error());
    hgcd_close(client);
    return 1;
}

/* The wall's force along z (N) at height z (m) for a plane at `height` (m) of stiffness k
 * (N/m), within the protocol's per-axis limit. */
static double wall_force(double z, double height, double k) {
    double f = k * (height - z);
    if (f < 0.0) {
        return 0.0;
    }
    return f < HGCD_DEFAULT_MAX_FORCE_N ? f : HGCD_DEFAULT_MAX_FORCE_N;
}

int main(int argc, char **argv) {
    const char *socket_path = NULL, *device = NULL; /* neither: the only daemon running */
    double stiffness = 1.0, height_mm = 0.0, duration = 5.0;
    for (int i = 1; i < argc; i++) {
        const char *value = i + 1 < argc ? argv[i + 1] : NULL;
        if (strcmp(argv[i], "--socket") == 0 && value) {
            socket_path = value;
        } else if (strcmp(argv[i], "--device") == 0 && value) {
            device = value;
        } else if (strcmp(argv[i], "--stiffness") == 0) {
            stiffness = number("--stiffness", value);
        } else if (strcmp(argv[i], "--height") == 0) {
            height_mm = number("--height", value);
        } else if (strcmp(argv[i], "--duration") == 0) {
            duration = number("--duration", value);
        } else {
            fprintf(stderr, "virtual_wall: unknown option '%s'\n%s", argv[i], usage);
            return 2;
        }
        i++;
    }
    const double k = stiffness * 1e3, height = height_mm * 1e-3;

    hgcd_client *client = NULL;
    int connected = socket_path || !device ? hgcd_connect(socket_path, &client)
                                           : hgcd_connect_device(device, &client);
    if (connected != HGCD_OK) {
        return fail(client, "connecting to hgcd");
    }
    hgcd_welcome welcome;
    if (hgcd_take_ownership(client, "virtual_wall.c", &welcome) != HGCD_OK) {
        return fail(client, "taking the force");
    }
    if (hgcd_subscribe(client, welcome.rate_hz) != HGCD_OK) {
        return fail(client, "subscribing to the state");
    }

    hgcd_state s;
    double first_time = 0.0, sum = 0.0;
    long count = 0;
    int started = 0;
    for (;;) {
        int rc = hgcd_newest_state(client, STATE_WAIT_MS, &s);
        if (rc == HGCD_NO_SAMPLE) {
            fprintf(stderr, "virtual_wall: no state from the daemon for %d ms\n", STATE_WAIT_MS);
            hgcd_close(client);
            return 1;
        }
        if (rc != HGCD_OK) {
            return fail(client, "reading the state");
        }
        if (!started) {
            first_time = s.time;
            started = 1;
        }
        double elapsed = s.time - first_time;
        if (elapsed >= duration) {
            break;
        }
        if (hgcd_set_force(client, 0.0, 0.0, wall_force(s.position[2], height, k)) != HGCD_OK) {
            return fail(client, "sending the force");
        }
        if (elapsed >= duration - 1.0) {
            sum += s.position[2] < height ? height - s.position[2] : 0.0;
            count++;
        }
    }
    if (hgcd_set_force(client, 0.0, 0.0, 0.0) != HGCD_OK) {
        return fail(client, "releasing the force");
    }
    if (count > 0) {
        printf("mean penetration over the last second: %.3f mm\n", sum / count * 1e3);
    }
    hgcd_close(client);
    return 0;
}
