"""The CEDDP's channel ingest, in-process: CPU a sample through the reliable channel's two
callbacks, one call of ``on_data`` a sample (with its ``DataInfo``) against a writer's run handed
over whole (``on_data_run``, what the CEDDP uses), on the same payloads as
``benchmarks/ceddp_ingest.py`` (3 robots x 6 topics, values repeating, so cache control has hits
and misses) in runs of ``--run`` samples of one topic. A real ``CeddpServer`` with its dashboard
and planner behind a router session; no publishers, no channel protocol: only what the CEDDP
does with a delivered sample. Alternating rounds, the median printed.

    python benchmarks/investigations/ingest_cost.py [--runs 200] [--run 64] [--rounds 3]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from arpz.core.messages import Sample, encode
from arpz.core.protocol.events import DataInfo
from benchmarks.ceddp_ingest import ceddp_server  # the same CEDDP as the ingest benchmark

TOPICS = [
    (f"robot{r}", name)
    for r in range(1, 4)
    for name in ("lidar", "imu", "dht11", "pir", "light", "flame")
]


def runs_of(count: int, size: int) -> list[tuple[str, list[bytes]]]:
    """``count`` runs of ``size`` samples, the topics in turn, each topic's seqs from 1."""
    seqs = dict.fromkeys(TOPICS, 0)
    out = []
    for i in range(count):
        robot, name = topic = TOPICS[i % len(TOPICS)]
        payloads = []
        for _ in range(size):
            seqs[topic] += 1
            step = seqs[topic] * len(TOPICS)
            value = {
                "pir": "detect" if (step // 400) % 2 else "not detect",
                "light": "light",
                "flame": False,
            }.get(name, float((step // 90) % 7))
            payloads.append(encode(Sample(f"{robot}:p0", seqs[topic], time.time_ns(), value)))
        out.append((f"arpz/bench/robot/{robot}/sensor/{name}", payloads))
    return out


def cpu_us_a_sample(whole: bool, runs: list[tuple[str, list[bytes]]], workdir: Path) -> float:
    with ceddp_server(workdir, "channel") as (server, _endpoint):
        intake = server.intake
        total = sum(len(payloads) for _, payloads in runs)
        cpu0 = time.thread_time()
        if whole:
            for key, payloads in runs:
                intake._on_channel_run(key, payloads)
        else:  # the per-sample path it replaced: a DataInfo, a call, the lock, a clock read
            for key, payloads in runs:
                for seq, payload in enumerate(payloads, 1):
                    info = DataInfo(key, "w", seq, 0)
                    intake._ingest_one(info.key, payload, large=False)
        cpu_s = time.thread_time() - cpu0
        server.shutdown()
    if intake.processed != total:
        raise RuntimeError(f"ingested {intake.processed} of {total}")
    return cpu_s / total * 1e6


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=200 * len(TOPICS))
    parser.add_argument("--run", type=int, default=64, help="samples a run (a batch)")
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    if args.runs < 1 or args.run < 1 or args.rounds < 1:
        parser.error("--runs, --run and --rounds must be at least 1")
    runs = runs_of(args.runs, args.run)
    one: list[float] = []
    whole: list[float] = []
    with tempfile.TemporaryDirectory() as tmp:
        for round_ in range(1, args.rounds + 1):
            one.append(cpu_us_a_sample(False, runs, Path(tmp)))
            whole.append(cpu_us_a_sample(True, runs, Path(tmp)))
            print(
                f"round {round_}/{args.rounds}: a call a sample {one[-1]:.2f} us, "
                f"runs whole {whole[-1]:.2f} us a sample",
                flush=True,
            )
    a, b = statistics.median(one), statistics.median(whole)
    print(
        f"{len(runs) * args.run} samples in runs of {args.run}, median of {args.rounds}: "
        f"a call a sample {a:.2f} us, runs whole {b:.2f} us ({b / a:.2f}x)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
