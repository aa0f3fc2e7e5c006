"""``python -m arpz.perf`` as separate processes through a router process."""

from __future__ import annotations

import contextlib
import json
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from arpz.channel import Writer
from arpz.core.protocol.qos import HistoryPolicy, QosProfile
from arpz.perf.harness import child, free_port, perf_router, pingpong, pubsub
from arpz.perf.report import make_payload
from tests.support import client, wait_until

pytestmark = pytest.mark.integration


@pytest.mark.parametrize(
    ("transport", "extra"),
    [("arpz", ()), ("arpz", ("--batch", "16")), ("zenoh", ()), ("advanced", ())],
)
def test_pub_sub_report_counts_every_sample(transport: str, extra: tuple[str, ...]) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with perf_router(endpoint):
        pub, report = pubsub(
            transport=transport,
            pub_connect=endpoint,
            sub_connect=endpoint,
            count=2000,
            rate_hz=4000,
            extra=extra,
        )
    assert pub["sent"] == 2000
    assert (report["sent"], report["received"], report["lost"], report["unaccounted"]) == (
        2000,
        2000,
        0,
        0,
    )
    assert report["duplicates"] == 0 and report["out_of_order"] == 0
    lat = report["latency_us"]
    assert 0 < lat["min"] <= lat["p50"] <= lat["p90"] <= lat["p99"] <= lat["max"]
    assert report["throughput_msg_s"] > 500
    if transport == "arpz":
        assert report["channel"]["delivered"] == 2000 and pub["acknowledged"] is True


def test_ping_pong_measures_round_trips_for_arpz(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    out = tmp_path / "rtt.npy"
    with perf_router(endpoint):
        report = pingpong(
            transport="arpz",
            connect=endpoint,
            count=300,
            rate_hz=500,
            extra=["--express", "--latency-out", str(out)],
        )
    assert report["received"] == 300 and report["round_trip"] is True
    assert report["latency_us"]["p50"] > 0
    latency_us = np.load(out)  # every round trip, as the report's percentiles summarise them
    assert len(latency_us) == 300
    assert latency_us.min() == pytest.approx(report["latency_us"]["min"])
    assert latency_us.max() == pytest.approx(report["latency_us"]["max"])


def test_sub_writes_its_json_report_on_sigint_and_qos_flags_are_validated(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    out = tmp_path / "report.json"
    argv = [
        sys.executable,
        "-m",
        "arpz.perf",
        "sub",
        "--connect",
        endpoint,
        "--key",
        "perf/x",
        "--deadline-ms",
        "100",
        "--json",
        str(out),
    ]
    with perf_router(endpoint), child(argv, ready="ready") as sub:
        time.sleep(0.2)
        sub.send_signal(signal.SIGINT)
        assert sub.wait(timeout=15) == 0
    report = json.loads(out.read_text())
    assert report["received"] == 0 and report["latency_us"] is None
    bad = subprocess.run(
        [
            sys.executable,
            "-m",
            "arpz.perf",
            "sub",
            "--connect",
            endpoint,
            "--depth",
            "0",
            "--count",
            "1",
        ],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert bad.returncode == 2 and "depth" in bad.stderr


PING = [sys.executable, "-m", "arpz.perf", "ping", "--connect", "tcp/127.0.0.1:9"]


def test_an_output_file_that_cannot_be_written_is_refused_before_the_run(tmp_path: Path) -> None:
    missing = tmp_path / "no-such-dir" / "rtt.npy"
    for option in ("--latency-out", "--json"):
        bad = subprocess.run(
            [*PING, option, str(missing)],
            capture_output=True,
            text=True,
            timeout=30,
        )
        assert bad.returncode == 2, bad.stderr
        assert option in bad.stderr and "No such file" in bad.stderr


RAISING_READER = """
import sys, threading
from arpz.core.protocol.qos import QosProfile, HistoryPolicy
from arpz.channel import Reader
from arpz.core.transport import SessionSettings
from arpz.transport.zenoh import ZenohTransport

def on_data(payload, info):
    raise ValueError("a callback that fails on every sample")

transport = ZenohTransport.open(SessionSettings(mode="client", connect=[sys.argv[1]]))
reader = Reader(transport, "perf/raising", QosProfile(history=HistoryPolicy.KEEP_ALL), on_data)
print("ready", file=sys.stderr, flush=True)
threading.Event().wait()  # until the test terminates it
"""


def _keep_all_writer(endpoint: str, key: str) -> Iterator[Writer]:
    with (
        client(endpoint) as transport,
        Writer(transport, key, QosProfile(history=HistoryPolicy.KEEP_ALL)) as writer,
    ):
        wait_until(lambda: writer.matched_count == 1, what="the reader matched")
        yield writer


def test_a_reader_whose_callback_raises_on_every_sample_keeps_acknowledging() -> None:
    """Its stderr is a pipe nobody reads (as a benchmark's child): a traceback per sample
    filled the pipe after a few dozen samples, the channel's thread blocked on the write and
    the KEEP_ALL writer's history filled (found with
    ``benchmarks/investigations/robot_tick_cost.py``)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with (
        perf_router(endpoint),
        child([sys.executable, "-c", RAISING_READER, endpoint], ready="ready"),
        contextlib.contextmanager(_keep_all_writer)(endpoint, "perf/raising") as writer,
    ):
        for n in range(3000):
            writer.write(b"sample %d" % n)
        assert writer.wait_for_acknowledgments(30.0), writer.stats()


def test_sub_counts_what_is_not_a_perf_sample_apart_and_keeps_receiving() -> None:
    """Pointed at a robot's sensor keys, ``sub`` read sensor bytes as seqs beyond int64 and
    raised on every sample: now they are ``foreign``, and perf samples beside them count."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    argv = [sys.executable, "-m", "arpz.perf", "sub", "--connect", endpoint]
    argv += ["--key", "perf/mixed", "--duration", "6"]
    with (
        perf_router(endpoint),
        child(argv, ready="ready") as sub,
        contextlib.contextmanager(_keep_all_writer)(endpoint, "perf/mixed") as writer,
    ):
        for n in range(1, 1001):
            writer.write(b"\xff" * 40)  # a seq of 2**64 - 1
            writer.write(b"short")
            writer.write(make_payload(n, time.time_ns(), 24))
        assert writer.wait_for_acknowledgments(30.0), writer.stats()
        out, _ = sub.communicate(timeout=30)
        err = sub.stderr_text()
    report = json.loads(out.splitlines()[-1])
    assert (report["foreign"], report["received"], report["sent"]) == (2000, 1000, 1000)
    assert report["unaccounted"] == 0 and report["channel"]["callback_errors"] == 0
    assert "2000 payloads on perf/mixed were not arpz.perf samples" in err
