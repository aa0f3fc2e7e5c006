"""The performance tool of arpz (``python -m arpz.perf``): docs/perf.md."""

from arpz.perf.report import (
    LatencyUs,
    Recorder,
    Report,
    build_report,
    make_payload,
    payload_maker,
    percentile,
)

__all__ = [
    "LatencyUs",
    "Recorder",
    "Report",
    "build_report",
    "make_payload",
    "payload_maker",
    "percentile",
]
