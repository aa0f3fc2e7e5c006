"""Camera frames over a lossy WiFi-like link: arpz FrameWriter (KEEP_ALL) vs raw Zenoh vs Advanced.

One run, one table. Per cell a fresh router (UDP + TCP) and, for UDP cells, a fresh
``python -m arpz.netem --per-frame`` proxy losing L % of 1500-byte frames each way (a datagram of k
frames is lost with probability 1 - (1 - L)^k); the publisher's session connects through the
proxy, the subscriber's over TCP. Every session turns Zenoh's shared memory off (otherwise a large
payload bypasses the link on one host) and the publisher's sets ``transport/link/tx/batch_size``
to 1472 bytes, so that no datagram exceeds one frame (same link for all three transports). The
proxy's byte counters must show at least the payload bytes of the frames delivered leaving the
proxy towards the router: the run fails loudly otherwise (and prints what entered the proxy and
what the kernel dropped before the proxy read it, ``rx_overflow``, which is not emulated loss).

Also at 0 % loss over TCP (publisher straight to the router): arpz's goodput against raw
Zenoh's, at the frame rate and flat out (``--flat-frames`` frames back to back), with the
default 1280-byte fragments and with 32 and 60 KiB ones (``--tcp-fragments``; Zenoh's TCP batches
are 64 KiB, so nothing is cut again there).

    python benchmarks/large_messages.py --frames 30 --loss 0 1 10

Frames are random bytes (640x480 RGB = 921 600 by default, ``--size``), stamped with the send
time: latency is stamp to complete frame at the subscriber (same host, same clock); goodput is
the payload bytes delivered over the time from the first write to the last delivery.
"""

from __future__ import annotations

import argparse
import random
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from typing import Any

from arpz.channel import FrameInfo, FrameReader, FrameWriter, HistoryPolicy, QosProfile
from arpz.core.endpoints import frame_fragment_bytes
from arpz.core.percentiles import percentile
from arpz.core.protocol.fragments import DEFAULT_FRAGMENT_BYTES
from arpz.core.transport import SessionSettings
from arpz.netem.process import netem_process
from arpz.netem.proxy import kernel_drops
from arpz.perf import zenoh_baselines as zb
from arpz.tools.launch import free_port
from arpz.transport.zenoh import ZenohTransport

NO_SHM: dict[str, object] = {"transport/shared_memory/enabled": False}
#: the largest UDP payload of one 1500-byte frame (1500 - 20 IP - 8 UDP)
ONE_FRAME_BATCH = 1472
KEY = "bench/camera/front"
STAMP = struct.Struct("!q")  # raw Zenoh frames carry their send time in their first 8 bytes


@dataclass
class Cell:
    link: str
    loss: float
    transport: str
    rate_hz: float
    fragment_bytes: int = DEFAULT_FRAGMENT_BYTES
    delivered: int = 0
    intact: int = 0
    latencies_ms: list[float] = field(default_factory=list)
    goodput_mbs: float = 0.0
    proxy: dict[str, Any] | None = None
    extra: str = ""


class Received:
    """What the subscriber got: frames, how many intact, latencies, time of the last one."""

    def __init__(self, payloads: list[bytes]) -> None:
        self.payloads = payloads
        #: raw Zenoh frames carry their stamp in their first bytes: compare the rest
        self.tails = {p[STAMP.size :] for p in payloads}
        self.lock = threading.Lock()
        self.count = self.intact = 0
        self.latencies_ms: list[float] = []
        self.last_at = 0.0

    def frame(self, payload: bytes, stamp_ns: int | None, index: int | None) -> None:
        """``stamp_ns`` and ``index`` from arpz's FrameInfo; None for raw Zenoh."""
        now_ns, now = time.time_ns(), time.monotonic()
        if stamp_ns is None:
            stamp_ns = STAMP.unpack_from(payload)[0]
            intact = payload[STAMP.size :] in self.tails
        else:
            intact = index is not None and payload == self.payloads[index]
        with self.lock:
            self.count += 1
            self.intact += intact
            self.latencies_ms.append((now_ns - stamp_ns) / 1e6)
            self.last_at = now


@contextmanager
def link(
    kind: str, loss: float, seed: int, rate_mbps: float
) -> Iterator[tuple[str, str, Callable[[], Any]]]:
    """A router and (UDP) a netem proxy before it; yields (publisher endpoint, subscriber
    endpoint, stop() -> the proxy's counters or None)."""
    udp, tcp = free_port(socket.SOCK_DGRAM), free_port()
    listen = [f"udp/127.0.0.1:{udp}", f"tcp/127.0.0.1:{tcp}"]
    with ExitStack() as stack:
        stack.enter_context(
            ZenohTransport.open(SessionSettings(mode="router", listen=listen, extra=NO_SHM))
        )
        if kind == "tcp":
            yield f"tcp/127.0.0.1:{tcp}", f"tcp/127.0.0.1:{tcp}", lambda: None
            return
        proxy = free_port(socket.SOCK_DGRAM)
        netem = stack.enter_context(
            netem_process(
                f"udp/127.0.0.1:{proxy}",
                f"udp/127.0.0.1:{udp}",
                *("--loss", str(loss), "--per-frame", "--clean-s", "2", "--seed", str(seed)),
                *("--rate-kbps", str(rate_mbps * 1000)),
            )
        )

        def stop() -> Any:
            report = netem.stop()
            if report is not None:  # what the router's own socket lost to bursts
                report["router_rx_overflow"] = kernel_drops(port=udp)
            return report

        yield f"udp/127.0.0.1:{proxy}", f"tcp/127.0.0.1:{tcp}", stop


def settings(connect: str, batch: bool) -> SessionSettings:
    extra = dict(NO_SHM)
    if batch:
        extra["transport/link/tx/batch_size"] = ONE_FRAME_BATCH
    return SessionSettings(connect=[connect], extra=extra)


def send(cell: Cell, payloads: list[bytes], write: Callable[[int], object], got: Received) -> float:
    """Write the frames at the cell's rate (0: back to back); returns the start time."""
    t0 = time.monotonic()
    for i in range(len(payloads)):
        write(i)
        if cell.rate_hz:
            time.sleep(max(0.0, t0 + (i + 1) / cell.rate_hz - time.monotonic()))
    return t0


def drain(got: Received, n: int, idle_s: float, cap_s: float) -> None:
    """Wait until every frame arrived, or none for ``idle_s`` (since the last one, or since
    the drain began if none came), or ``cap_s`` in all."""
    start = time.monotonic()
    end = start + cap_s
    while time.monotonic() < end:
        with got.lock:
            if got.count >= n:
                return
            last = got.last_at
        if time.monotonic() - (last or start) > idle_s:
            return
        time.sleep(0.05)


def run_arpz(cell: Cell, pub: str, sub: str, payloads: list[bytes], clean_until: float) -> Received:
    got = Received(payloads)
    qos = QosProfile(history=HistoryPolicy.KEEP_ALL, max_samples=8, max_blocking_time_s=5.0)
    size = len(payloads[0])

    def on_frame(payload: bytes, info: FrameInfo) -> None:
        got.frame(payload, info.stamp_ns, info.frame_id - 1)

    frag = cell.fragment_bytes
    with (
        ZenohTransport.open(settings(sub, False), timeout_s=5) as b,
        ZenohTransport.open(settings(pub, cell.link == "udp"), timeout_s=5) as a,
        FrameReader(b, KEY, qos, on_frame, max_frame_bytes=size, fragment_bytes=frag) as reader,
        FrameWriter(a, KEY, qos, max_frame_bytes=size, fragment_bytes=frag) as writer,
    ):
        wait(lambda: writer.matched_count == 1 and writer.wait_for_acknowledgments(0.05), 10)
        time.sleep(max(0.0, clean_until - time.monotonic()))
        t0 = send(cell, payloads, lambda i: writer.write(payloads[i]), got)
        drain(got, len(payloads), idle_s=10.0, cap_s=60.0)
        cell.goodput_mbs = goodput(got, t0)
        ws, rs = writer.stats(), reader.stats()
        f = rs.frames
        cell.extra = (
            f"fragments {ws.fragments_sent} resent {ws.channel.retransmitted} (seqs NACKed "
            f"{ws.channel.nacks}, held off {ws.channel.resends_held_off}, duplicates at the "
            f"reader {rs.channel.duplicates}); frames delivered {f.frames_delivered} dropped "
            f"{f.frames_dropped_incomplete + f.frames_dropped_over_limit} missing "
            f"{f.frames_missing} in assembly {f.in_assembly}; fragments lost {rs.channel.lost}"
        )
    return got


def run_zenoh(
    cell: Cell, pub: str, sub: str, payloads: list[bytes], clean_until: float
) -> Received:
    got = Received(payloads)

    def on_payload(payload: bytes) -> None:
        got.frame(payload, None, None)

    advanced = cell.transport == "advanced"
    sub_session = zb.open_session(settings(sub, False))
    receiver: zb.ZenohSub | zb.AdvancedSub = (
        zb.AdvancedSub(sub_session, KEY, on_payload)
        if advanced
        else zb.ZenohSub(sub_session, KEY, on_payload)
    )
    try:
        pub_session = zb.open_session(settings(pub, cell.link == "udp"))
        sender: zb.ZenohPub = (
            zb.AdvancedPub(pub_session, KEY, False, cache=len(payloads))
            if advanced
            else zb.ZenohPub(pub_session, KEY, False)
        )
        try:
            sender.wait_matched(10)
            time.sleep(max(0.0, clean_until - time.monotonic()))

            def write(i: int) -> None:
                stamped = bytearray(payloads[i])
                STAMP.pack_into(stamped, 0, time.time_ns())
                sender.put(bytes(stamped))

            t0 = send(cell, payloads, write, got)
            drain(got, len(payloads), idle_s=5.0 if advanced else 2.0, cap_s=30.0)
            cell.goodput_mbs = goodput(got, t0)
            if advanced:
                cell.extra = f"reported missed {receiver.lost()}"
        finally:
            sender.close()
    finally:
        receiver.close()
    return got


def wait(predicate: Callable[[], bool], timeout_s: float) -> None:
    end = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > end:
            raise SystemExit("FAILED: the writer never matched its reader")
        time.sleep(0.05)


def goodput(got: Received, t0: float) -> float:
    with got.lock:
        if not got.count:
            return 0.0
        return got.intact * len(got.payloads[0]) / max(got.last_at - t0, 1e-9) / 1e6


def check_link(cell: Cell, delivered_bytes: int) -> None:
    """The payload delivered must have crossed the emulated link, not Zenoh's shared memory."""
    report = cell.proxy
    if report is None:
        raise SystemExit(f"FAILED: no counters from the netem proxy for {cell}")
    up_out = report["up"]["bytes_out"]
    if up_out < delivered_bytes:
        raise SystemExit(
            f"FAILED: {cell.transport} at {cell.loss:g} %: the proxy forwarded {up_out} bytes "
            f"from the publisher, but {delivered_bytes} payload bytes were delivered: the "
            "payload did not cross the emulated link (shared memory on?)"
        )


def row(cell: Cell, n: int, base: Cell | None) -> str:
    p50 = percentile(cell.latencies_ms, 50)
    p99 = percentile(cell.latencies_ms, 99)
    ratio = f"{cell.goodput_mbs / base.goodput_mbs:.2f}x" if base and base.goodput_mbs else "-"
    link_mb = (
        f"{cell.proxy['up']['bytes_out'] / 1e6:.1f} / {cell.proxy['up']['largest_datagram']}"
        if cell.proxy
        else "-"
    )
    rate = f"{cell.rate_hz:g} Hz" if cell.rate_hz else "flat out"
    name = cell.transport
    if cell.transport == "arpz" and cell.fragment_bytes != DEFAULT_FRAGMENT_BYTES:
        name += f" ({cell.fragment_bytes} B fragments)"
    return (
        f"| {cell.link} | {cell.loss:g} % | {rate} | {name} | {cell.delivered}/{n} "
        f"({cell.intact} intact) | {fmt(p50)} | {fmt(p99)} | {cell.goodput_mbs:.2f} | {ratio} "
        f"| {link_mb} |"
    )


def fmt(value: float | None) -> str:
    return "-" if value is None else f"{value:.0f}"


def run_cell(cell: Cell, payloads: list[bytes], seed: int, rate_mbps: float = 0.0) -> Cell:
    print(f"... {cell.link} {cell.loss:g} % {cell.transport} {cell.rate_hz:g} Hz", flush=True)
    runner = run_arpz if cell.transport == "arpz" else run_zenoh
    with link(cell.link, cell.loss, seed, rate_mbps) as (pub, sub, stop):
        clean_until = time.monotonic() + (2.0 if cell.link == "udp" else 0.0)
        got = runner(cell, pub, sub, payloads, clean_until)
        cell.proxy = stop()
    cell.delivered, cell.intact, cell.latencies_ms = got.count, got.intact, got.latencies_ms
    size = len(payloads[0])
    if cell.link == "udp":
        check_link(cell, cell.intact * size)
        assert cell.proxy is not None
        up = cell.proxy["up"]
        print(
            f"    link up: {up.get('bytes_in')} bytes in, {up.get('bytes_out')} out "
            f"(payload written {len(payloads) * size}, delivered {cell.intact * size}), "
            f"dropped {up.get('dropped')} of {up.get('received')} datagrams, largest "
            f"{up.get('largest_datagram')} B; kernel overflow at the proxy "
            f"{up.get('rx_overflow')}, at the router {cell.proxy.get('router_rx_overflow')}",
            flush=True,
        )
    print(f"    delivered {cell.delivered}, intact {cell.intact}; {cell.extra}", flush=True)
    return cell


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=30, help="frames per cell")
    ap.add_argument("--size", type=int, default=921_600, help="bytes per frame")
    ap.add_argument("--rate", type=float, default=10.0, help="frames per second")
    ap.add_argument(
        "--loss", type=float, nargs="*", default=[0.0, 1.0, 10.0], help="none: TCP cells only"
    )
    ap.add_argument("--no-tcp", action="store_true", help="skip the TCP goodput cells")
    ap.add_argument(
        "--flat-frames",
        type=int,
        default=100,
        help="frames of the flat-out TCP cells (30 back to back last under 0.1 s: too short)",
    )
    ap.add_argument(
        "--tcp-fragments",
        type=int,
        nargs="+",
        default=[DEFAULT_FRAGMENT_BYTES, 32 * 1024, 60 * 1024],
        help="arpz fragment sizes over TCP (Zenoh's TCP batch is 64 KiB)",
    )
    ap.add_argument(
        "--link-mbps",
        type=float,
        default=0.0,
        help="bandwidth of the emulated link (0: unlimited); a radio spaces the datagrams of a "
        "burst, loopback does not, and the router's socket overflows on an unpaced burst",
    )
    args = ap.parse_args()
    rng = random.Random(7)
    payloads = [rng.randbytes(args.size) for _ in range(args.frames)]
    n = args.frames
    rows: list[str] = []
    verdicts: list[str] = []
    for i, loss in enumerate(args.loss):
        cells = {
            t: run_cell(Cell("udp", loss, t, args.rate), payloads, 11 + i, args.link_mbps)
            for t in ("zenoh", "advanced", "arpz")
        }
        for t in ("arpz", "zenoh", "advanced"):
            rows.append(row(cells[t], n, cells["zenoh"] if t != "zenoh" else None))
            print(rows[-1], flush=True)
        if loss > 0:
            a = cells["arpz"]
            ok = a.intact == n
            verdicts.append(
                f"{'met' if ok else 'NOT MET'}: at {loss:g} % loss per frame arpz KEEP_ALL "
                f"delivered {a.intact} of {n} frames intact"
            )
    if not args.no_tcp:
        flat = [rng.randbytes(args.size) for _ in range(args.flat_frames)]
        for rate, frames in ((args.rate, payloads), (0.0, flat)):
            base = run_cell(Cell("tcp", 0.0, "zenoh", rate), frames, seed=0)
            rows.append(row(base, len(frames), None))
            print(rows[-1], flush=True)
            for fragment in args.tcp_fragments:
                cell = run_cell(Cell("tcp", 0.0, "arpz", rate, fragment), frames, seed=0)
                rows.append(row(cell, len(frames), base))
                print(rows[-1], flush=True)
                ratio = cell.goodput_mbs / base.goodput_mbs if base.goodput_mbs else 0.0
                # the size a robot connecting by TCP picks by itself (frame_fragment_bytes)
                own = fragment == frame_fragment_bytes(["tcp/127.0.0.1:7447"])
                verdicts.append(
                    f"{'met' if ratio >= 0.8 else 'NOT MET'}: TCP 0 % "
                    f"{'flat out' if not rate else f'{rate:g} Hz'}, {fragment} B fragments"
                    f"{' (a TCP robot default)' if own else ''}: "
                    f"arpz goodput {cell.goodput_mbs:.1f} MB/s = {ratio:.2f}x raw Zenoh's "
                    f"{base.goodput_mbs:.1f} MB/s (target >= 0.8x)"
                )
    print()
    bandwidth = f"{args.link_mbps:g} Mb/s" if args.link_mbps else "unlimited"
    print(
        f"{n} frames of {args.size} random bytes per cell ({args.flat_frames} flat out); "
        f"UDP link {bandwidth}; "
        "latency = send stamp to complete "
        "frame; goodput = intact payload bytes / (first write to last delivery); link MB = "
        "payload and headers the proxy forwarded from the publisher, with its largest datagram"
    )
    print()
    print(
        "| link | loss per frame | rate | transport | frames delivered | p50 ms | p99 ms "
        "| goodput MB/s | vs raw Zenoh | link MB / largest datagram B |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    print()
    print("\n".join(verdicts))
    return 0


if __name__ == "__main__":
    sys.exit(main())
