#!/usr/bin/env python3
"""A psychophysics-style trial through hgcd, writing every state sample to CSV.

1. Hold: a stiff, damped spring holds the handle where it was when the trial started, until it
   has stayed still (speed under --still-speed mm/s) for --still-time s.
2. Stimulus: a spring of --stiffness N/mm anchored at the same point, for --duration s.

Gravity compensation comes from the daemon underneath: the springs are the only forces this
script renders. A load on the handle (the participant's hand, a probe mass m_p) settles where the
stimulus spring balances it, k * displacement = m_p g; the script prints both over the last
second.

    hgcd --socket /tmp/hgcd.sock --state-dir /tmp/hgcd-state run --device sim:point-mass &
    python3 clients/python/examples/spring_trial.py --socket /tmp/hgcd.sock --csv trial.csv

CSV columns: phase, tick, time_s, x_m, y_m, z_m, vx_m_s, vy_m_s, vz_m_s, fx_n, fy_n, fz_n (force
sent to the device: the offset plus compensation), ox_n, oy_n, oz_n (the offset this script sent
in answer to the sample), flags, offset_seq.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import sys
from typing import List, Sequence

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import hgcd_client  # noqa: E402  (the module one directory up)

#: Stiffness and damping of the hold, N/m and N*s/m.
HOLD_STIFFNESS = 300.0
HOLD_DAMPING = 3.0
#: How long without a state sample means the daemon has stalled, s.
STATE_WAIT_S = 2.0


def spring(position: Sequence[float], velocity: Sequence[float], anchor: Sequence[float],
           k: float, b: float, limit: float) -> List[float]:
    """F = -k (x - anchor) - b v, each axis within the daemon's per-axis `limit` (N)."""
    return [max(-limit, min(limit, -k * (x - a) - b * v))
            for x, a, v in zip(position, anchor, velocity)]


def run(args: argparse.Namespace) -> None:
    k = args.stiffness * 1e3
    still_speed = args.still_speed * 1e-3
    with hgcd_client.connect(args.socket, args.device) as client, open(args.csv, "w", newline="") as out:
        welcome = client.take_ownership("spring_trial.py")
        client.subscribe(welcome.rate_hz)
        rows = csv.writer(out)
        rows.writerow(["phase", "tick", "time_s", "x_m", "y_m", "z_m", "vx_m_s", "vy_m_s",
                       "vz_m_s", "fx_n", "fy_n", "fz_n", "ox_n", "oy_n", "oz_n", "flags",
                       "offset_seq"])
        anchor = None
        phase, phase_start, still_since = "hold", 0.0, None
        last_second: List[List[float]] = []  # displacement and offset, stimulus phase
        while True:
            s = client.newest_state(wait=STATE_WAIT_S)
            if s is None:
                raise hgcd_client.HgcdError(f"no state from the daemon for {STATE_WAIT_S} s")
            if anchor is None:
                anchor, phase_start = s.position, s.time
            elapsed = s.time - phase_start
            if phase == "hold":
                if math.sqrt(sum(v * v for v in s.velocity)) >= still_speed:
                    still_since = None
                elif still_since is None:
                    still_since = s.time
                if still_since is not None and s.time - still_since >= args.still_time:
                    phase, phase_start, elapsed = "stimulus", s.time, 0.0
                elif elapsed > args.hold_timeout:
                    raise hgcd_client.HgcdError(
                        f"the handle did not stay still within {args.hold_timeout} s")
            done = phase == "stimulus" and elapsed >= args.duration
            if done:
                offset = [0.0, 0.0, 0.0]
            elif phase == "hold":
                offset = spring(s.position, s.velocity, anchor, HOLD_STIFFNESS, HOLD_DAMPING,
                                welcome.max_force_n)
            else:
                offset = spring(s.position, s.velocity, anchor, k, 0.0, welcome.max_force_n)
            client.set_force(offset)
            rows.writerow([phase, s.tick, s.time, *s.position, *s.velocity, *s.force, *offset,
                           s.flags, s.offset_seq])
            if done:
                break
            if phase == "stimulus" and elapsed >= args.duration - 1.0:
                last_second.append([x - a for x, a in zip(s.position, anchor)] + offset)
    if last_second:
        mean = [sum(r[i] for r in last_second) / len(last_second) for i in range(6)]
        print("stimulus, last second: displacement ({:.3f}, {:.3f}, {:.3f}) mm, "
              "spring force ({:.3f}, {:.3f}, {:.3f}) N".format(*(m * 1e3 for m in mean[:3]),
                                                              *mean[3:]))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--socket", help="the daemon's application socket (default: that of "
                        "the daemon of --device)")
    parser.add_argument("--device", help="the daemon's device, a device id or spec (default: "
                        "the only daemon running)")
    parser.add_argument("--csv", default="trial.csv", help="where to write the samples")
    parser.add_argument("--stiffness", type=float, default=0.2,
                        help="stimulus spring, N/mm (default 0.2)")
    parser.add_argument("--duration", type=float, default=3.0,
                        help="stimulus duration, s (default 3)")
    parser.add_argument("--still-speed", type=float, default=5.0,
                        help="speed below which the handle is still, mm/s (default 5)")
    parser.add_argument("--still-time", type=float, default=0.3,
                        help="how long it must stay still before the stimulus, s (default 0.3)")
    parser.add_argument("--hold-timeout", type=float, default=10.0,
                        help="give up when the handle is not still after this long, s")
    args = parser.parse_args()
    try:
        run(args)
    except hgcd_client.HgcdError as e:
        print(f"spring_trial: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
