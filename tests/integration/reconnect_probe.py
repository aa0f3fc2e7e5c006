"""What plain Zenoh does after a dead zone or a roam, measured in the kernel lab (issue 39).

    sudo .venv/bin/python -m tests.integration.reconnect_probe --link tls --fault dead:15
    sudo .venv/bin/python -m tests.integration.reconnect_probe --link udp --fault roam \\
        --set transport/unicast/open_timeout=1500 \\
        --set 'connect/retry={"period_init_ms":250,"period_max_ms":500,"period_increase_factor":2}'

A Python Zenoh router (the CEDDP's role) in the CEDDP namespace of ``arpz.lab``, a Python Zenoh
client (a robot's role: 50 puts a second of 1 KB with DROP congestion control, and a liveliness
token) in the robot's. The router prints when each sample run begins after a silence and when the
client's token comes and goes; the driver cuts the link (an nftables drop-all for N seconds, or a
move to the other access point's subnet) and reports how long after the link was usable again
the first sample arrived. Every time is ``time.time()``, one clock for every process of a host.
``--set KEY=JSON`` adds a Zenoh config entry to the client's (``--router-set`` to the router's).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

FLEET = "lab"
KEY = f"arpz/{FLEET}/robot/robot1/sensor/probe"
TOKEN = f"arpz/{FLEET}/robot/robot1/presence"
CEDDP_TOKEN = f"arpz/{FLEET}/ceddp/presence"
PORT = 7447


def _config(base: str | None, mode: str, sets: list[str]):  # type: ignore[no-untyped-def]
    import zenoh

    conf = zenoh.Config.from_file(base) if base else zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    for item in sets:
        key, _, value = item.partition("=")
        conf.insert_json5(key, value)
    return conf


def router(args: argparse.Namespace) -> None:
    import zenoh

    conf = _config(args.zenoh_config, "router", args.set)
    conf.insert_json5("listen/endpoints", json.dumps([args.endpoint]))
    last = [0.0]
    count = [0]

    def on_sample(sample: zenoh.Sample) -> None:
        now = time.time()
        if now - last[0] > 0.3:
            print(f"RUN {now:.3f} gap {now - last[0]:.3f}", flush=True)
        last[0] = now
        count[0] += 1

    def on_token(sample: zenoh.Sample) -> None:
        kind = "JOIN" if sample.kind == zenoh.SampleKind.PUT else "LEAVE"
        print(f"{kind} {time.time():.3f}", flush=True)

    with zenoh.open(conf) as session:
        # kept: a token or subscriber object that is dropped is undeclared
        kept = [
            session.declare_subscriber(KEY, on_sample),
            session.liveliness().declare_subscriber(TOKEN, on_token, history=True),
            session.liveliness().declare_token(CEDDP_TOKEN),
        ]
        print("READY", flush=True)
        end = time.monotonic() + args.run_s
        while time.monotonic() < end:
            time.sleep(1.0)
            print(f"COUNT {time.time():.3f} {count[0]}", flush=True)
        del kept


def client(args: argparse.Namespace) -> None:
    import zenoh

    conf = _config(args.zenoh_config, "client", args.set)
    conf.insert_json5("connect/endpoints", json.dumps([args.endpoint]))

    def on_ceddp(sample: zenoh.Sample) -> None:
        alive = sample.kind == zenoh.SampleKind.PUT
        print(f"CEDDP {'alive' if alive else 'gone'} {time.time():.3f}", flush=True)

    with zenoh.open(conf) as session:
        pub = session.declare_publisher(KEY, congestion_control=zenoh.CongestionControl.DROP)
        kept = [
            session.liveliness().declare_token(TOKEN),
            session.liveliness().declare_subscriber(CEDDP_TOKEN, on_ceddp, history=True),
        ]
        print("CONNECTED", flush=True)
        payload = bytes(1000)
        end = time.monotonic() + args.run_s
        while time.monotonic() < end:
            try:
                pub.put(payload)
            except zenoh.ZError as exc:
                print(f"PUT_ERROR {time.time():.3f} {exc}", flush=True)
            time.sleep(0.02)
        del kept


def _wait_line(log: Path, needle: str, after: float = 0.0, timeout_s: float = 30) -> float | None:
    """The time of the first line ``needle T ...`` with T > ``after`` (None: none in time)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for line in log.read_text().splitlines():
            parts = line.split()
            if parts and parts[0] == needle:
                stamp = float(parts[1]) if len(parts) > 1 else 0.0
                if stamp > after or needle in ("READY", "CONNECTED"):
                    return stamp
        time.sleep(0.05)
    return None


def _received_after(log: Path, cut: float) -> int:
    """Samples the router counted after ``cut`` (from its once-a-second COUNT lines)."""
    counts = [
        (float(parts[1]), int(parts[2]))
        for parts in (line.split() for line in log.read_text().splitlines())
        if parts and parts[0] == "COUNT"
    ]
    before = [n for t, n in counts if t <= cut]
    return counts[-1][1] - (before[-1] if before else 0) if counts else 0


def drive(args: argparse.Namespace) -> int:
    from arpz.lab import Lab, LinkState
    from arpz.lab.fleet import make_certs

    tmp = Path(tempfile.mkdtemp(prefix="arpz-probe-"))
    me = ["-m", "tests.integration.reconnect_probe"]
    root = Path(__file__).resolve().parents[2]
    with Lab.create(["robot1"]) as lab:
        endpoint = f"{args.link}/{lab.ceddp_address}:{PORT}"
        common = ["--endpoint", endpoint, "--run-s", str(args.wait_s + 60)]
        router_conf, client_conf = [], []
        if args.link in ("tls", "quic"):
            zenoh_files = make_certs(tmp / "tls", FLEET, ["robot1"], lab.ceddp_address) / "zenoh"
            router_conf = ["--zenoh-config", str(zenoh_files / "ceddp-router.json5")]
            client_conf = ["--zenoh-config", str(zenoh_files / "robot1-client.json5")]
        rargs = [*me, "router", *common, *router_conf]
        for item in args.router_set:
            rargs += ["--set", item]
        # spawned in ``root`` (the module must import) with their logs in ``tmp``
        lab.spawn("router", lab.ceddp_namespace, rargs, tmp, env={"PYTHONPATH": str(root)})
        rlog, clog = tmp / "router.log", tmp / "client.log"
        if _wait_line(rlog, "READY") is None:
            print(rlog.read_text())
            return 1
        cargs = [*me, "client", *common, *client_conf]
        for item in args.set:
            cargs += ["--set", item]
        robot_ns = lab.robot("robot1").namespace
        lab.spawn("client", robot_ns, cargs, tmp, env={"PYTHONPATH": str(root)})
        if _wait_line(clog, "CONNECTED") is None:
            print(clog.read_text())
            return 1
        time.sleep(2.0)
        kind, _, seconds = args.fault.partition(":")
        cut = time.time()
        if kind == "dead":
            lab.apply("robot1", LinkState(dead=True), "dead zone")
            time.sleep(float(seconds))
            lab.apply("robot1", LinkState(), "back in range")
        else:
            lab.apply("robot1", LinkState(subnet=1), "roam")
        usable = time.time()
        # the first run of samples after the cut (runs begin only after a silence): UDP datagrams
        # may arrive while the second rule is being removed, a moment before ``usable``
        back = _wait_line(rlog, "RUN", after=cut, timeout_s=args.wait_s)
        result = {
            "link": args.link,
            "fault": args.fault,
            "client_set": args.set,
            "rejoined_after_usable_s": None if back is None else round(max(0.0, back - usable), 2),
            "rejoined_after_cut_s": None if back is None else round(back - cut, 2),
            "router": [
                ln
                for ln in rlog.read_text().splitlines()
                if ln.split()[0] in ("RUN", "JOIN", "LEAVE")
            ],
            "received_after_cut": _received_after(rlog, cut),
            "client": [ln for ln in clog.read_text().splitlines()[-8:]],
        }
        if args.ss:
            result["robot_sockets"] = lab.run(robot_ns, ["ss", "-tnio"]).stdout.splitlines()
        print(json.dumps(result, indent=1))
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tests.integration.reconnect_probe")
    parser.add_argument("role", nargs="?", default="drive", choices=["drive", "router", "client"])
    parser.add_argument("--link", default="tcp", choices=["tcp", "tls", "udp", "quic"])
    parser.add_argument("--fault", default="dead:15", help="dead:SECONDS or roam")
    parser.add_argument("--set", action="append", default=[], help="client Zenoh KEY=JSON")
    parser.add_argument("--router-set", action="append", default=[], help="router KEY=JSON")
    parser.add_argument("--wait-s", type=float, default=60.0, help="give up after this")
    parser.add_argument("--ss", action="store_true", help="list the robot's sockets at the end")
    parser.add_argument("--endpoint")
    parser.add_argument("--zenoh-config")
    parser.add_argument("--run-s", type=float, default=120.0)
    args = parser.parse_args(argv)
    if args.role == "router":
        router(args)
        return 0
    if args.role == "client":
        client(args)
        return 0
    return drive(args)


if __name__ == "__main__":
    sys.exit(main())
