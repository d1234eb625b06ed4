/*
 * Two devices, one application, from C: a virtual spring and damper between the handles of two
 * daemons, the counterpart of examples/two_handles.rs. Each handle is pulled toward the other,
 * F_a = k (x_b - x_a) + b (v_b - v_a) and F_b = -F_a. Gravity compensation comes from the
 * daemons.
 *
 * Build and run (from the repository; see docs/app-protocol.md, "From C"):
 *
 *   cargo build --release -p hgcd-c
 *   cc -std=c99 -Wall -Iclients/c/include clients/c/examples/two_handles.c \
 *      -Ltarget/release -lhgcd_c -lm -Wl,-rpath,"$PWD/target/release" -o two_handles
 *   ./two_handles --device hid:1209:4847:SN1 --device hid:1209:4847:SN2 --duration 5
 *
 * It prints the distance between the handles at the start and at the end.
 */
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include "hgcd.h"

/* How long to wait for a state sample before deciding a daemon has stalled, ms. */
#define STATE_WAIT_MS 2000

static const char *usage =
    "usage: two_handles (--device SPEC | --socket PATH) (--device SPEC | --socket PATH)\n"
    "                   [--stiffness N_PER_MM] [--damping N_S_PER_M] [--duration S]\n";

/* Parse the value of option `name` as a number; exit with one line saying what was wrong. */
static double number(const char *name, const char *text) {
    char *end = NULL;
    double value = text ? strtod(text, &end) : 0.0;
    if (!text || end == text || *end != '\0') {
        fprintf(stderr, "two_handles: %s needs a number, got '%s'\n%s", name, text ? text : "",
                usage);
        exit(2);
    }
    return value;
}

/* Print what failed with the library's message, close both connections, return 1. */
static int fail(hgcd_client *a, hgcd_client *b, const char *doing) {
    fprintf(stderr, "two_handles: %s: %s\n", doing, hgcd_last_error());
    hgcd_close(a);
    hgcd_close(b);
    return 1;
}

/* Connect to the daemon at `socket` or of `device`, owning its force. */
static int open_end(int by_socket, const char *name, hgcd_client **client) {
    hgcd_welcome welcome;
    int rc = by_socket ? hgcd_connect(name, client) : hgcd_connect_device(name, client);
    if (rc == HGCD_OK) {
        rc = hgcd_take_ownership(*client, "two_handles.c", &welcome);
    }
    if (rc == HGCD_OK) {
        rc = hgcd_subscribe(*client, welcome.rate_hz);
    }
    return rc;
}

/* The newest state of `client`, or an error code (HGCD_NO_SAMPLE: none within the wait). */
static int next_state(hgcd_client *client, hgcd_state *s) {
    return hgcd_newest_state(client, STATE_WAIT_MS, s);
}

static double within(double f) {
    double limit = HGCD_DEFAULT_MAX_FORCE_N;
    return f > limit ? limit : f < -limit ? -limit : f;
}

int main(int argc, char **argv) {
    const char *names[2];
    int by_socket[2], ends = 0;
    double stiffness = 0.2, damping = 5.0, duration = 5.0;
    for (int i = 1; i < argc; i++) {
        const char *value = i + 1 < argc ? argv[i + 1] : NULL;
        int is_socket = strcmp(argv[i], "--socket") == 0;
        if ((is_socket || strcmp(argv[i], "--device") == 0) && value && ends < 2) {
            names[ends] = value;
            by_socket[ends++] = is_socket;
        } else if (strcmp(argv[i], "--stiffness") == 0) {
            stiffness = number("--stiffness", value);
        } else if (strcmp(argv[i], "--damping") == 0) {
            damping = number("--damping", value);
        } else if (strcmp(argv[i], "--duration") == 0) {
            duration = number("--duration", value);
        } else {
            fprintf(stderr, "two_handles: unexpected '%s'\n%s", argv[i], usage);
            return 2;
        }
        i++;
    }
    if (ends != 2) {
        fprintf(stderr, "two_handles: name two daemons\n%s", usage);
        return 2;
    }
    const double k = stiffness * 1e3;

    hgcd_client *a = NULL, *b = NULL;
    if (open_end(by_socket[0], names[0], &a) != HGCD_OK) {
        return fail(a, b, names[0]);
    }
    if (open_end(by_socket[1], names[1], &b) != HGCD_OK) {
        return fail(a, b, names[1]);
    }

    hgcd_state sa, sb;
    double first_time = 0.0, first_gap = -1.0, gap = 0.0;
    for (;;) {
        int rc = next_state(a, &sa);
        if (rc == HGCD_OK) {
            rc = next_state(b, &sb);
        }
        if (rc == HGCD_NO_SAMPLE) {
            fprintf(stderr, "two_handles: no state for %d ms\n", STATE_WAIT_MS);
            hgcd_close(a);
            hgcd_close(b);
            return 1;
        }
        if (rc != HGCD_OK) {
            return fail(a, b, "reading the state");
        }
        double f[3], squares = 0.0;
        for (int j = 0; j < 3; j++) {
            double d = sb.position[j] - sa.position[j];
            squares += d * d;
            f[j] = within(k * d + damping * (sb.velocity[j] - sa.velocity[j]));
        }
        gap = sqrt(squares);
        if (first_gap < 0.0) {
            first_gap = gap;
            first_time = sa.time;
        }
        if (sa.time - first_time >= duration) {
            break;
        }
        if (hgcd_set_force(a, f[0], f[1], f[2]) != HGCD_OK ||
            hgcd_set_force(b, -f[0], -f[1], -f[2]) != HGCD_OK) {
            return fail(a, b, "sending the force");
        }
    }
    if (hgcd_set_force(a, 0.0, 0.0, 0.0) != HGCD_OK || hgcd_set_force(b, 0.0, 0.0, 0.0) != HGCD_OK) {
        return fail(a, b, "releasing the force");
    }
    printf("distance between the handles: %.3f mm at the start, %.3f mm at the end\n",
           first_gap * 1e3, gap * 1e3);
    hgcd_close(a);
    hgcd_close(b);
    return 0;
}
