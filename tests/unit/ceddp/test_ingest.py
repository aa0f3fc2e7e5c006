from arpz.ceddp.cache_control import CacheControl
from arpz.ceddp.ingest import MAX_WRITERS_PER_TOPIC, Ingest
from arpz.ceddp.planner import HelloRelay, Planner, Reading
from arpz.core.messages import HELLO_DECODER, Hello, LargeSample, Sample, encode

KEY = "arpz/f/robot/r1/sensor/pir"


class Collect(Planner):
    def __init__(self) -> None:
        self.readings: list[Reading] = []
        self.hellos: list[tuple[str, Hello]] = []

    def on_reading(self, reading: Reading) -> None:
        self.readings.append(reading)

    def on_hello(self, robot: str, hello: Hello) -> None:
        self.hellos.append((robot, hello))


def feed(
    ingest: Ingest, key: str, seqs: list[int], value: object = "detect", writer: str = "r1:a"
) -> None:
    for seq in seqs:
        ingest.handle_sensor(key, encode(Sample(writer, seq, 1000, value)), 2_001_000)  # type: ignore[arg-type]


def test_gaps_are_loss_and_late_ones_are_out_of_order() -> None:
    ingest = Ingest("f", Collect(), CacheControl(enabled=False))
    feed(ingest, KEY, [1, 2, 5, 4, 6])
    m = ingest.topics[("r1", "pir")]
    assert (m.received, m.lost, m.out_of_order, m.next_seq) == (5, 2, 1, 7)
    assert m.latency_ms.quantile(50) == 2.0


def test_a_new_writer_is_a_new_stream_and_a_late_join_is_not_loss() -> None:
    ingest = Ingest("f", Collect(), CacheControl(enabled=False))
    feed(ingest, KEY, [10, 11])
    feed(ingest, KEY, [1, 2, 3], writer="r1:b")
    m = ingest.topics[("r1", "pir")]
    assert (m.lost, m.before_join, m.writer_changes, m.received) == (0, 9, 1, 5)


def test_two_writers_on_one_topic_keep_their_own_sequences() -> None:
    ingest = Ingest("f", Collect(), CacheControl(enabled=False))
    for seq in (1, 2, 3):
        feed(ingest, KEY, [seq], writer="r1:a")
        feed(ingest, KEY, [seq], writer="r1:b")
    feed(ingest, KEY, [5], writer="r1:a")  # one lost from writer a
    m = ingest.topics[("r1", "pir")]
    assert (m.received, m.lost, m.before_join, m.writer_changes) == (7, 1, 0, 1)
    assert Ingest.highest_seq(m, "r1:a") == 5 and Ingest.highest_seq(m, "r1:b") == 3


def test_cache_control_sits_between_ingest_and_planner() -> None:
    planner = Collect()
    ingest = Ingest("f", planner, CacheControl())
    feed(ingest, KEY, [1, 2, 3], value="detect")
    feed(ingest, KEY, [4], value="not detect")
    assert [r.seq for r in planner.readings] == [1, 4]
    assert ingest.cache_counters("r1", "pir").hits == 2


def test_bad_payloads_and_unknown_keys_are_counted_not_raised() -> None:
    planner = Collect()
    ingest = Ingest("f", planner, CacheControl())
    ingest.handle_sensor(KEY, b"\xff\x00garbage", 0)
    ingest.handle_sensor(KEY, encode(Sample("w", 1, 0, "x")) + b"trailing", 0)
    ingest.handle_sensor(KEY, b"\x94\xa1\x80", 0)  # a str that is not UTF-8
    ingest.handle_sensor("arpz/f/robot/r1/sensor/pir/extra", b"", 0)
    ingest.handle_sensor("arpz/other/robot/r1/sensor/pir", b"", 0)
    ingest.handle_sensor("arpz/f/robot/r1/sensor/hello", b"\x01", 0)
    assert ingest.topics[("r1", "pir")].decode_errors == 3
    assert ingest.topics[("r1", "hello")].decode_errors == 1
    assert ingest.counters.unknown_keys == 2
    assert planner.readings == []


class Sink:
    def __init__(self) -> None:
        self.sent: list[tuple[str, str, Hello]] = []

    def send(self, robot: str, name: str, payload: bytes) -> None:
        self.sent.append((robot, name, HELLO_DECODER.decode(payload)))


def test_hello_relay_routes_origin_to_relay_and_back() -> None:
    sink = Sink()
    relay = HelloRelay(sink, "ceddp:x", relay="r3")
    relay.on_hello("r1", Hello("r1:a", 1, 5, "r1", 1, 5, 0))  # r3 not seen yet: counted
    relay.on_robot("r3", True)
    relay.on_hello("r1", Hello("r1:a", 1, 5, "r1", 1, 5, 0))
    relay.on_hello("r3", Hello("r3:a", 1, 6, "r1", 1, 5, 2))
    relay.on_hello("r3", Hello("r3:a", 2, 7, "r1", 1, 5, 9))
    assert [(r, h.stage, h.origin_seq, h.t0_ns, h.writer) for r, _, h in sink.sent] == [
        ("r3", 1, 1, 5, "ceddp:x"),
        ("r1", 3, 1, 5, "ceddp:x"),
    ]
    relay.on_robot("r3", False)
    relay.on_robot("r1", True)
    relay.on_hello("r1", Hello("r1:a", 2, 8, "r1", 2, 8, 0))
    assert relay.counters.no_relay == 2 and relay.counters.bad_stage == 1


def feed_at(ingest: Ingest, seq: int, arrival_s: float, writer: str = "r1:a") -> None:
    sample = Sample(writer, seq, 1000, "detect")  # type: ignore[arg-type]
    ingest.handle_sensor(KEY, encode(sample), int(arrival_s * 1e9))


def test_implausible_seqs_are_refused_as_bad_input_not_loss() -> None:
    ingest = Ingest("f", Collect(), CacheControl(enabled=False))
    for seq in range(1, 6):
        feed_at(ingest, seq, 10 + seq * 0.01)
    feed_at(ingest, 10**6, 10.06)  # 10 ms after the last: at most ~10 000 seqs can follow
    feed_at(ingest, 2**64 - 1, 10.07)  # out of range
    feed_at(ingest, 0, 10.08)
    feed_at(ingest, 6, 10.09)
    feed_at(ingest, 6 + 20_000, 20.09)  # 10 s of silence (an outage): a real jump, real loss
    m = ingest.topics[("r1", "pir")]
    assert (m.received, m.lost, m.implausible_seq) == (7, 19_999, 3)


def test_a_writer_id_per_sample_is_bounded_per_topic() -> None:
    ingest = Ingest("f", Collect(), CacheControl(enabled=False))
    for i in range(100):
        feed_at(ingest, 1, 10 + i * 0.001, writer=f"r1:{i}")
    m = ingest.topics[("r1", "pir")]
    assert m.received == MAX_WRITERS_PER_TOPIC and len(m.others) == MAX_WRITERS_PER_TOPIC - 1
    assert m.writers_over_limit == 100 - MAX_WRITERS_PER_TOPIC


def test_samples_larger_than_their_kinds_bound_are_refused_undecoded() -> None:
    ingest = Ingest(
        "f", Collect(), CacheControl(enabled=False), max_sample_bytes={"default": 100, "pir": 40}
    )
    small, big = (
        encode(Sample("r1:a", 1, 1000, "detect")),
        encode(Sample("r1:a", 2, 1000, "x" * 60)),
    )
    ingest.handle_sensor(KEY, small, 2_000_000)
    ingest.handle_sensor(KEY, big, 2_000_000)  # 60+ bytes: within the default bound
    ingest.set_kinds("r1", {"pir": "pir"})  # announced: its kind's bound applies
    ingest.handle_sensor(KEY, encode(Sample("r1:a", 3, 1000, "x" * 60)), 2_000_000)
    ingest.handle_sensor(KEY, b"\xc1" * 101, 2_000_000)
    m = ingest.topics[("r1", "pir")]
    assert (m.received, m.oversize, m.decode_errors, m.max_bytes) == (2, 2, 0, 40)


def test_samples_the_previous_run_received_are_flagged_not_planned_again() -> None:
    planner = Collect()
    ingest = Ingest("f", planner, CacheControl(enabled=False))
    ingest.load_previous_run({("r1", "pir"): {"r1:a": 6}, ("r1", "x"): {"r1:z": 3}})
    feed(ingest, KEY, list(range(1, 11)))  # the TRANSIENT_LOCAL history from seq 1 again
    feed(ingest, KEY, [1, 2], writer="r1:b")  # another incarnation: nothing seen before
    m = ingest.topics[("r1", "pir")]
    assert (m.received, m.lost, m.repeated_from_previous_run) == (12, 0, 6)
    assert [r.seq for r in planner.readings] == [7, 8, 9, 10, 1, 2]


def test_large_samples_are_decoded_as_bytes_and_bounded_by_their_kind() -> None:
    planner = Collect()
    ingest = Ingest(
        "f", planner, CacheControl(enabled=True), max_sample_bytes={"camera": 1_000_000}
    )
    key = "arpz/f/robot/r1/sensor/front"
    frame = bytes(range(256)) * 3600  # 921 600 bytes, a 640x480 RGB frame
    # reassembled from fragments before the robot announced the camera: large from now on
    ingest.handle_sensor(key, encode(LargeSample("r1:a", 1, 1000, frame)), 2_000_000, large=True)
    ingest.handle_sensor(key, encode(LargeSample("r1:a", 2, 1000, frame)), 2_000_000, large=True)
    m = ingest.topics[("r1", "front")]
    assert (m.received, m.decode_errors, m.oversize) == (2, 0, 0)
    assert [r.value for r in planner.readings] == [frame]  # the repeat was discarded by CC
    # announced: the camera's own bound applies, also to a plain-mode sample on sensor/
    ingest.set_kinds("r1", {"front": "camera", "pir": "pir"})
    assert m.large and m.max_bytes == 1_000_000
    ingest.handle_sensor(key, encode(LargeSample("r1:a", 3, 1000, frame + frame)), 2_000_000)
    assert m.oversize == 1
    # a small topic still refuses bytes where a reading belongs: a decode error, counted
    ingest.handle_sensor(KEY, encode(LargeSample("r1:a", 1, 1000, b"xy")), 2_000_000)
    assert ingest.topics[("r1", "pir")].decode_errors == 1


def test_a_frame_on_a_topic_announced_small_is_refused_not_a_change_of_kind() -> None:
    ingest = Ingest("f", Collect(), CacheControl(enabled=True))
    ingest.set_kinds("r1", {"pir": "pir"})
    feed(ingest, KEY, [1])
    ingest.handle_sensor(
        KEY, encode(LargeSample("r1:a", 2, 1000, b"x" * 100)), 2_000_000, large=True
    )
    feed(ingest, KEY, [2])  # the small sensor's own next sample still decodes
    m = ingest.topics[("r1", "pir")]
    assert (m.received, m.decode_errors, m.large) == (2, 1, False)


def test_a_run_is_ingested_as_its_samples_one_by_one_would_be() -> None:
    """``handle_run`` (a batch the reliable channel delivered) counts, measures and plans each
    sample as ``handle_sensor`` does, the first run of a topic included; a bad sample in the
    middle is counted and the rest of the run still arrives."""
    values = ["detect", "detect", "not detect", "not detect", "detect"]
    payloads = [encode(Sample("r1:a", seq, 1000, v)) for seq, v in enumerate(values, 1)]
    one_planner, run_planner = Collect(), Collect()
    one = Ingest("f", one_planner, CacheControl())
    by_run = Ingest("f", run_planner, CacheControl())
    for payload in payloads:
        one.handle_sensor(KEY, payload, 2_001_000)
    by_run.handle_run(KEY, payloads[:2], 2_001_000)  # a new topic: looked up a sample at a time
    by_run.handle_run(KEY, [*payloads[2:4], b"\xff\x00garbage", payloads[4]], 2_001_000)
    a, b = one.topics[("r1", "pir")], by_run.topics[("r1", "pir")]
    assert (b.received, b.lost, b.next_seq, b.decode_errors) == (5, 0, 6, 1)
    assert (a.received, a.lost, a.next_seq, a.decode_errors) == (5, 0, 6, 0)
    assert b.latency_ms.total == a.latency_ms.total == 5
    assert b.latency_ms.quantiles(0, 100) == a.latency_ms.quantiles(0, 100) == [2.0, 2.0]
    planned = [r.seq for r in run_planner.readings]
    assert planned == [r.seq for r in one_planner.readings] == [1, 3, 5]
    assert by_run.cache_counters("r1", "pir").hits == one.cache_counters("r1", "pir").hits == 2


def test_a_run_on_an_unknown_key_is_counted_a_sample_at_a_time() -> None:
    ingest = Ingest("f", Collect(), CacheControl())
    ingest.handle_run("arpz/f/robot/r1/sensor/pir/extra", [b"", b"", b""], 0)
    assert ingest.counters.unknown_keys == 3


def test_a_planner_that_raises_loses_only_its_own_sample_of_a_run() -> None:
    class Fails(Collect):
        def on_reading(self, reading: Reading) -> None:
            if reading.seq == 2:
                raise RuntimeError("planner bug")
            super().on_reading(reading)

    planner = Fails()
    ingest = Ingest("f", planner, CacheControl(enabled=False))
    feed(ingest, KEY, [1])  # the topic exists: the run takes the fast path
    ingest.handle_run(KEY, [encode(Sample("r1:a", seq, 1000, "x")) for seq in (2, 3, 4)], 0)
    assert [r.seq for r in planner.readings] == [1, 3, 4]
    assert ingest.topics[("r1", "pir")].received == 4
