"""CEDDP ingest throughput against a raw zenoh-python subscriber, on the same traffic, in one run.

Both subscribers live in the router's own session (where the CEDDP's subscriber lives), fed by
the same publisher processes sending the same pre-encoded samples (3 robots x 6 topics, values
repeating as the simulated sensors do, so cache control has both hits and misses):

- raw: a callback that only counts (the ceiling for a Python subscriber);
- arpz raw: the real ``CeddpServer`` with its Rerun dashboard: Zenoh FIFO -> worker -> decode ->
  sequence check -> latency -> cache control -> planner;
- arpz channel: the same server behind its reliable-channel fleet Reader, fed by
  ``arpz.channel`` Writers (KEEP_ALL, batching; bulk publishers, see BULK_BATCH_DELAY_S);
- arpz channel-unbatched: the same with one sample per message (``batch_max_samples = 1``), the
  CEDDP's per-message cost, as a fleet of robots at 100 Hz per topic makes it pay.

Throughput = samples / (time the last one was processed - time publishing started). Each arpz
run also prints the CPU a sample of the CEDDP (``ceddp_us``) and of the publishers
(``publishers_us``): on 2 shared cores a costly publisher lowers the rate the CEDDP is offered,
and ``dup``, samples the CEDDP received twice (resends of what it NACKed). Rounds
alternate raw/arpz so drift on a shared machine hits both. Targets: the raw path >= 0.5x raw
(issue 2), the reliable channel >= 0.5x raw (issue 17).

    python benchmarks/ceddp_ingest.py [--samples 200000] [--rounds 3] [--publishers 2]
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from functools import partial
from pathlib import Path

from arpz.ceddp.dashboard import Dashboard
from arpz.ceddp.server import CeddpServer
from arpz.channel import QOS_RELIABLE_ALL
from arpz.core.config import CeddpConfig
from arpz.core.transport import SessionSettings
from arpz.perf.zenoh_baselines import ZenohCounter, open_session
from arpz.tools.launch import free_port
from arpz.transport.zenoh import ZenohTransport

#: progress lines, printed as they come
SAY = partial(print, flush=True)

ROOT = Path(__file__).resolve().parents[1]

#: The channel publishers' batch delay (``--publisher-batch-delay-ms``). The benchmark measures
#: the CEDDP, so its publishers must not set the rate: each publisher process here holds 18
#: writers written flat out, and with the default delay (0.5 ms) each of them ticks every 0.5 ms
#: while it streams, so the publishers, not the CEDDP, set the rate (``--publisher-batch-delay-ms
#: 0.5`` against the default: benchmarks/RESULTS.md). A robot's writers at 100 Hz never stream.
BULK_BATCH_DELAY_S = 0.02

PUBLISHER = r"""
import sys, time
from arpz.core.messages import Sample, encode
from arpz.core.transport import SessionSettings
from arpz.transport.zenoh import ZenohTransport

endpoint, count, index, path = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
t = ZenohTransport.open(SessionSettings(mode="client", connect=[endpoint]), timeout_s=10)
topics = [(f"robot{r}", name) for r in range(1, 4)
          for name in ("lidar", "imu", "dht11", "pir", "light", "flame")]
keys = [f"arpz/bench/robot/{r}/sensor/{n}" for r, n in topics]
if path.startswith("channel"):
    import msgspec
    from arpz.channel import QOS_RELIABLE_ALL, Writer
    # bulk publishers (see BULK_BATCH_DELAY_S); "channel-unbatched": one sample per message,
    # what a fleet of robots at 100 Hz per topic sends
    # written flat out, a publisher runs ahead of the CEDDP by the whole KEEP_ALL history and
    # then waits for acknowledgements as long as the CEDDP takes to read its backlog: with the
    # profile's 0.1 s a write failed (HistoryFullError) in runs of 600 000 samples
    qos = msgspec.structs.replace(
        QOS_RELIABLE_ALL, batch_max_delay_s=float(sys.argv[5]), max_blocking_time_s=60.0
    )
    if path == "channel-unbatched":
        qos = msgspec.structs.replace(qos, batch_max_samples=1)
    writers = [Writer(t, key, qos) for key in keys]
    deadline = time.monotonic() + 20
    while not all(w.matched_count for w in writers) and time.monotonic() < deadline:
        time.sleep(0.01)
    puts = [w.write for w in writers]
else:
    puts = [t.publisher(key).put for key in keys]
payloads = []
for i in range(count):
    r, n = topics[i % len(topics)]
    value = {"pir": "detect" if (i // 400) % 2 else "not detect", "light": "light",
             "flame": False}.get(n, float((i // 90) % 7))
    payloads.append(encode(Sample(f"{r}:p{index}", i // len(topics) + 1, time.time_ns(), value)))
time.sleep(0.5)
cpu0 = time.process_time()
print("go", flush=True)
for i, payload in enumerate(payloads):
    puts[i % len(puts)](payload)
print("done", flush=True)
sys.stdin.read()
if path.startswith("channel"):
    for w in writers:
        w.close()
t.close()
print(f"cpu {time.process_time() - cpu0}", flush=True)
"""


def start_publishers(
    endpoint: str,
    per_publisher: int,
    publishers: int,
    path: str = "raw",
    batch_delay_s: float = BULK_BATCH_DELAY_S,
) -> tuple[list[subprocess.Popen[str]], float]:
    procs = [
        subprocess.Popen(
            [
                sys.executable,
                "-c",
                PUBLISHER,
                endpoint,
                str(per_publisher),
                str(i),
                path,
                str(batch_delay_s),
            ],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            cwd=ROOT,
        )
        for i in range(publishers)
    ]
    for proc in procs:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        if line.strip() != "go":
            raise RuntimeError(f"publisher failed to start: {line!r}")
    return procs, time.perf_counter()


def stop_publishers(procs: list[subprocess.Popen[str]]) -> float:
    """Stop the publishers; the CPU seconds they spent from "go" to their end."""
    cpu_s = 0.0
    for proc in procs:
        assert proc.stdin is not None and proc.stdout is not None
        proc.stdin.close()
        for line in proc.stdout.read().splitlines():
            if line.startswith("cpu "):
                cpu_s += float(line.split()[1])
        proc.wait(timeout=30)
        proc.stdout.close()
    return cpu_s


def wait_count(
    get: Callable[[], int], total: int, timeout_s: float, procs: list[subprocess.Popen[str]]
) -> float:
    """When ``total`` samples were processed; fails at once if a publisher died (its traceback
    is on stderr), rather than waiting out the timeout for samples that will never come."""
    deadline = time.perf_counter() + timeout_s
    while time.perf_counter() < deadline:
        if get() >= total:
            return time.perf_counter()
        dead = [p.returncode for p in procs if p.poll() is not None]
        if dead:
            raise RuntimeError(f"a publisher exited (code {dead[0]}) after {get()} of {total}")
        time.sleep(0.001)
    raise RuntimeError(f"only {get()} of {total} samples arrived within {timeout_s} s")


def run_raw(total: int, publishers: int) -> tuple[float, float]:
    """A plain zenoh-python router session whose subscriber callback only counts: samples/s,
    and this process's CPU a sample (us) while it took them in, as ``run_arpz``'s CEDDP's."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = open_session(SessionSettings(mode="router", listen=[endpoint]))
    try:
        sub = ZenohCounter(session, "arpz/bench/robot/*/sensor/*")
        try:
            procs, t0 = start_publishers(endpoint, total // publishers, publishers)
            cpu0 = time.process_time()
            t1 = wait_count(lambda: sub.count, total, 120, procs)
            cpu_s = time.process_time() - cpu0
            stop_publishers(procs)
        finally:
            sub.close()
    finally:
        session.close()  # type: ignore[no-untyped-call]
    return total / (t1 - t0), cpu_s / total * 1e6


@contextlib.contextmanager
def ceddp_server(workdir: Path, path: str) -> Iterator[tuple[CeddpServer, str]]:
    """The real ``CeddpServer`` and its Rerun dashboard in a router session of this process
    (the CEDDP is this process), on the channel or the raw path; yields it started, with the
    router's endpoint. The caller shuts it down (its summary is the run's counts)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = CeddpConfig(
        fleet="bench",
        listen=[endpoint],
        rrd=str(workdir / f"bench-{path}.rrd"),
        reliability="channel" if path.startswith("channel") else "none",
        sensor_qos=QOS_RELIABLE_ALL,
    )
    router = ZenohTransport.open(SessionSettings(mode="router", listen=[endpoint]))
    dashboard = Dashboard(config.rrd)
    try:
        server = CeddpServer(config, router, dashboard=dashboard)
        server.start()
        yield server, endpoint
    finally:
        router.close()
        dashboard.close()


def run_arpz(
    total: int, publishers: int, workdir: Path, path: str, batch_delay_s: float
) -> tuple[float, dict[str, int]]:
    with ceddp_server(workdir, path) as (server, endpoint):
        procs, t0 = start_publishers(endpoint, total // publishers, publishers, path, batch_delay_s)
        cpu0 = time.process_time()  # this process is the CEDDP (and a thread polling its count)
        t1 = wait_count(lambda: server.processed, total, 300, procs)
        ceddp_cpu_s = time.process_time() - cpu0
        publishers_cpu_s = stop_publishers(procs)
        # samples that came twice: resends of what the CEDDP had asked for again (spurious
        # NACKs, since nothing is lost on loopback TCP)
        reader = server.intake.reader
        duplicates = reader.stats().duplicates if reader is not None else 0
        summary = server.shutdown()
    hits = sum(t["cc_discarded"] for r in summary["robots"].values() for t in r["topics"].values())
    lost = sum(r["lost"] for r in summary["robots"].values())
    info = {
        "processed": server.processed,
        "cc_discarded": hits,
        "lost": lost,
        "dup": duplicates,
        # CPU a sample, microseconds: the CEDDP while it took the samples in, the publishers
        # from their start to their end (what they cost a sample, acknowledgements included)
        "ceddp_us": round(ceddp_cpu_s / total * 1e6, 2),
        "publishers_us": round(publishers_cpu_s / total * 1e6, 1),
    }
    return total / (t1 - t0), info


def measure(
    total: int,
    publishers: int,
    paths: list[str],
    rounds: int,
    batch_delay_s: float = BULK_BATCH_DELAY_S,
    log: Callable[[str], object] = SAY,
) -> tuple[list[float], dict[str, list[float]], dict[str, list[float]]]:
    """Samples/s a round, the raw subscriber's and the CEDDP's on each path, and the CPU a
    sample (us) of each ("raw" and the paths). Each round runs raw, then every path, so a
    round's figures share a window of the host."""
    raw_rates: list[float] = []
    arpz_rates: dict[str, list[float]] = {p: [] for p in paths}
    cpu_us: dict[str, list[float]] = {p: [] for p in ["raw", *paths]}
    with tempfile.TemporaryDirectory() as tmp:
        for round_ in range(1, rounds + 1):
            raw, raw_cpu = run_raw(total, publishers)
            raw_rates.append(raw)
            cpu_us["raw"].append(raw_cpu)
            line = f"round {round_}/{rounds}: raw {raw:,.0f} samples/s ({raw_cpu:.2f} us CPU)"
            for path in paths:
                rate, info = run_arpz(total, publishers, Path(tmp), path, batch_delay_s)
                arpz_rates[path].append(rate)
                cpu_us[path].append(info["ceddp_us"])
                line += f"; arpz {path} {rate:,.0f} samples/s ({rate / raw:.2f}x) {info}"
            log(line)
    return raw_rates, arpz_rates, cpu_us


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--samples", type=int, default=200_000)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--publishers", type=int, default=2)
    parser.add_argument(
        "--paths",
        default="raw,channel,channel-unbatched",
        help="CEDDP ingest paths to measure: raw (plain Zenoh samples), channel "
        "(arpz.channel KEEP_ALL writers, batching -> the CEDDP's fleet reader), "
        "channel-unbatched (one sample per message)",
    )
    parser.add_argument(
        "--publisher-batch-delay-ms",
        type=float,
        default=BULK_BATCH_DELAY_S * 1000,
        help="the channel publishers' batch_max_delay_s in ms (default %(default)g; the "
        "channel's own default is 0.5)",
    )
    args = parser.parse_args()
    paths = [p for p in args.paths.split(",") if p]
    total = args.samples // args.publishers * args.publishers
    raw_rates, arpz_rates, _ = measure(
        total, args.publishers, paths, args.rounds, args.publisher_batch_delay_ms / 1000
    )
    raw_m = statistics.median(raw_rates)
    print(f"\n{total} samples from {args.publishers} publisher processes, median of {args.rounds}:")
    print(f"  raw zenoh-python subscriber      : {raw_m:>10,.0f} samples/s")
    for path in paths:
        median = statistics.median(arpz_rates[path])
        # each round's ratio pairs runs made back to back; the ratio of the medians may pair a
        # fast round's raw with a slow round's arpz on a shared host. Both are printed
        paired = statistics.median(a / r for a, r in zip(arpz_rates[path], raw_rates, strict=True))
        print(
            f"  arpz CEDDP ingest, {path:<13} : {median:>10,.0f} samples/s "
            f"= {median / raw_m:.2f}x raw (target >= 0.5x); median of the rounds' ratios "
            f"{paired:.2f}x"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
