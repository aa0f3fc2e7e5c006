"""The Hello round trip over wifi-bad with the downlink through the reliable channel vs plain puts.

Seed 001's Hello probe goes robot1 -> CEDDP -> robot2 -> CEDDP -> robot1: two hops up and two
down. Before issue 14 the two CEDDP -> robot hops were plain Zenoh puts, so about 14 % of Hellos
were lost over wifi-bad whatever the QoS. This runs the same fleet (robot1 the origin, robot2
the relay, each behind its own ``arpz.netem`` wifi-bad link) twice in one run: with the downlink
through the channel (arpz's default) and with ``plain_downlink = true`` (the old downlink), and
prints Hello sent, lost, loss % and the round trip, with the ratios.

    python benchmarks/downlink_hello.py --duration 20 --depth 10 [--keep-all]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from arpz.experiment.runner import impairments  # noqa: E402
from arpz.experiment.spec import PROFILES  # noqa: E402
from arpz.netem import Impairments, NetemProxy  # noqa: E402
from tests.integration.fleet import ceddp, robots, settle, write_robot  # noqa: E402
from tests.support import free_udp_port, wait_until  # noqa: E402


def run(tmp: Path, *, plain_downlink: bool, duration_s: float, qos: str) -> dict[str, Any]:
    top = "plain_downlink = true\n" if plain_downlink else ""
    udp = f"udp/127.0.0.1:{free_udp_port()}"
    proxies = {r: NetemProxy(f"udp/127.0.0.1:{free_udp_port()}", udp, Impairments()) for r in
               ("robot1", "robot2")}  # fmt: skip
    bad = impairments(PROFILES["wifi-bad"])
    with ceddp(tmp, relay="robot2", extra=top + qos, also_listen=(udp,)) as (server, _):
        for proxy in proxies.values():
            proxy.start()
        try:
            configs = [
                write_robot(
                    tmp,
                    robot,
                    f"udp/127.0.0.1:{proxies[robot].listen_port}",
                    preset=preset,
                    rate_hz=20,
                    hello=robot == "robot1",
                    extra=qos,
                    top=top,
                )
                for robot, preset in (("robot2", "machine3"), ("robot1", "machine1"))
            ]
            with robots(tmp, configs) as procs:
                wait_until(lambda: "robot robot1 joined" in server.output(), what="robot1")
                for proxy in proxies.values():
                    lossy = dataclasses.replace(bad, clean_s=proxy.elapsed_s)
                    proxy.set_impairments(lossy, lossy)
                settle(duration_s)
                for proc in reversed(procs):  # the origin first: its Hellos settle at the relay
                    assert proc.interrupt(timeout_s=30) == 0, proc.output()
            assert server.interrupt() == 0, server.output()
        finally:
            reports = [p.stop() for p in proxies.values()]
            dropped = sum(r.up.dropped + r.down.dropped for r in reports)
    row = json.loads((tmp / "summary.json").read_text())["robots"]["robot1"]
    hello = row["hello"]
    return {
        "downlink": "plain puts" if plain_downlink else "reliable channel",
        "sent": hello["sent"],
        "received": hello["received"],
        "lost": hello["lost"],
        "loss_pct": 100.0 * hello["lost"] / max(hello["sent"], 1),
        "rtt_ms_p50": hello["rtt_ms_p50"],
        "rtt_ms_p99": hello["rtt_ms_p99"],
        "datagrams_dropped_by_the_link": dropped,
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--duration", type=float, default=20.0, help="seconds over wifi-bad")
    parser.add_argument("--depth", type=int, default=10, help="KEEP_LAST depth of every hop")
    parser.add_argument("--keep-all", action="store_true", help="KEEP_ALL on every hop")
    parser.add_argument("--json", type=Path, help="write the figures here")
    args = parser.parse_args()
    history = "keep_all" if args.keep_all else "keep_last"
    qos = f'[sensor_qos]\nreliability = "reliable"\nhistory = "{history}"\ndepth = {args.depth}\n'
    rows = []
    for plain in (False, True):
        started = time.monotonic()
        label = "plain-put downlink" if plain else "channel downlink"
        print(f"running {args.duration:.0f} s with the {label} ...", flush=True)
        with tempfile.TemporaryDirectory() as tmp:
            rows.append(run(Path(tmp), plain_downlink=plain, duration_s=args.duration, qos=qos))
        print(f"  done in {time.monotonic() - started:.0f} s", flush=True)
    print(f"\nwifi-bad, {history}" + ("" if args.keep_all else f" {args.depth}"))
    print(f"{'downlink':<18}{'sent':>6}{'lost':>6}{'loss %':>8}{'rtt p50':>9}{'rtt p99':>9}")
    for r in rows:
        print(
            f"{r['downlink']:<18}{r['sent']:>6}{r['lost']:>6}{r['loss_pct']:>8.2f}"
            f"{r['rtt_ms_p50'] or 0:>9.2f}{r['rtt_ms_p99'] or 0:>9.2f}"
        )
    channel, plain_row = rows
    if plain_row["rtt_ms_p50"] and channel["rtt_ms_p50"]:
        print(
            f"channel / plain: rtt p50 {channel['rtt_ms_p50'] / plain_row['rtt_ms_p50']:.2f}x, "
            f"p99 {channel['rtt_ms_p99'] / plain_row['rtt_ms_p99']:.2f}x; loss "
            f"{channel['loss_pct']:.2f} % vs {plain_row['loss_pct']:.2f} %"
        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
