#!/usr/bin/env python3
"""Two devices, one application: a virtual spring and damper between the handles of two daemons.

The counterpart of examples/two_handles.rs, the simplest teleoperation: each handle is pulled
toward the other, F_a = k (x_b - x_a) + b (v_b - v_a) and F_b = -F_a; move one and the other
follows. Gravity compensation comes from the daemons underneath.

    python3 clients/python/examples/two_handles.py --device hid:1209:4847:SN1 --device hid:1209:4847:SN2
    python3 clients/python/examples/two_handles.py --socket /tmp/a.sock --socket /tmp/b.sock

It prints the distance between the handles at the start and at the end.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
from typing import List, Optional, Tuple

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
import hgcd_client  # noqa: E402  (the module one directory up)

#: How long without a state sample means a daemon has stalled, s.
STATE_WAIT_S = 2.0


def state(client: hgcd_client.Client) -> hgcd_client.State:
    s = client.newest_state(wait=STATE_WAIT_S)
    if s is None:
        raise hgcd_client.HgcdError(f"no state from the daemon for {STATE_WAIT_S} s")
    return s


def run(args: argparse.Namespace, ends: List[Tuple[Optional[str], Optional[str]]]) -> None:
    k = args.stiffness * 1e3
    with hgcd_client.connect(*ends[0]) as a, hgcd_client.connect(*ends[1]) as b:
        welcomes = [c.take_ownership("two_handles.py") for c in (a, b)]
        if welcomes[0].device_id == welcomes[1].device_id:
            raise hgcd_client.HgcdError(
                f"both names lead to the same device {welcomes[0].device_id}")
        # Each axis within the smaller limit, so that the two forces stay equal and opposite.
        limit = min(w.max_force_n for w in welcomes)
        for client, welcome in zip((a, b), welcomes):
            client.subscribe(welcome.rate_hz)
        start, first_gap = None, None
        while True:
            sa, sb = state(a), state(b)
            gap = math.dist(sa.position, sb.position)
            if start is None:
                start, first_gap = sa.time, gap
            if sa.time - start >= args.duration:
                break
            f = [max(-limit, min(limit, k * (xb - xa) + args.damping * (vb - va)))
                 for xa, xb, va, vb in zip(sa.position, sb.position, sa.velocity, sb.velocity)]
            a.set_force(f)
            b.set_force([-c for c in f])
        a.set_force((0.0, 0.0, 0.0))
        b.set_force((0.0, 0.0, 0.0))
    print(f"coupled {welcomes[0].device_id} and {welcomes[1].device_id}: distance between the "
          f"handles {first_gap * 1e3:.3f} mm at the start, {gap * 1e3:.3f} mm at the end")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", action="append", default=[],
                        help="a daemon's device, a device id or spec (give two in all)")
    parser.add_argument("--socket", action="append", default=[],
                        help="a daemon's application socket")
    parser.add_argument("--stiffness", type=float, default=0.2, help="spring, N/mm (default 0.2)")
    parser.add_argument("--damping", type=float, default=5.0,
                        help="damping on the relative velocity, N*s/m (default 5)")
    parser.add_argument("--duration", type=float, default=5.0,
                        help="how long to couple, s of the first device's time (default 5)")
    args = parser.parse_args()
    ends = [(s, None) for s in args.socket] + [(None, d) for d in args.device]
    if len(ends) != 2:
        parser.error("name two daemons: two --device, two --socket, or one of each")
    if not (args.stiffness > 0 and math.isfinite(args.stiffness)):
        parser.error("--stiffness must be a positive number of N/mm")
    if not (args.damping >= 0 and math.isfinite(args.damping)):
        parser.error("--damping must be a number of N*s/m, 0 or more")
    try:
        run(args, ends)
    except hgcd_client.HgcdError as e:
        print(f"two_handles: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
