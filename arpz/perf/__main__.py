"""``python -m arpz.perf``: the project's performance_test (docs/perf.md).

    python -m arpz.perf router --listen tcp/127.0.0.1:7447
    python -m arpz.perf sub --connect tcp/127.0.0.1:7447 --key perf/t --transport arpz --json r.json
    python -m arpz.perf pub --connect tcp/127.0.0.1:7447 --key perf/t --transport arpz \\
        --rate 1000 --count 5000

``ping``/``pong`` measure round trips the same way. Every command closes its Zenoh session on
every exit path (end, error, SIGINT, SIGTERM): a process exiting with a declared callback
subscriber would hang.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import signal
import sys
import time
from types import FrameType
from typing import Any

import msgspec
import numpy as np

from arpz.channel import HistoryFullError
from arpz.core.config import ConfigError
from arpz.core.link_sizes import link_sizes
from arpz.core.protocol.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    LivelinessPolicy,
    QosProfile,
    ReliabilityPolicy,
    load_qos,
)
from arpz.core.transport import SessionSettings, TransportError
from arpz.perf import fleet
from arpz.perf.endpoints import STOP, TRANSPORTS, ArpzPub, ArpzSub, OnPayload, Pub, Sub
from arpz.perf.fleet import add_fleet_parser
from arpz.perf.report import HEADER, Recorder, build_report, payload_maker
from arpz.perf.zenoh_baselines import AdvancedPub, AdvancedSub, ZenohPub, ZenohSub, open_session
from arpz.runtime.startup import JSON_TO_STDOUT, add_json_option, add_version_option, fail
from arpz.transport.zenoh import ZenohTransport, load_zenoh_config


def _on_signal(signum: int, frame: FrameType | None) -> None:
    STOP.set()


def _endpoints(text: str) -> list[str]:
    return [e.strip() for e in text.split(",") if e.strip()]


def add_qos_flags(ap: argparse.ArgumentParser) -> None:
    g = ap.add_argument_group("QoS (arpz transport)")
    g.add_argument("--qos-file", help="TOML profile; the flags below override it")
    g.add_argument("--reliability", choices=[p.value for p in ReliabilityPolicy])
    g.add_argument("--history", choices=[p.value for p in HistoryPolicy])
    g.add_argument("--depth", type=int)
    g.add_argument("--max-samples", type=int)
    g.add_argument("--durability", choices=[p.value for p in DurabilityPolicy])
    g.add_argument("--deadline-ms", type=float)
    g.add_argument("--lifespan-ms", type=float)
    g.add_argument("--liveliness", choices=[p.value for p in LivelinessPolicy])
    g.add_argument("--lease-ms", type=float)
    g.add_argument("--heartbeat-ms", type=float)
    g.add_argument("--nack-delay-ms", type=float)
    g.add_argument("--reorder-timeout-ms", type=float)
    g.add_argument(
        "--batch", type=int, help="batch_max_samples: samples per message (default 64, 1 = off)"
    )
    g.add_argument("--batch-delay-us", type=float, help="batch_max_delay_s in microseconds")
    g.add_argument("--cache", type=int, default=10000, help="advanced: publisher cache size")


def qos_from_args(args: argparse.Namespace) -> QosProfile:
    base = load_qos(args.qos_file) if args.qos_file else QosProfile(history=HistoryPolicy.KEEP_ALL)
    changes: dict[str, Any] = {}
    for flag, field, conv in (
        ("reliability", "reliability", ReliabilityPolicy),
        ("history", "history", HistoryPolicy),
        ("depth", "depth", int),
        ("max_samples", "max_samples", int),
        ("durability", "durability", DurabilityPolicy),
        ("deadline_ms", "deadline_s", lambda v: v / 1000),
        ("lifespan_ms", "lifespan_s", lambda v: v / 1000),
        ("liveliness", "liveliness", LivelinessPolicy),
        ("lease_ms", "lease_duration_s", lambda v: v / 1000),
        ("heartbeat_ms", "heartbeat_period_s", lambda v: v / 1000),
        ("nack_delay_ms", "nack_delay_s", lambda v: v / 1000),
        ("reorder_timeout_ms", "reorder_timeout_s", lambda v: v / 1000),
        ("batch", "batch_max_samples", int),
        ("batch_delay_us", "batch_max_delay_s", lambda v: v / 1e6),
    ):
        value = getattr(args, flag)
        if value is not None:
            changes[field] = conv(value)
    return msgspec.structs.replace(base, **changes) if changes else base


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="python -m arpz.perf", description="arpz performance test")
    add_version_option(ap)
    sub = ap.add_subparsers(dest="command", required=True)
    r = sub.add_parser("router", help="a bare Zenoh router")
    r.add_argument("--listen", required=True, help="ENDPOINT[,ENDPOINT...]")
    r.add_argument("--duration", type=float, default=0.0)
    add_zenoh_config_flag(r)
    for name in ("pub", "sub", "ping", "pong"):
        p = sub.add_parser(name)
        p.add_argument("--connect", required=True, help="ENDPOINT[,ENDPOINT...]")
        p.add_argument("--key", default="perf/topic")
        p.add_argument("--transport", choices=TRANSPORTS, default="arpz")
        p.add_argument("--express", action="store_true", help="no batching (lower latency)")
        p.add_argument(
            "--inline",
            action="store_true",
            help="arpz: deliver on the transport thread (Reader inline_delivery=True)",
        )
        p.add_argument("--rate", type=float, default=0.0, help="Hz; 0 = as fast as possible")
        p.add_argument("--count", type=int, default=0)
        p.add_argument("--duration", type=float, default=0.0)
        p.add_argument("--size", type=int, default=24, help="payload bytes (at least 16)")
        add_json_option(p, "the report (always printed as one JSON line on stdout too)")
        p.add_argument(
            "--latency-out",
            metavar="FILE",
            help="sub/ping: save every latency (us, in arrival order) as a NumPy .npy file",
        )
        p.add_argument(
            "--linger",
            type=float,
            default=5.0,
            help="pub: seconds to wait for acknowledgements at the end",
        )
        p.add_argument(
            "--warmup",
            type=float,
            default=0.0,
            help="pub/ping: seconds to wait after matching before the first sample",
        )
        p.add_argument(
            "--idle-timeout",
            type=float,
            default=3.0,
            help="sub/ping: stop this long after the last sample once the end is known",
        )
        add_qos_flags(p)
        add_zenoh_config_flag(p)
    add_fleet_parser(sub)
    for name in ("fleet", "fleet-worker"):
        add_zenoh_config_flag(sub.choices[name])
    return ap


def add_zenoh_config_flag(ap: argparse.ArgumentParser) -> None:
    ap.add_argument(
        "--zenoh-config",
        metavar="FILE",
        help="a Zenoh JSON5 config applied to every session first (arpz's settings on top), "
        "e.g. to turn shared memory off: { transport: { shared_memory: { enabled: false } } }",
    )


def _settings(args: argparse.Namespace, **kwargs: Any) -> SessionSettings:
    """The session this command opens: ``--zenoh-config`` first, then ``kwargs`` on top."""
    return SessionSettings(config_file=args.zenoh_config, **kwargs)


def _transport(args: argparse.Namespace) -> ZenohTransport:
    return ZenohTransport.open(_settings(args, connect=_endpoints(args.connect)), timeout_s=10)


def make_pub(args: argparse.Namespace, key: str) -> Pub:
    if args.transport == "arpz":
        link = link_sizes(_endpoints(args.connect)).fragment_bytes
        return ArpzPub(_transport(args), key, qos_from_args(args), args.express, link)
    session = open_session(_settings(args, connect=_endpoints(args.connect)))
    if args.transport == "zenoh":
        return ZenohPub(session, key, args.express)
    return AdvancedPub(session, key, args.express, args.cache)


def make_sub(args: argparse.Namespace, key: str, on_payload: OnPayload) -> Sub:
    if args.transport == "arpz":
        return ArpzSub(_transport(args), key, qos_from_args(args), on_payload, args.inline)
    session = open_session(_settings(args, connect=_endpoints(args.connect)))
    if args.transport == "zenoh":
        return ZenohSub(session, key, on_payload)
    return AdvancedSub(session, key, on_payload)


class EndMarker:
    """The publisher's final count on ``{key}/perf/end``: the subscriber's "sent"."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.key = f"{args.key}/perf/end"
        self.transport = _transport(args)
        self.count: int | None = None

    def announce(self, count: int) -> None:
        for _ in range(5):
            self.transport.put(self.key, str(count).encode())
            time.sleep(0.05)

    def listen(self) -> None:
        def on_end(key: str, payload: bytes, attachment: bytes | None) -> None:
            with contextlib.suppress(ValueError):  # not ours: the highest seq stands in
                self.count = int(payload)

        self.transport.subscribe(self.key, on_end)

    def close(self) -> None:
        self.transport.close()


def _pace(args: argparse.Namespace) -> tuple[int, float]:
    if not args.count and not args.duration:
        raise SystemExit("give --count N or --duration S")
    return args.count, args.duration


def run_pub(args: argparse.Namespace) -> dict[str, Any]:
    count, duration = _pace(args)
    marker = EndMarker(args)
    pub = make_pub(args, args.key)
    try:
        if not pub.wait_matched(10.0):
            print(
                "arpz.perf pub: no subscriber matched within 10 s; publishing anyway",
                file=sys.stderr,
            )
        STOP.wait(args.warmup)
        make = payload_maker(args.size)
        seq = 0
        t0 = time.monotonic()
        cpu0 = time.process_time()
        period = 1.0 / args.rate if args.rate > 0 else 0.0
        while not STOP.is_set():
            if count and seq >= count:
                break
            if duration and time.monotonic() - t0 >= duration:
                break
            try:
                pub.put(make(seq + 1, time.time_ns()))
            except HistoryFullError:  # only raised once SIGINT/SIGTERM asked us to stop
                break
            seq += 1
            if period:
                delay = t0 + seq * period - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
        elapsed = time.monotonic() - t0
        cpu_s = time.process_time() - cpu0
        extra = pub.finish(args.linger)
        marker.announce(seq)
        return {
            "sent": seq,
            "elapsed_s": elapsed,
            "rate_msg_s": seq / elapsed if elapsed else 0.0,
            # CPU of the whole process (all threads) while publishing: stable on a shared host,
            # where throughput is not
            "cpu_s": cpu_s,
            "cpu_us_per_msg": 1e6 * cpu_s / seq if seq else 0.0,
            **extra,
        }
    finally:
        pub.close()
        marker.close()


def _receive(
    args: argparse.Namespace, rec: Recorder, sub: Sub, marker: EndMarker, t0: float
) -> None:
    """Wait until everything sent is received or reported lost, or idle, or time is up.

    The distinct seqs are counted incrementally (only what arrived since the last poll): a
    fresh set of everything received, 50 times a second, took the GIL from the receiving
    thread for longer and longer and slowed down the very throughput being measured."""
    seen: set[int] = set()
    counted = 0
    while not STOP.is_set():
        time.sleep(0.02)
        now = time.monotonic()
        if args.duration and now - t0 >= args.duration:
            return
        expected = marker.count or args.count
        arrived = len(rec)
        seen.update(rec.seqs[counted:arrived])
        counted = arrived
        if expected and arrived and len(seen) + sub.lost() >= expected:
            return
        if marker.count is not None and (
            not len(rec) or now - rec.arrival_s[-1] > args.idle_timeout
        ):
            return


def _report(
    args: argparse.Namespace,
    rec: Recorder,
    sent: int | None,
    lost: int,
    counters: dict[str, int],
    t0: float,
) -> dict[str, Any]:
    report = build_report(
        rec,
        transport=args.transport,
        key=args.key,
        size=args.size,
        rate_hz=args.rate,
        sent=sent,
        lost=lost,
        retransmissions=int(counters.get("retransmitted", 0)),
        nacks=int(counters.get("nacks", 0)),
        duration_s=time.monotonic() - t0,
    )
    if args.latency_out:
        with rec.lock:
            latency_us = np.frombuffer(rec.latency_ns, dtype=np.int64) / 1000.0
        with open(args.latency_out, "wb") as fh:  # a file object: np.save adds no ".npy"
            np.save(fh, latency_us)
    if report.foreign:
        print(
            f"arpz.perf: {report.foreign} payloads on {args.key} were not arpz.perf samples "
            "(published by something other than `python -m arpz.perf pub`?); not counted",
            file=sys.stderr,
        )
    result: dict[str, Any] = msgspec.to_builtins(report)
    return result


def run_sub(args: argparse.Namespace, *, key: str | None = None) -> dict[str, Any]:
    rec = Recorder()

    def on_payload(payload: bytes) -> None:
        rec.add_payload(payload, time.time_ns(), time.monotonic())

    marker = EndMarker(args)
    marker.listen()
    sub = make_sub(args, key or args.key, on_payload)
    t0 = time.monotonic()
    cpu0 = time.process_time()
    try:
        print("arpz.perf sub: ready", file=sys.stderr, flush=True)
        _receive(args, rec, sub, marker, t0)
        cpu_s = time.process_time() - cpu0
        lost = sub.lost()
        counters = sub.counters()
    finally:
        sub.close()
        marker.close()
    cpu = {"cpu_s": cpu_s, "cpu_us_per_msg": 1e6 * cpu_s / len(rec) if len(rec) else 0.0}
    return {**_report(args, rec, marker.count, lost, counters, t0), **cpu, "channel": counters}


def run_pong(args: argparse.Namespace) -> dict[str, Any]:
    """Echo every ping back, until stopped (or --duration)."""
    pub = make_pub(args, f"{args.key}/pong")
    echoed = [0]

    def echo(payload: bytes) -> None:
        pub.put(payload)
        echoed[0] += 1

    sub = make_sub(args, f"{args.key}/ping", echo)
    t0 = time.monotonic()
    try:
        print("arpz.perf pong: ready", file=sys.stderr, flush=True)
        while not STOP.is_set() and not (args.duration and time.monotonic() - t0 >= args.duration):
            time.sleep(0.05)
    finally:
        sub.close()
        pub.close()
    return {"echoed": echoed[0]}


def run_ping(args: argparse.Namespace) -> dict[str, Any]:
    count, duration = _pace(args)
    rec = Recorder()

    def on_pong(payload: bytes) -> None:
        rec.add_payload(payload, time.time_ns(), time.monotonic())

    sub = make_sub(args, f"{args.key}/pong", on_pong)
    pub = make_pub(args, f"{args.key}/ping")
    t0 = time.monotonic()
    seq = 0
    try:
        if not pub.wait_matched(10.0):
            print("arpz.perf ping: no pong matched within 10 s", file=sys.stderr)
        STOP.wait(max(0.5, args.warmup))  # the pong's return path matches too
        make = payload_maker(args.size)
        t0 = time.monotonic()
        period = 1.0 / args.rate if args.rate > 0 else 0.001
        while not STOP.is_set():
            if (count and seq >= count) or (duration and time.monotonic() - t0 >= duration):
                break
            seq += 1
            pub.put(make(seq, time.time_ns()))
            delay = t0 + seq * period - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        end = time.monotonic() + args.idle_timeout
        while len(rec) < seq and time.monotonic() < end and not STOP.is_set():
            time.sleep(0.01)
        lost = sub.lost()
        counters = sub.counters()
    finally:
        pub.close()
        sub.close()
    return {**_report(args, rec, seq, lost, counters, t0), "round_trip": True}


def run_router(args: argparse.Namespace) -> dict[str, Any]:
    settings = _settings(args, mode="router", listen=_endpoints(args.listen))
    with ZenohTransport.open(settings):
        print(f"arpz.perf router: listening on {args.listen}", file=sys.stderr, flush=True)
        t0 = time.monotonic()
        while not STOP.is_set() and not (args.duration and time.monotonic() - t0 >= args.duration):
            time.sleep(0.1)
    return {"router": args.listen}


def _check_writable(path: str | None, option: str) -> None:
    """Refuse an output file that cannot be written before the run, not after it."""
    if not path or path == JSON_TO_STDOUT:
        return
    try:
        with open(path, "ab"):
            pass
    except OSError as exc:
        raise ValueError(f"--{option.replace('_', '-')} {path}: {exc.strerror}") from exc


def _check_zenoh_config(path: str | None) -> None:
    """Refuse a Zenoh config that cannot be used before any session opens (exit 2)."""
    if path:
        load_zenoh_config(path, source="--zenoh-config")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    signal.signal(signal.SIGINT, _on_signal)
    signal.signal(signal.SIGTERM, _on_signal)
    try:
        _check_zenoh_config(args.zenoh_config)
    except ConfigError as exc:
        return fail(f"perf {args.command}", str(exc))
    if args.command in ("fleet", "fleet-worker"):
        return fleet.main(args)
    if args.command != "router" and args.size < HEADER.size:
        return fail("perf", f"--size must be at least {HEADER.size}")
    runner = {
        "router": run_router,
        "pub": run_pub,
        "sub": run_sub,
        "ping": run_ping,
        "pong": run_pong,
    }
    try:
        if args.command != "router":
            qos_from_args(args)  # a bad profile is refused before any session opens
            for option in ("json", "latency_out"):
                _check_writable(getattr(args, option, None), option)
        result = runner[args.command](args)
    except (ValueError, msgspec.ValidationError, TransportError) as exc:
        return fail(f"perf {args.command}", str(exc))
    text = json.dumps(result)
    print(text, flush=True)
    if getattr(args, "json", None) not in (None, JSON_TO_STDOUT):
        with open(args.json, "w") as fh:
            fh.write(json.dumps(result, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
