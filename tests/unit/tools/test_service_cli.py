"""``python -m arpz service``'s input: service names, requests as ``ros2 service call`` takes
them, and the bad ones refused before the tool joins a fleet (exit 2)."""

from __future__ import annotations

import pytest

from arpz.tools.service import BadInput, main, parse_request, parse_service, plain


@pytest.mark.parametrize(
    "given",
    ["/robot1/dock", "robot1/dock", "/robot1/srv/dock", "arpz/lab/robot/robot1/srv/dock"],
)
def test_a_service_is_named_as_ros_2_names_it_or_by_its_key(given: str) -> None:
    assert parse_service("lab", given) == ("robot1", "dock")


@pytest.mark.parametrize(
    ("given", "says"),
    [
        ("robot1", "does not name a service"),
        ("/robot1/cmd/dock/x", "does not name a service"),
        ("/Robot1/dock", "robot id"),
        ("arpz/other/robot/robot1/srv/dock", "not a service key of fleet 'lab'"),
        ("arpz/lab/robot/robot1/sensor/dock", "not a service key"),
    ],
)
def test_a_name_that_is_no_service_is_refused(given: str, says: str) -> None:
    with pytest.raises(BadInput, match=says):
        parse_service("lab", given)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("", {}),
        ("{}", {}),
        ('{"data": true}', {"data": True}),
        ("{data: true}", {"data": True}),
        (
            "{data: False, message: 'a, b', n: -3, x: 1.5e3, s: on}",
            {
                "data": False,
                "message": "a, b",
                "n": -3,
                "x": 1500.0,
                "s": "on",
            },
        ),
        (
            "{start: {pose: {position: {x: 1}}}, xs: [1, 2.5, null], t: ~}",
            {
                "start": {"pose": {"position": {"x": 1}}},
                "xs": [1, 2.5, None],
                "t": None,
            },
        ),
        ('{name: "quoted \\"x\\""}', {"name": 'quoted "x"'}),
    ],
)
def test_a_request_is_json_or_yaml_flow_style(text: str, expected: object) -> None:
    assert parse_request(text) == expected


@pytest.mark.parametrize(
    ("text", "says"),
    [
        ("{data: true", "misses a closing"),
        ("{data true}", "a ':' must follow"),
        ("{data: true}}", "unexpected"),
        ("{data: }", "unexpected"),
    ],
)
def test_a_request_that_cannot_be_read_says_where(text: str, says: str) -> None:
    with pytest.raises(BadInput, match=says):
        parse_request(text)


def test_plain_shows_bytes_as_numbers_and_hides_the_empty_placeholder() -> None:
    assert plain({"structure_needs_at_least_one_member": 0}) == {}
    assert plain({"data": b"\x01\x02", "xs": [{"b": b"\x03"}]}) == {
        "data": [1, 2],
        "xs": [{"b": [3]}],
    }


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["call", "/robot1/dock", "std_srvs/srv/Trigga"], "did you mean std_srvs/srv/Trigger"),
        (["call", "/robot1/lamp", "std_srvs/srv/SetBool", "{data: 3}"], "at `$.data`"),
        (["call", "/robot1/lamp", "std_srvs/srv/SetBool", "{colour: 1}"], "colour"),
        (["call", "/robot1/dock", "std_srvs/msg/Trigger"], "package/srv/Name"),
        (["call", "/robot1/dock", "std_srvs/srv/Trigger", "--timeout", "0"], "--timeout"),
        (["call", "/robot1/dock", "std_srvs/srv/Trigger", "--connect", "tcp/nowhere"], "--connect"),
        (["list", "--fleet", "Lab"], "--fleet"),
        (["call", "robot1", "std_srvs/srv/Trigger"], "does not name a service"),
    ],
)
def test_bad_input_exits_2_before_joining_a_fleet(
    args: list[str], says: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("arpz service: error: ") and says in err, err
