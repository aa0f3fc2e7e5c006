"""topic's command line without a fleet: argument errors, the echo text, the figures of hz, bw
and delay from given messages, and the delay's clock correction."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from arpz.core.messages import ClockStats, LargeSample, RobotStats, Sample, encode
from arpz.tools import topic
from arpz.tools.fleet_graph import CEDDP, Endpoint, FleetGraph, TopicEntry
from arpz.tools.topic_figures import Bw, Delay, Echo, Hz, clock_correction
from arpz.tools.topic_stream import Message, TopicStream
from arpz.tools.topic_text import Output, decode, echo_text, message_document


def entry(arpz_type: str = "Sample", kind: str | None = "lidar", owner: str = "r1") -> TopicEntry:
    return TopicEntry(
        name="/r1/lidar",
        key="arpz/f/robot/r1/sensor/lidar",
        owner=owner,
        arpz_type=arpz_type,
        value_type="float",
        kind=kind,
        ros_types=("sensor_msgs/msg/LaserScan",),
        mode="channel",
        announced_rate_hz=10.0,
        measured_rate_hz=10.0,
        writers=(Endpoint("r1", "aa", None),),
        readers=(),
    )


class FakeStream(TopicStream):
    def counters(self) -> dict[str, int]:
        return {"delivered": 3, "lost": 1, "retransmitted": 0}

    def close(self) -> None:
        pass


def message(payload: bytes, arrival_s: float, arrival_ns: int = 0) -> Message:
    return Message("arpz/f/robot/r1/sensor/lidar", payload, arrival_ns, arrival_s, "aa", None)


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["list", "--connect", "foo"], "--connect[0] 'foo'"),
        (["list", "--connect", ","], "--connect: give at least one endpoint"),
        (["list", "--fleet", "Bad Name"], "--fleet 'Bad Name' is not a valid key chunk"),
        (["hz", "/r1/lidar", "--window", "1"], "--window must be >= 2"),
        (["echo", "/r1/lidar", "--duration", "-1"], "--duration must be >= 0"),
    ],
)
def test_bad_input_is_an_error_naming_the_flag(
    argv: list[str], needle: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert topic.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("arpz topic: error: ") and needle in err


def test_help_names_the_three_forms_of_a_topic(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        topic.main(["echo", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    for form in ("/robot1/lidar", "robot1/lidar", "arpz/FLEET/robot/robot1/sensor/lidar"):
        assert form in out
    assert "BEST_EFFORT" in out and "--reliable" in out


def test_a_sample_echoes_on_one_line_and_as_json() -> None:
    t = entry()
    payload = encode(Sample("r1:abc", 7, 1_700_000_000_000_000_000, 2.5))
    doc = message_document(t, message(payload, 0.0, 5), decode(t, payload))
    assert doc["message"] == {
        "writer": "r1:abc",
        "seq": 7,
        "stamp_ns": 1_700_000_000_000_000_000,
        "value": 2.5,
        "changed_ns": 0,
        "since_ns": 0,
    }
    assert json.loads(json.dumps(doc))["arrival_ns"] == 5
    text = echo_text(t, doc)
    assert "seq=7" in text and "value=2.5" in text and "stamp=2023-11-14T22:13:20.000000Z" in text


def test_a_frame_echoes_as_a_summary_not_its_bytes() -> None:
    t = entry("LargeSample", "camera")
    pixels = bytes(range(256)) * 3 * 100
    payload = encode(LargeSample("r1:abc", 1, 2, pixels))
    doc = message_document(t, message(payload, 0.0), decode(t, payload))
    value = doc["message"]["value"]  # type: ignore[index]
    assert value["bytes"] == len(pixels) and value["pixels"] == len(pixels) // 3
    assert len(json.dumps(doc)) < 400


def test_a_report_echoes_as_a_block() -> None:
    t = entry("RobotStats", None)
    stats = RobotStats(robot="r1", incarnation="x", stamp_ns=1, final=True, topics={})
    doc = message_document(t, message(encode(stats), 0.0), decode(t, encode(stats)))
    text = echo_text(t, doc)
    assert 'robot: "r1"' in text and "final: true" in text and text.endswith("---")


def test_echo_counts_undecodable_messages(tmp_path: Path) -> None:
    out = Output(str(tmp_path / "e.jsonl"))
    echo = Echo(entry(), out, count=2)
    echo.on_message(message(b"\xc1", 0.0))
    echo.on_message(message(encode(Sample("r1:a", 1, 1, 1.0)), 0.0))
    assert (echo.printed, echo.decode_errors, echo.done) == (1, 1, False)
    echo.final(FakeStream(entry(), "fake"))
    out.close()
    lines = [json.loads(line) for line in (tmp_path / "e.jsonl").read_text().splitlines()]
    assert lines[0]["message"]["seq"] == 1
    assert lines[-1]["final"] is True and lines[-1]["counters"]["decode_errors"] == 1


def test_hz_and_bw_figures(tmp_path: Path) -> None:
    out = Output(str(tmp_path / "hz.jsonl"))
    hz, bw = Hz(entry(), out, 100), Bw(entry(), out, 100)
    stream = FakeStream(entry(), "fake")
    for i in range(11):  # 10 Hz, 100-byte messages
        m = message(b"x" * 100, i * 0.1)
        hz.on_message(m)
        bw.on_message(m)
    hz.report(stream)
    bw.final(stream)
    out.close()
    lines = [json.loads(line) for line in (tmp_path / "hz.jsonl").read_text().splitlines()]
    assert lines[0]["rate_hz"] == pytest.approx(10.0)
    assert lines[0]["window"] == 11 and lines[0]["counters"]["lost"] == 1
    assert lines[1]["bytes_per_s"] == pytest.approx(1000.0)
    assert lines[1]["size_mean"] == 100.0 and lines[1]["final"] is True


def test_no_new_messages_is_said(capsys: pytest.CaptureFixture[str]) -> None:
    hz = Hz(entry(), Output(None), 100)
    hz.report(FakeStream(entry(), "fake"))
    assert capsys.readouterr().out.strip() == "no new messages"


@pytest.mark.parametrize(
    ("correction", "expected_s", "corrected"),
    [(None, 0.005, False), (2_000_000, 0.003, True), (-1_000_000, 0.006, True)],
)
def test_delay_subtracts_the_clock_correction(
    correction: int | None, expected_s: float, corrected: bool
) -> None:
    delay = Delay(entry(), Output(None), 100, lambda: (correction, "note"))
    stamp = 1_000_000_000
    delay.on_message(message(encode(Sample("r1:a", 1, stamp, 1.0)), 0.0, stamp + 5_000_000))
    figures = delay.figures(0.0)
    assert figures is not None
    assert figures["delay_mean_s"] == pytest.approx(expected_s)
    assert figures["corrected"] is corrected


def test_the_correction_of_the_ceddps_own_keys_is_this_hosts_offset() -> None:
    class Host:
        def refresh(self) -> None:
            pass

        def offset_ns(self) -> int | None:
            return 3_000

    class NoStats:
        def graph(self) -> object:
            raise AssertionError("the CEDDP's keys need no robot stats")

    ceddp = entry("CeddpStats", None, owner=CEDDP)
    correction, note = clock_correction(NoStats(), ceddp, Host())()  # type: ignore[arg-type]
    assert correction == -3_000 and "corrected" in note


@pytest.mark.parametrize("offset_ns", [None, 4_000_000])
def test_a_robots_correction_is_its_offset_minus_this_hosts(offset_ns: int | None) -> None:
    clock = ClockStats(offset_ns=offset_ns, delay_ns=100_000)
    stats = RobotStats(robot="r1", incarnation="x", stamp_ns=1, final=False, topics={}, clock=clock)

    class Discovery:
        def graph(self) -> FleetGraph:
            return FleetGraph("f", (), (), {"r1": stats})

    class Host:
        def refresh(self) -> None:
            pass

        def offset_ns(self) -> int | None:
            return 1_000_000

    correction, note = clock_correction(Discovery(), entry(), Host())()  # type: ignore[arg-type]
    if offset_ns is None:
        assert correction is None and note.endswith("offset unknown, uncorrected")
    else:
        assert correction == 3_000_000
        assert "r1 +4.000 ms" in note and "this host +1.000 ms" in note
