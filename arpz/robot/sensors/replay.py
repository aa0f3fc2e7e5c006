"""Replay of a recorded trace: CSV (``t_s,value``) or JSON lines (``{"t_s": ..., "value": ...}``).

The reading at time t is the last record with ``t_s <= t`` (a sample-and-hold, as a real sensor
read between two changes would give); after the last record the trace loops if ``loop`` is set
in the driver options, else it holds its last value.
"""

from __future__ import annotations

import bisect
import csv
import json
from pathlib import Path
from typing import Any, ClassVar

from arpz.core.errors import ArpzError
from arpz.core.messages import SensorValue
from arpz.robot.sensors.base import VALUE_TYPES, SensorDriver, check_value


class TraceError(ArpzError, ValueError):
    """A trace file that cannot be replayed; the message names the file and the line."""


def _parse_value(kind: str, raw: object, where: str) -> SensorValue:
    expected = VALUE_TYPES[kind]
    try:
        if isinstance(raw, str) and expected is float:
            raw = float(raw)
        elif isinstance(raw, str) and expected is bool:
            lowered = raw.strip().lower()
            if lowered not in ("true", "false", "1", "0"):
                raise ValueError(f"not a boolean: {raw!r}")
            raw = lowered in ("true", "1")
        return check_value(kind, raw)
    except (ValueError, TypeError) as exc:
        raise TraceError(f"{where}: {exc}") from None


def load_trace(path: Path, kind: str) -> tuple[list[float], list[SensorValue]]:
    times: list[float] = []
    values: list[SensorValue] = []
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise TraceError(f"{path}: cannot read trace: {exc.strerror}") from None
    if path.suffix in (".jsonl", ".json", ".ndjson"):
        rows: list[tuple[object, object, str]] = []
        for number, line in enumerate(text.splitlines(), start=1):
            if not line.strip():
                continue
            try:
                record = json.loads(line)
                rows.append((record["t_s"], record["value"], f"{path}:{number}"))
            except (json.JSONDecodeError, KeyError, TypeError) as exc:
                raise TraceError(
                    f'{path}:{number}: expected {{"t_s": ..., "value": ...}}: {exc}'
                ) from None
    else:
        reader = csv.DictReader(text.splitlines())
        if reader.fieldnames is None or not {"t_s", "value"} <= set(reader.fieldnames):
            raise TraceError(f"{path}: a CSV trace needs the header 't_s,value'")
        rows = [(r["t_s"], r["value"], f"{path}:{n}") for n, r in enumerate(reader, start=2)]
    for t_raw, v_raw, where in rows:
        try:
            t_s = float(t_raw)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            raise TraceError(f"{where}: t_s must be a number, got {t_raw!r}") from None
        if times and t_s < times[-1]:
            raise TraceError(f"{where}: t_s must not decrease ({t_s} after {times[-1]})")
        times.append(t_s)
        values.append(_parse_value(kind, v_raw, where))
    if not times:
        raise TraceError(f"{path}: the trace has no records")
    return times, values


class ReplayDriver(SensorDriver):
    kind: ClassVar[str] = ""

    def __init__(self, kind: str, path: Path, options: dict[str, Any], seed: int) -> None:
        super().__init__(options, seed)
        self.kind_name = kind
        self.times, self.values = load_trace(path, kind)
        self.loop = bool(options.get("loop", False))
        self.span_s = self.times[-1] - self.times[0]

    def read(self, now_s: float) -> SensorValue:
        t = self.times[0] + now_s
        if self.loop and self.span_s > 0 and t > self.times[-1]:
            t = self.times[0] + (now_s % self.span_s)
        index = bisect.bisect_right(self.times, t) - 1
        return self.values[max(index, 0)]
