"""The CEDDP's channel ingest by runs: chunks under one hold of the ingest lock, down to one
sample a hold while holds are long (a slow planner must not keep the control worker out)."""

from __future__ import annotations

import threading
import time
from types import TracebackType

import pytest

from arpz.ceddp import intake as intake_module
from arpz.ceddp.cache_control import CacheControl
from arpz.ceddp.ingest import Ingest
from arpz.ceddp.intake import _RUN_CHUNK, SensorIntake
from arpz.ceddp.planner import Planner, Reading
from arpz.core.config import CeddpConfig
from arpz.core.messages import Sample, encode
from arpz.transport.memory import MemoryBus, MemoryTransport

KEY = "arpz/f/robot/r1/sensor/pir"
#: the bound on one hold in these tests: far above what a loaded test host adds to a quick chunk
HOLD_NS = 20_000_000


@pytest.fixture(autouse=True)
def _hold_bound(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(intake_module, "_RUN_HOLD_NS", HOLD_NS)


class CountingLock:
    """The ingest lock, counting its holds."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.holds = 0

    def __enter__(self) -> None:
        self._lock.acquire()
        self.holds += 1

    def __exit__(
        self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self._lock.release()


class SlowPlanner(Planner):
    """Costs ``cost_s`` a reading, as ``[overload] planner_cost_us`` does."""

    def __init__(self, cost_s: float) -> None:
        self.cost_s = cost_s
        self.seqs: list[int] = []

    def on_reading(self, reading: Reading) -> None:
        end = time.perf_counter() + self.cost_s
        while time.perf_counter() < end:
            pass
        self.seqs.append(reading.seq)


def _intake(planner: Planner) -> tuple[SensorIntake, CountingLock]:
    ingest = Ingest("f", planner, CacheControl(enabled=False))
    lock = CountingLock()
    ingest.lock = lock  # type: ignore[assignment]
    intake = SensorIntake(
        CeddpConfig(fleet="f"),
        MemoryTransport(MemoryBus()),
        ingest,
        planner,
        None,  # type: ignore[arg-type]  # the control worker: not used by the ingest of runs
        lambda _kind, _text: None,
    )
    return intake, lock


def _run(first: int, count: int) -> list[bytes]:
    return [encode(Sample("r1:a", seq, 1000, seq)) for seq in range(first, first + count)]


def test_a_quick_run_is_ingested_a_chunk_per_hold() -> None:
    planner = SlowPlanner(0.0)
    intake, lock = _intake(planner)
    # the topic's first sample creates its state (milliseconds, once), outside the runs
    intake.ingest.handle_sensor(KEY, _run(1, 1)[0], time.time_ns())
    intake._on_channel_run(KEY, _run(2, 4 * _RUN_CHUNK))
    assert planner.seqs == list(range(1, 4 * _RUN_CHUNK + 2))
    assert intake.processed == 4 * _RUN_CHUNK
    assert lock.holds == 4


def test_a_slow_planner_takes_the_chunks_down_to_one_sample_a_hold_and_back() -> None:
    # a whole chunk at this cost would hold the lock about twice the bound
    planner = SlowPlanner(2 * HOLD_NS / 1e9 / _RUN_CHUNK)
    intake, lock = _intake(planner)
    intake._on_channel_run(KEY, _run(1, 3 * _RUN_CHUNK))
    # the first chunk shows the pace, then one sample a hold
    assert lock.holds == 1 + 2 * _RUN_CHUNK
    assert planner.seqs == list(range(1, 3 * _RUN_CHUNK + 1))
    planner.cost_s = 0.0
    lock.holds = 0
    intake._on_channel_run(KEY, _run(3 * _RUN_CHUNK + 1, 3 * _RUN_CHUNK))
    # one quick sample shows a whole chunk fits in the bound again
    assert lock.holds == 1 + 3
    assert intake.processed == 6 * _RUN_CHUNK
