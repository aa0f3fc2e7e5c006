"""The curated benchmark suite's judgement (benchmarks/suite.py): a ratio regressed when it moved
the wrong way by more than 15 %, an entry that regressed is measured again and fails only if
both measurements regressed, informational ratios never fail, and the references come from
RESULTS.md's table (which must name every ratio of every entry). Fake entries, no measurement."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from benchmarks import suite
from benchmarks.entries import ENTRIES
from benchmarks.suite import Entry, Measurement, Reference, TableError

TABLE = f"""# Results

{suite.BEGIN}
Last full run: never.

{suite.HEADER}
|---|---|---:|---|---|---|
| speed | a / b | 2.00x | higher | yes | 2026-12-01, abc1234 |
| speed | tail | 1.5x | lower | info: moved 1.2-2.0x between two runs | 2026-12-01, abc1234 |
| cost | c / d | 0.5 | lower | yes | |
{suite.END}

## Prose below the table
"""


def ref(value: float, better: str, info: str | None = None) -> Reference:
    return Reference("e", "r", value, better, info)


@pytest.mark.parametrize(
    ("value", "better", "regressed"),
    [
        (1.69, "higher", True),  # 15 % below 2.0 is 1.70
        (1.71, "higher", False),
        (5.00, "higher", False),
        (2.31, "lower", True),
        (2.29, "lower", False),
        (0.10, "lower", False),
        (float("nan"), "higher", True),
        (float("nan"), "lower", True),
    ],
)
def test_a_ratio_regressed_when_it_moved_the_wrong_way_by_more_than_15_pct(
    value: float, better: str, regressed: bool
) -> None:
    assert suite.regressed(value, ref(2.0, better)) is regressed


def test_the_table_is_read_between_its_markers() -> None:
    refs = suite.parse_references(TABLE)
    assert list(refs) == [("speed", "a / b"), ("speed", "tail"), ("cost", "c / d")]
    assert refs[("speed", "a / b")] == Reference(
        "speed", "a / b", 2.0, "higher", None, "2026-12-01, abc1234"
    )
    assert refs[("speed", "tail")].info == "moved 1.2-2.0x between two runs"
    assert refs[("cost", "c / d")].value == 0.5


@pytest.mark.parametrize(
    ("broken", "message"),
    [
        (TABLE.replace(suite.END, ""), "no suite table"),
        (TABLE.replace("| higher | yes |", "| up | yes |"), "higher or lower"),
        (TABLE.replace("| 2.00x |", "| fast |"), "not a ratio"),
        (TABLE.replace("| higher | yes |", "| higher | maybe |"), "yes or info"),
        (TABLE.replace("| cost | c / d |", "| speed | a / b |"), "twice"),
        (TABLE.replace("| 0.5 | lower | yes | |", "| 0.5 | lower |"), "cells"),
        (TABLE.replace(suite.HEADER + "\n", ""), "header"),
    ],
)
def test_a_malformed_table_is_refused_with_its_line(broken: str, message: str) -> None:
    with pytest.raises(TableError, match=message):
        suite.parse_references(broken)


def test_results_md_names_every_ratio_of_every_entry_and_nothing_else() -> None:
    refs = suite.parse_references(suite.RESULTS.read_text(encoding="utf-8"))
    declared = {(e.name, name): better for e in ENTRIES for name, better in e.ratios.items()}
    assert set(refs) == set(declared)
    assert suite.check_directions(ENTRIES, refs) == []
    for reference in refs.values():
        assert reference.value > 0 and reference.measured, reference


def fake_entry(results: list[dict[str, float]], name: str = "speed") -> tuple[Entry, list[bool]]:
    """An entry whose measurements are ``results`` in turn; the list records its calls."""
    calls: list[bool] = []
    feed: Iterator[dict[str, float]] = iter(results)

    def run(quick: bool) -> Measurement:
        calls.append(quick)
        return Measurement(dict(next(feed)), [f"call {len(calls)}"])

    return Entry(name, "fake", {"a / b": "higher", "tail": "lower"}, run), calls


def judge(results: list[dict[str, float]]) -> tuple[list[suite.Verdict], int]:
    entry, calls = fake_entry(results)
    refs = suite.parse_references(TABLE)
    lines: list[str] = []
    run, verdicts = suite.run_entry(entry, refs, False, lines.append)
    assert len(run.measurements) == len(calls)
    return verdicts, len(calls)


def test_an_entry_within_15_pct_is_measured_once_and_passes() -> None:
    verdicts, calls = judge([{"a / b": 1.8, "tail": 1.6}])
    assert calls == 1
    assert [(v.status, v.measured) for v in verdicts] == [("pass", [1.8]), ("info", [1.6])]


def test_a_regression_is_measured_again_and_passes_if_the_second_does_not_regress() -> None:
    verdicts, calls = judge([{"a / b": 1.5, "tail": 1.5}, {"a / b": 1.9, "tail": 1.5}])
    assert calls == 2
    assert verdicts[0].status == "pass" and verdicts[0].measured == [1.5, 1.9]
    assert "not in the 2nd" in verdicts[0].note
    assert not any(v.failed for v in verdicts)


def test_a_regression_in_both_measurements_fails() -> None:
    verdicts, calls = judge([{"a / b": 1.5, "tail": 1.5}, {"a / b": 1.6, "tail": 1.5}])
    assert calls == 2
    assert verdicts[0].status == "FAIL" and verdicts[0].failed
    assert verdicts[0].note == "regressed in both measurements"


def test_an_informational_ratio_never_fails_nor_asks_for_a_second_measurement() -> None:
    verdicts, calls = judge([{"a / b": 2.0, "tail": 9.0}])
    assert calls == 1
    assert verdicts[1].status == "info" and not verdicts[1].failed
    assert "informational" in verdicts[1].note


def test_a_ratio_the_entry_stopped_measuring_fails_and_a_new_one_is_reported() -> None:
    verdicts, _ = judge([{"tail": 1.5, "extra": 3.0}])
    by_name = {v.ratio: v for v in verdicts}
    assert by_name["a / b"].status == "MISSING" and by_name["a / b"].failed
    assert by_name["extra"].status == "new" and not by_name["extra"].failed


def test_an_entry_that_raises_is_an_error_and_the_suite_goes_on() -> None:
    def boom(quick: bool) -> Measurement:
        print("what the entry said before it failed")
        raise RuntimeError("no router")

    entry = Entry("speed", "fake", {"a / b": "higher"}, boom)
    lines: list[str] = []
    run, verdicts = suite.run_entry(entry, suite.parse_references(TABLE), True, lines.append)
    assert run.error == "RuntimeError: no router"
    assert [v.status for v in verdicts] == ["ERROR"]
    assert "what the entry said before it failed" in "\n".join(lines)


Main = Callable[..., tuple[int, str, str]]


@pytest.fixture
def main(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> Main:
    results = tmp_path / "RESULTS.md"
    results.write_text(TABLE, encoding="utf-8")

    def call(*argv: str, entries: list[Entry]) -> tuple[int, str, str]:
        code = suite.main([*argv, "--results", str(results)], entries)
        out, err = capsys.readouterr()
        return code, out, err

    return call


def test_main_prints_one_table_and_exits_0_when_nothing_failed(main: Main, tmp_path: Path) -> None:
    speed, _ = fake_entry([{"a / b": 2.1, "tail": 1.4}])
    cost = Entry("cost", "fake", {"c / d": "lower"}, lambda quick: Measurement({"c / d": 0.5}))
    code, out, err = main("--json", str(tmp_path / "run.json"), entries=[speed, cost])
    assert code == 0
    assert "| speed | a / b | 2.10x | 2.00x | higher | +5% | pass |" in out
    assert "| cost | c / d | 0.50x | 0.50x | lower | +0% | pass |" in out
    assert "measured twice: none" in out and "passed" in out.splitlines()[-1]
    # progress: a line when each entry starts and ends, with the time elapsed
    assert "speed (1/2): started" in err and "cost (2/2): done in" in err
    doc = json.loads((tmp_path / "run.json").read_text())
    assert doc["passed"] is True and doc["quick"] is False
    assert [e["entry"] for e in doc["entries"]] == ["speed", "cost"]
    assert doc["ratios"][0]["reference"] == 2.0


def test_main_exits_1_and_says_it_measured_twice_when_a_ratio_failed(main: Main) -> None:
    speed, calls = fake_entry([{"a / b": 1.0, "tail": 1.5}, {"a / b": 1.1, "tail": 1.5}])
    code, out, err = main("--quick", entries=[speed])
    assert code == 1 and calls == [True, True]
    assert "FAIL (regressed in both measurements)" in out
    assert "measured twice: speed" in out and "FAILED" in out.splitlines()[-1]
    assert "measuring again" in err


def test_only_list_and_refusals(main: Main) -> None:
    speed, calls = fake_entry([])
    cost = Entry("cost", "fake", {"c / d": "lower"}, lambda quick: Measurement({"c / d": 0.5}))
    code, out, _ = main("--only", "cost", entries=[speed, cost])
    assert code == 0 and "| cost |" in out and "| speed |" not in out and calls == []
    code, out, _ = main("--list", entries=[speed, cost])
    assert code == 0 and "a / b: 2.00x (higher is better)" in out
    with pytest.raises(SystemExit, match="unknown entry nope"):
        main("--only", "nope", entries=[speed, cost])
    code, _, err = main("--quick", "--update-results", entries=[speed, cost])
    assert code == 2 and "not references" in err
    flipped = Entry("cost", "fake", {"c / d": "higher"}, speed.run)
    code, _, err = main(entries=[flipped])
    assert code == 2 and "RESULTS.md says lower, the entry higher" in err


def test_update_results_writes_the_run_into_the_table_and_keeps_the_rest(
    main: Main, tmp_path: Path
) -> None:
    speed, _ = fake_entry([{"a / b": 2.2, "tail": 3.0, "extra": 7.0}])
    cost = Entry("cost", "fake", {"c / d": "lower"}, lambda quick: Measurement({"c / d": 0.5}))
    code, out, _ = main("--update-results", "--only", "speed", entries=[speed, cost])
    assert code == 0 and "wrote the run's ratios" in out
    text = (tmp_path / "RESULTS.md").read_text()
    refs = suite.parse_references(text)
    assert refs[("speed", "a / b")].value == 2.2
    assert list(refs) == [
        ("speed", "a / b"),
        ("speed", "tail"),
        ("speed", "extra"),
        ("cost", "c / d"),
    ]
    assert refs[("speed", "tail")].info == "moved 1.2-2.0x between two runs"  # kept
    assert refs[("speed", "extra")].value == 7.0 and refs[("speed", "extra")].info is None
    assert refs[("cost", "c / d")] == suite.parse_references(TABLE)[("cost", "c / d")]
    assert "Last full run: never." in text  # not a full run
    assert text.endswith("## Prose below the table\n")
    code, _, _ = main("--update-results", entries=[fake_entry([{"a / b": 2.0}])[0], cost])
    assert "Last full run: 20" in (tmp_path / "RESULTS.md").read_text()
