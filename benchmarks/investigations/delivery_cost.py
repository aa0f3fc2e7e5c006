"""What handing a reader's in-order run to ``on_data`` costs a sample: the channel's loop
(``Channel._deliver_run``) against iterating ``DeliverRun.samples()``, the generator it used
before, for a run of one sample (a message of a robot at 100 Hz) and of 64 (a batch). Both give
each sample its own ``DataInfo`` and call a callback that does nothing, in the same run.

    python benchmarks/investigations/delivery_cost.py [--samples 400000]
"""

from __future__ import annotations

import argparse
import sys
import timeit
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from arpz.channel._channel import Channel
from arpz.core.protocol.actions import DeliverRun
from arpz.core.protocol.events import DataInfo


def _ignore(payload: bytes, info: DataInfo) -> None:
    pass


class _Counts:
    """What ``Channel._deliver_run`` needs of its channel: somewhere to count a raising callback."""

    callback_errors = 0

    def _on_data_raised(self) -> None:
        self.callback_errors += 1


def per_sample_us(run: DeliverRun, samples: int) -> tuple[float, float]:
    """(generator, channel loop) in microseconds a sample, best of 5."""

    counts = _Counts()

    def generator() -> None:  # what Channel.perform did
        for payload, info in run.samples():
            try:
                _ignore(payload, info)
            except Exception:
                counts._on_data_raised()

    def channel_loop() -> None:
        Channel._deliver_run(counts, _ignore, run)  # type: ignore[arg-type]

    n = max(1, samples // len(run.payloads))
    results = []
    for fn in (generator, channel_loop):
        best = min(timeit.repeat(fn, number=n, repeat=5))
        results.append(best / (n * len(run.payloads)) * 1e6)
    return results[0], results[1]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--samples", type=int, default=400_000)
    args = parser.parse_args()
    for size in (1, 64):
        run = DeliverRun("f/robot/r/sensor/t", "ab" * 8, 1, tuple(range(size)), (b"x",) * size)
        gen_us, loop_us = per_sample_us(run, args.samples)
        print(
            f"run of {size:>2}: DeliverRun.samples() {gen_us:.3f} us a sample, channel loop "
            f"{loop_us:.3f} us ({loop_us / gen_us:.2f}x)"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
