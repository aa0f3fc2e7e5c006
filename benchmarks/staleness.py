"""Staleness with the local cache over a bad WiFi link (issue 14).

A robot with the local cache on, KEEP_LAST depth 1, publishing machine2's sensors at a high rate
through ``arpz.netem``'s ``wifi-bad`` profile (3 % loss plus bursts, 5 ms each way, 54 Mb/s) to
a real CEDDP. Staleness is how long the CEDDP held a value other than the robot's latest reading,
measured once per change (docs/protocol.md, ``changed_ns``). The bound of the issue: one sensor
period plus one round trip plus the NACK delay. The round trip is measured in the same run: twice
the median one-way sample latency.

    python benchmarks/staleness.py --rate 1000 --duration 20

prints one row per topic (p50, p99, max staleness) against the issue's bound and against the
time one NACK recovery takes (half a round trip more: the heartbeat that reveals the loss must
travel too), and exits 1 if any topic's p99 exceeds the latter. ``--json FILE`` writes them.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from arpz.channel import QOS_DEFAULT  # noqa: E402
from arpz.experiment.runner import impairments  # noqa: E402
from arpz.experiment.spec import PROFILES  # noqa: E402
from tests.integration.fleet import ceddp, robots, settle, udp_link, write_robot  # noqa: E402
from tests.support import wait_until  # noqa: E402


def measure(tmp: Path, *, rate_hz: float, duration_s: float, depth: int) -> dict[str, Any]:
    """Run one robot over wifi-bad and return the CEDDP summary's robot row and the proxy's."""
    qos = f'[sensor_qos]\nreliability = "reliable"\nhistory = "keep_last"\ndepth = {depth}\n'
    link = udp_link()  # the session comes up clean, then the link turns bad
    udp, proxy = link.ceddp_endpoint, link.proxy
    with ceddp(tmp, extra=qos, also_listen=(udp,)) as (server, _):
        proxy.start()
        try:
            config = write_robot(
                tmp,
                "robot1",
                link.robot_endpoint,
                preset="machine2",
                rate_hz=rate_hz,
                extra=qos,
            )
            with robots(tmp, [config]) as (robot,):
                wait_until(lambda: "robot robot1 joined" in server.output(), what="robot1")
                link.impair(impairments(PROFILES["wifi-bad"]))
                settle(duration_s)
                assert robot.interrupt(timeout_s=30) == 0, robot.output()
            assert server.interrupt() == 0, server.output()
        finally:
            report = proxy.stop()
    row = json.loads((tmp / "summary.json").read_text())["robots"]["robot1"]
    return {"row": row, "proxy": report.as_dict()}


def figures(row: dict[str, Any], *, rate_hz: float) -> dict[str, Any]:
    latencies = [
        t["latency_ms_p50"] for t in row["topics"].values() if t["latency_ms_p50"] is not None
    ]
    rtt_ms = 2 * sorted(latencies)[len(latencies) // 2]
    nack_ms = QOS_DEFAULT.nack_delay_s * 1000
    bound_ms = 1000.0 / rate_hz + rtt_ms + nack_ms
    # a lost change is recovered by: the next held-back reading's heartbeat (one period), its
    # one-way trip, the NACK delay, then the NACK and the resend (a round trip): half a round
    # trip more than the bound, which no recovery can beat
    recovery_ms = 1000.0 / rate_hz + 1.5 * rtt_ms + nack_ms
    topics = {
        name: {
            "received": t["received"],
            "lost": t["lost"],
            "cache_forgets": t["cache_forgets"],
            "held_back": t["held_back"],
            "staleness_ms_p50": t["staleness_ms_p50"],
            "staleness_ms_p99": t["staleness_ms_p99"],
            "staleness_ms_max": t["staleness_ms_max"],
        }
        for name, t in sorted(row["topics"].items())
        if name != "hello"
    }
    return {
        "rate_hz": rate_hz,
        "rtt_ms": rtt_ms,
        "bound_ms": bound_ms,
        "recovery_bound_ms": recovery_ms,
        "topics": topics,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rate", type=float, default=1000.0, help="sensor rate, Hz")
    parser.add_argument("--duration", type=float, default=20.0, help="seconds over wifi-bad")
    parser.add_argument("--depth", type=int, default=1, help="KEEP_LAST depth")
    parser.add_argument("--json", type=Path, help="write the figures here")
    args = parser.parse_args()
    started = time.monotonic()
    print(f"running {args.duration:.0f} s over wifi-bad at {args.rate:.0f} Hz ...", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        result = measure(Path(tmp), rate_hz=args.rate, duration_s=args.duration, depth=args.depth)
    out = figures(result["row"], rate_hz=args.rate)
    out["proxy"] = result["proxy"]
    print(
        f"bound: period {1000 / args.rate:.2f} ms + round trip {out['rtt_ms']:.2f} ms "
        f"+ NACK delay {QOS_DEFAULT.nack_delay_s * 1000:.1f} ms = {out['bound_ms']:.2f} ms"
    )
    print(
        f"one recovery (period + 1.5 round trips + NACK delay): {out['recovery_bound_ms']:.2f} ms"
    )
    print(
        f"{'topic':<12}{'received':>9}{'lost':>6}{'forgets':>8}{'p50 ms':>9}{'p99 ms':>9}"
        f"{'max ms':>9}  within bound / recovery bound"
    )
    ok = True
    for name, t in out["topics"].items():
        p99 = t["staleness_ms_p99"]
        if p99 is None:
            print(f"{name:<12}{t['received']:>9}{t['lost']:>6}  no change of value arrived")
            continue
        fine = p99 <= out["recovery_bound_ms"]
        ok &= fine
        print(
            f"{name:<12}{t['received']:>9}{t['lost']:>6}{t['cache_forgets']:>8}"
            f"{t['staleness_ms_p50']:>9.2f}{p99:>9.2f}{t['staleness_ms_max']:>9.2f}  "
            f"{'yes' if p99 <= out['bound_ms'] else 'NO'} / {'yes' if fine else 'NO'}"
        )
    print(f"({time.monotonic() - started:.0f} s)")
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
