"""The summary file the CEDDP rewrites every summary_period_s (``write_json_atomically``)."""

from __future__ import annotations

import json
import math
from pathlib import Path

from arpz.ceddp.server import write_json_atomically


def test_the_summary_file_is_the_indented_json_of_the_summary(tmp_path: Path) -> None:
    doc = {
        "fleet": "f",
        "robots": {"robot1": {"topics": {"lidar": {"sent": 3, "latency_ms_p99": 1.5}}}},
        "lost": [1, 2],
        "none": None,
        "text": 'é "quoted"',
    }
    path = tmp_path / "deep" / "summary.json"
    write_json_atomically(path, doc)
    assert path.read_text(encoding="utf-8") == json.dumps(doc, indent=2, ensure_ascii=False)
    assert not path.with_name("summary.json.partial").exists()
    write_json_atomically(path, {"fleet": "g"})  # replaced whole
    assert json.loads(path.read_text(encoding="utf-8")) == {"fleet": "g"}


def test_a_float_that_is_not_finite_is_written_as_null(tmp_path: Path) -> None:
    path = tmp_path / "summary.json"
    write_json_atomically(path, {"p99": math.nan, "max": math.inf})
    assert json.loads(path.read_text(encoding="utf-8")) == {"p99": None, "max": None}
