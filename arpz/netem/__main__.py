"""``python -m arpz.netem``: a lossy UDP link between a Zenoh client and its router.

Example: 10 % loss each way, 5 ms +/- 2 ms delay, the first second clean so the session opens::

    python -m arpz.netem --listen udp/127.0.0.1:7450 --forward udp/127.0.0.1:7447 \\
        --loss 10 --delay-ms 5 --jitter-ms 2 --clean-s 1 --duration 60

Counters are printed on exit (``--duration`` elapsed, SIGINT or SIGTERM), as text on stderr and
as one JSON line on stdout (``--json FILE`` writes them to a file as well).
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
from types import FrameType

from arpz.netem.model import GilbertElliott, Impairments, Outage
from arpz.netem.proxy import NetemProxy
from arpz.runtime.startup import JSON_TO_STDOUT, add_json_option, add_version_option, fail


def _outage(text: str) -> Outage:
    start, _, duration = text.partition(":")
    try:
        return Outage(start_s=float(start), duration_s=float(duration))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--outage wants START_S:DURATION_S, got {text!r}"
        ) from None


def _burst(text: str) -> GilbertElliott:
    try:
        values = [float(v) for v in text.split(",")]
        if len(values) == 2:
            return GilbertElliott(p=values[0], r=values[1])
        if len(values) == 4:
            return GilbertElliott(p=values[0], r=values[1], loss_good=values[2], loss_bad=values[3])
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    raise argparse.ArgumentTypeError(f"--burst wants P,R or P,R,LOSS_GOOD,LOSS_BAD, got {text!r}")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m arpz.netem", description=__doc__.split("\n")[0])
    ap.add_argument("--listen", required=True, help="udp/HOST:PORT the Zenoh client connects to")
    ap.add_argument("--forward", required=True, help="udp/HOST:PORT of the router")
    ap.add_argument("--loss", type=float, default=0.0, help="random loss in %% (each direction)")
    ap.add_argument(
        "--per-frame",
        action="store_true",
        help="--loss applies to each radio frame of --frame-bytes: a datagram IP fragments into "
        "k frames is lost with probability 1 - (1 - loss)^k (large datagrams, as on WiFi)",
    )
    ap.add_argument(
        "--frame-bytes", type=int, default=1500, help="MTU of one radio frame (--per-frame)"
    )
    ap.add_argument(
        "--burst", type=_burst, help="Gilbert-Elliott P,R[,LOSS_GOOD,LOSS_BAD] (fractions)"
    )
    ap.add_argument("--delay-ms", type=float, default=0.0)
    ap.add_argument("--jitter-ms", type=float, default=0.0, help="uniform +/- around the delay")
    ap.add_argument("--rate-kbps", type=float, default=0.0, help="bandwidth cap, 0 = none")
    ap.add_argument(
        "--queue-ms", type=float, default=500.0, help="tail-drop beyond this queue delay"
    )
    ap.add_argument("--duplicate", type=float, default=0.0, help="duplication in %%")
    ap.add_argument("--reorder", type=float, default=0.0, help="%% held back --reorder-gap-ms")
    ap.add_argument("--reorder-gap-ms", type=float, default=5.0)
    ap.add_argument(
        "--outage",
        type=_outage,
        action="append",
        default=[],
        metavar="START_S:DURATION_S",
        help="link down from START_S (after the clean period) for DURATION_S; repeatable",
    )
    ap.add_argument(
        "--clean-s", type=float, default=0.0, help="no impairment for the first seconds"
    )
    ap.add_argument(
        "--direction",
        choices=["both", "up", "down"],
        default="both",
        help="impair client->router (up), router->client (down) or both",
    )
    ap.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds")
    ap.add_argument("--seed", type=int, default=None)
    add_json_option(ap, "the counters (always printed as one JSON line on stdout too)")
    add_version_option(ap)
    return ap


def impairments_from(args: argparse.Namespace) -> Impairments:
    return Impairments(
        loss=args.loss / 100,
        burst=args.burst,
        delay_s=args.delay_ms / 1000,
        jitter_s=args.jitter_ms / 1000,
        rate_bps=args.rate_kbps * 1000,
        queue_limit_s=args.queue_ms / 1000,
        duplicate=args.duplicate / 100,
        reorder=args.reorder / 100,
        reorder_gap_s=args.reorder_gap_ms / 1000,
        outages=tuple(args.outage),
        clean_s=args.clean_s,
        per_frame=args.per_frame,
        frame_bytes=args.frame_bytes,
    )


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        imp = impairments_from(args)
        clean = Impairments()
        up = imp if args.direction in ("both", "up") else clean
        down = imp if args.direction in ("both", "down") else clean
        proxy = NetemProxy(args.listen, args.forward, up, down, seed=args.seed)
    except (ValueError, OSError) as exc:
        return fail("netem", str(exc))

    def stop(signum: int, frame: FrameType | None) -> None:
        proxy.request_stop()

    signal.signal(signal.SIGINT, stop)
    signal.signal(signal.SIGTERM, stop)
    print(f"arpz netem: {args.listen} -> {args.forward} ready", file=sys.stderr, flush=True)
    report = proxy.run(args.duration or None)
    data = report.as_dict()
    for name in ("up", "down"):
        c = data[name]
        assert isinstance(c, dict)
        print(
            f"arpz.netem {name}: received {c['received']} forwarded {c['forwarded']} "
            f"dropped {c['dropped']} (loss {c['dropped_loss']}, burst {c['dropped_burst']}, "
            f"outage {c['dropped_outage']}, queue {c['dropped_queue']}) duplicated "
            f"{c['duplicated']} reordered {c['reordered']} bytes in {c['bytes_in']} out "
            f"{c['bytes_out']} frames {c['frames_in']} largest datagram {c['largest_datagram']} "
            f"kernel rx overflow {c['rx_overflow']}",
            file=sys.stderr,
        )
    line = json.dumps(data)
    print(line, flush=True)
    if args.json and args.json != JSON_TO_STDOUT:
        with open(args.json, "w") as fh:
            fh.write(line + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
