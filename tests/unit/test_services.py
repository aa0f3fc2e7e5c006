"""Robot services end to end on the in-memory bus: ``arpz.robot.services.ServiceHost`` answers,
``arpz.ceddp.services.ServiceCaller`` calls, and both count (docs/nodes.md "Services")."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import msgspec
import pytest

from arpz.ceddp.services import (
    CallCounters,
    FleetServices,
    NoSuchService,
    RobotGone,
    RobotServices,
    ServiceBusy,
    ServiceCaller,
    ServiceFailed,
    ServiceRefused,
    ServiceTimeout,
    ServiceTypeError,
    services_summary,
)
from arpz.core import keys
from arpz.core.config import ConfigError, RobotConfig, from_dict
from arpz.core.messages import (
    SERVICE_ACCEPTED,
    SERVICE_BAD_REQUEST,
    SERVICE_OK,
    SERVICE_REPLY_DECODER,
    SERVICE_TYPE_ERROR,
    ServiceCounters,
    ServiceRequest,
    encode,
)
from arpz.core.msgtypes import MessageTypeError, MessageTypes
from arpz.robot.agent import RobotAgent
from arpz.robot.services import ServiceConfigError, ServiceHost, field_error, load_handler
from arpz.transport.memory import MemoryBus, MemoryTransport
from tests.support import wait_until

FLEET = "lab"
TYPES = MessageTypes()
#: released by the tests that make a handler hang
RELEASE = threading.Event()


# -- handlers, named in the configs below as tests.unit.test_services:NAME ---------------------


def dock(request: Any) -> dict[str, object]:
    return {"success": True, "message": "docked"}


def jammed(request: Any) -> dict[str, object]:
    raise RuntimeError("the dock is blocked")


def hangs(request: Any) -> dict[str, object]:
    RELEASE.wait(10)
    return {"success": True, "message": "late"}


def wrong_response(request: Any) -> dict[str, object]:
    return {"success": "yes", "message": "docked"}


class Lamp:
    """A class handler, made with its options."""

    def __init__(self, options: dict[str, Any]) -> None:
        self.prefix = str(options["prefix"])
        self.calls = 0

    def __call__(self, request: Any) -> dict[str, object]:
        self.calls += 1
        return {"success": request.data, "message": f"{self.prefix} {request.data}"}


NOT_CALLABLE = 3


def robot_config(*services: dict[str, Any]) -> RobotConfig:
    return from_dict(
        {"robot_id": "robot1", "fleet": FLEET, "services": list(services)},
        RobotConfig,
        source="test",
    )


def service(name: str, handler: str, type_: str = "std_srvs/srv/Trigger", **more: Any) -> dict:
    return {"name": name, "type": type_, "handler": f"tests.unit.test_services:{handler}", **more}


@pytest.fixture
def bus() -> MemoryBus:
    return MemoryBus()


@pytest.fixture
def host(bus: MemoryBus) -> Iterator[ServiceHost]:
    RELEASE.clear()
    config = robot_config(
        service("dock", "dock"),
        service("jammed", "jammed"),
        service("slow", "hangs", queue=1),
        service("wrong", "wrong_response"),
        service("lamp", "Lamp", "std_srvs/srv/SetBool", options={"prefix": "lamp"}),
    )
    served = ServiceHost(config, MemoryTransport(bus), TYPES)
    served.start()
    yield served
    RELEASE.set()
    served.close()


def caller_on(
    bus: MemoryBus, *, present: bool | None = True, access_control: bool | None = False
) -> ServiceCaller:
    return ServiceCaller(
        MemoryTransport(bus),
        FLEET,
        types=TYPES,
        caller="test",
        directory=lambda robot: RobotServices(present if robot == "robot1" else False),
        access_control=lambda: access_control,
    )


def robot_counts(host: ServiceHost, name: str) -> ServiceCounters:
    return host.counters()[name]


# -- calls that end well or badly --------------------------------------------------------------


def test_a_call_returns_the_typed_response_and_both_ends_count_it(
    bus: MemoryBus, host: ServiceHost
) -> None:
    caller = caller_on(bus)
    response = caller.call("robot1", "dock", {}, 2.0, type="std_srvs/srv/Trigger")
    assert type(response) is TYPES.struct("std_srvs/srv/Trigger_Response")
    assert (response.success, response.message) == (True, "docked")
    lamp = caller.call("robot1", "lamp", {"data": True}, 2.0, type="std_srvs/srv/SetBool")
    assert (lamp.success, lamp.message) == (True, "lamp True")
    assert caller.counters()["robot1"]["dock"] == CallCounters(
        calls=1, ok=1, latency_ms_max=caller.counters()["robot1"]["dock"].latency_ms_max
    )
    wait_until(lambda: robot_counts(host, "dock").ok == 1, what="the robot's count")
    counted = robot_counts(host, "dock")
    assert (counted.calls, counted.failed, counted.timeouts) == (1, 0, 0)
    assert counted.handler_ms_max is not None


def test_a_handler_that_raises_gives_service_failed_with_its_text(
    bus: MemoryBus, host: ServiceHost
) -> None:
    caller = caller_on(bus)
    with pytest.raises(ServiceFailed) as failed:
        caller.call("robot1", "jammed", {}, 2.0, type="std_srvs/srv/Trigger")
    assert failed.value.error == "RuntimeError: the dock is blocked"
    assert "the dock is blocked" in str(failed.value)
    wait_until(lambda: robot_counts(host, "jammed").failed == 1, what="the robot's failure")
    assert robot_counts(host, "jammed").last_error == "RuntimeError: the dock is blocked"
    assert caller.counters()["robot1"]["jammed"].failed == 1


def test_a_response_that_does_not_fit_its_type_is_a_failure(
    bus: MemoryBus, host: ServiceHost
) -> None:
    with pytest.raises(ServiceFailed, match="does not fit std_srvs/srv/Trigger_Response"):
        caller_on(bus).call("robot1", "wrong", {}, 2.0, type="std_srvs/srv/Trigger")


def test_a_handler_that_hangs_past_the_timeout_is_a_timeout_at_both_ends_and_busy_beyond_its_queue(
    bus: MemoryBus, host: ServiceHost
) -> None:
    caller = caller_on(bus)
    trigger = "std_srvs/srv/Trigger"
    with pytest.raises(ServiceTimeout) as first:
        caller.call("robot1", "slow", {}, 0.2, type=trigger)
    assert first.value.reached, "the robot took the call: a slow handler, not a lost request"
    # the handler still hangs: one call waits in the queue (queue = 1), the next is refused
    queued = caller.call_async("robot1", "slow", {}, 0.2, type=trigger)
    with pytest.raises(ServiceBusy, match="busy"):
        caller.call("robot1", "slow", {}, 0.2, type=trigger)
    with pytest.raises(ServiceTimeout):
        queued.result(2.0)
    RELEASE.set()
    # the hung call ends late (a timeout), the queued one is not run (its caller left)
    wait_until(lambda: robot_counts(host, "slow").timeouts == 2, what="the robot's timeouts")
    counted = robot_counts(host, "slow")
    assert (counted.calls, counted.ok, counted.busy) == (3, 0, 1)
    assert "past the caller's timeout" in counted.last_error
    mine = caller.counters()["robot1"]["slow"]
    assert (mine.calls, mine.timeouts, mine.busy, mine.pending) == (3, 2, 1, 0)


# -- bad input ------------------------------------------------------------------------------------


def test_a_request_that_does_not_fit_is_refused_before_it_is_sent_naming_the_field(
    bus: MemoryBus, host: ServiceHost
) -> None:
    caller = caller_on(bus)
    with pytest.raises(ServiceTypeError, match=r"data"):
        caller.call("robot1", "lamp", {"data": "on"}, 1.0, type="std_srvs/srv/SetBool")
    with pytest.raises(ServiceTypeError, match=r"colour"):
        caller.call("robot1", "lamp", {"data": True, "colour": 1}, 1.0, type="std_srvs/srv/SetBool")
    with pytest.raises(ServiceTypeError, match="did you mean std_srvs/srv/Trigger"):
        caller.call("robot1", "dock", {}, 1.0, type="std_srvs/srv/Triger")
    with pytest.raises(ServiceTypeError, match="timeout"):
        caller.call("robot1", "dock", {}, 0.0, type="std_srvs/srv/Trigger")
    assert caller.counters()["robot1"]["lamp"].type_errors == 2
    assert robot_counts(host, "lamp").calls == 0, "nothing reached the robot"


def test_the_robot_refuses_another_service_type_and_a_request_that_does_not_fit(
    bus: MemoryBus, host: ServiceHost
) -> None:
    caller = caller_on(bus)
    with pytest.raises(
        ServiceTypeError, match="lamp is std_srvs/srv/SetBool, not std_srvs/srv/Trigger"
    ):
        caller.call("robot1", "lamp", {}, 1.0, type="std_srvs/srv/Trigger")
    # a caller that is not arpz's: a request whose body does not fit SetBool_Request
    replies = raw_query(bus, "lamp", encode(bad_setbool_request()))
    assert [r.status for r in replies] == [SERVICE_TYPE_ERROR]
    assert "field 'data'" in replies[0].error
    assert raw_query(bus, "lamp", b"\xc1 not msgpack")[0].status == SERVICE_BAD_REQUEST
    counted = robot_counts(host, "lamp")
    assert (counted.calls, counted.type_errors, counted.ok) == (2, 2, 0)
    assert host.bad_requests == 1


def bad_setbool_request() -> ServiceRequest:
    return ServiceRequest(
        "std_srvs/srv/SetBool", msgspec.Raw(msgspec.msgpack.encode(["on"])), 1000, "raw", 7
    )


def raw_query(bus: MemoryBus, name: str, payload: bytes) -> list[Any]:
    done = threading.Event()
    got: list[bytes] = []
    MemoryTransport(bus).query(
        keys.service_key(FLEET, "robot1", name), payload, got.append, done.set, timeout_s=1.0
    )
    assert done.wait(2.0)
    return [SERVICE_REPLY_DECODER.decode(p) for p in got]


def test_an_unknown_service_name_is_answered_with_the_names_served(
    bus: MemoryBus, host: ServiceHost
) -> None:
    with pytest.raises(NoSuchService, match=r"serves no service 'dok' \(it serves: dock"):
        caller_on(bus).call("robot1", "dok", {}, 1.0, type="std_srvs/srv/Trigger")
    assert host.unknown == 1


def test_the_announced_type_is_used_and_a_different_one_refused() -> None:
    bus = MemoryBus()
    caller = ServiceCaller(
        MemoryTransport(bus),
        FLEET,
        types=TYPES,
        directory=lambda robot: RobotServices(True, {"dock": "std_srvs/srv/Trigger"}),
    )
    with pytest.raises(
        ServiceTypeError, match="dock is std_srvs/srv/Trigger, not std_srvs/srv/Empty"
    ):
        caller.call("robot1", "dock", {}, 1.0, type="std_srvs/srv/Empty")
    with pytest.raises(NoSuchService, match="it serves: dock"):
        caller.call("robot1", "undock", {}, 1.0)
    # the announced type, and no queryable on the bus: the robot is gone
    with pytest.raises(RobotGone):
        caller.call("robot1", "dock", {}, 1.0)


def test_a_robot_that_is_not_there_is_gone_and_a_hidden_one_refused(bus: MemoryBus) -> None:
    trigger = "std_srvs/srv/Trigger"
    absent = caller_on(bus, present=False)
    with pytest.raises(RobotGone, match="not present"):
        absent.call("robot1", "dock", {}, 5.0, type=trigger)
    # present, but no queryable this session can see: hidden by access control, or none
    with pytest.raises(ServiceRefused, match="refused by access control"):
        caller_on(bus, present=True, access_control=True).call(
            "robot1", "dock", {}, 5.0, type=trigger
        )
    with pytest.raises(RobotGone, match="serves nothing"):
        caller_on(bus, present=True).call("robot1", "dock", {}, 5.0, type=trigger)
    with pytest.raises(RobotGone, match="no robot robot1 answers"):
        caller_on(bus, present=None).call("robot1", "dock", {}, 5.0, type=trigger)
    assert absent.counters()["robot1"]["dock"].gone == 1


def test_no_reply_at_all_is_a_timeout_or_under_access_control_a_refusal(bus: MemoryBus) -> None:
    silent = MemoryTransport(bus)  # takes every call and never answers (a router that drops it)
    silent.serve_deferred(keys.robot_services(FLEET, "robot1"), lambda key, payload, r: None)
    with pytest.raises(ServiceTimeout) as timeout:
        caller_on(bus).call("robot1", "dock", {}, 0.2, type="std_srvs/srv/Trigger")
    assert not timeout.value.reached
    with pytest.raises(ServiceRefused, match="no reply at all"):
        caller_on(bus, access_control=True).call(
            "robot1", "dock", {}, 0.2, type="std_srvs/srv/Trigger"
        )


def test_fleet_services_follows_presence_and_announcements(bus: MemoryBus) -> None:
    from arpz.core.messages import Announce

    watching = FleetServices(MemoryTransport(bus), FLEET)
    robot = MemoryTransport(bus)
    token = robot.declare_token(keys.presence_key(FLEET, "robot1"))
    announce = Announce("robot1", "abc", [], ["hello"], services={"dock": "std_srvs/srv/Trigger"})
    robot.put(keys.announce_key(FLEET, "robot1"), encode(announce))
    assert watching("robot1") == RobotServices(True, {"dock": "std_srvs/srv/Trigger"})
    token.undeclare()
    assert watching("robot1").present is False
    assert list(watching.robots()) == ["robot1"]
    watching.close()


# -- the robot's configuration ----------------------------------------------------------------


def test_service_settings_are_checked() -> None:
    for bad, why in [
        ({"type": "std_srvs/msg/Trigger"}, "package/srv/Name"),
        ({"handler": "no_colon"}, "module.path:function"),
        ({"name": "Dock"}, "service name"),
        ({"queue": 0}, "queue"),
    ]:
        with pytest.raises(ConfigError, match=why):
            robot_config({**service("dock", "dock"), **bad})
    with pytest.raises(ConfigError, match="unique, repeated: dock"):
        robot_config(service("dock", "dock"), service("dock", "jammed"))


def test_handlers_that_cannot_be_made_stop_the_robot_with_the_setting_named(bus: MemoryBus) -> None:
    cases = [
        (service("dock", "nowhere"), "has no 'nowhere'"),
        ({**service("dock", "dock"), "handler": "no.such.module:dock"}, "cannot import"),
        (service("dock", "dock", options={"x": 1}), "takes no options"),
        (service("lamp", "Lamp", "std_srvs/srv/SetBool"), "KeyError"),
        (service("dock", "NOT_CALLABLE"), "neither a function nor a class"),
        (service("dock", "dock", "std_srvs/srv/Trigga"), "did you mean std_srvs/srv/Trigger"),
    ]
    for entry, why in cases:
        with pytest.raises(ServiceConfigError, match=why):
            ServiceHost(robot_config(entry), MemoryTransport(bus), TYPES)
    lamp = load_handler(robot_config(service("lamp", "Lamp", options={"prefix": "p"})).services[0])
    assert isinstance(lamp, Lamp) and lamp.prefix == "p"


def test_the_agent_announces_its_services_and_reports_their_counts(bus: MemoryBus) -> None:
    config = robot_config(service("dock", "dock"))
    agent = RobotAgent(config, MemoryTransport(bus))
    try:
        agent.services.start()
        announced: list[Any] = []
        from arpz.core.messages import ANNOUNCE_DECODER

        MemoryTransport(bus).subscribe(
            keys.announce_key(FLEET, "robot1"),
            lambda k, p, a: announced.append(ANNOUNCE_DECODER.decode(p)),
        )
        agent._publish_announce(0.0)
        assert announced[-1].services == {"dock": "std_srvs/srv/Trigger"}
        caller_on(bus).call("robot1", "dock", {}, 2.0, type="std_srvs/srv/Trigger")
        wait_until(lambda: agent.stats(final=False).services["dock"].ok == 1, what="stats")
    finally:
        agent.services.close()


# -- the pieces ---------------------------------------------------------------------------------


def test_a_teams_own_services_come_from_srv_files(tmp_path: Path) -> None:
    srv = tmp_path / "mylab" / "srv"
    srv.mkdir(parents=True)
    (srv / "Dock.srv").write_text("string station\nfloat64 speed\n---\nbool docked\nPath path\n")
    (tmp_path / "mylab" / "msg").mkdir()
    (tmp_path / "mylab" / "msg" / "Path.msg").write_text("float64[] xs\n")
    types = MessageTypes()
    types.add_msg_paths([tmp_path])
    assert types.add_srv_paths([tmp_path]) == ["mylab/srv/Dock"]
    request, response = types.service_types("mylab/srv/Dock")
    assert types.fields(request) == ["station", "speed"]
    assert types.fields(response) == ["docked", "path"]
    message = types.check_service_message(response, {"docked": True, "path": {"xs": [1.0]}})
    assert types.decode(response, types.encode(message)) == message
    (srv / "Bad.srv").write_text("string station\n")
    with pytest.raises(MessageTypeError, match=r"Bad\.srv.*one line '---'"):
        MessageTypes().add_srv_paths([tmp_path])
    (srv / "Bad.srv").write_text("flot64 x\n---\n")
    with pytest.raises(MessageTypeError, match=r"Bad\.srv"):
        MessageTypes().add_srv_paths([tmp_path])


def test_the_standard_services_are_known_with_their_request_and_response_types() -> None:
    names = TYPES.service_names()
    assert {"std_srvs/srv/Trigger", "std_srvs/srv/SetBool", "nav_msgs/srv/GetPlan"} <= set(names)
    assert TYPES.service_types("std_srvs/srv/SetBool") == (
        "std_srvs/srv/SetBool_Request",
        "std_srvs/srv/SetBool_Response",
    )
    plan = TYPES.service_types("nav_msgs/srv/GetPlan")[1]
    assert TYPES.field_defs(plan)[0].message == "nav_msgs/msg/Path"
    with pytest.raises(MessageTypeError, match="not a ROS 2 service type name"):
        TYPES.require_service("std_srvs/msg/Trigger")
    empty = TYPES.check_service_message("std_srvs/srv/Trigger_Request", {})
    assert TYPES.to_cdr("std_srvs/srv/Trigger_Request", empty) == b"\x00\x01\x00\x00\x00"


def test_field_error_names_the_field_of_an_array_like_message() -> None:
    assert field_error("Expected `bool`, got `str` - at `$[0]`", ["data"]) == (
        "Expected `bool`, got `str` - at field 'data'"
    )
    assert field_error("Expected `int` - at `$[1][2]`", ["a", "b"]) == (
        "Expected `int` - at field 'b[2]'"
    )
    assert field_error("no position", ["a"]) == "no position"


def test_the_summary_puts_both_ends_side_by_side() -> None:
    summary = services_summary(
        {"robot1": {"dock": CallCounters(calls=2, ok=1, timeouts=1)}},
        {"robot1": {"dock": ServiceCounters(calls=3, ok=2, timeouts=1)}, "robot2": {}},
    )
    dock = summary["robot1"]["dock"]
    assert dock["caller"]["calls"] == 2 and dock["caller"]["pending"] == 0
    assert dock["robot"]["calls"] == 3
    assert summary["robot2"] == {}


def test_memory_query_ends_once_at_the_timeout_and_drops_later_replies(bus: MemoryBus) -> None:
    held: list[Any] = []
    server = MemoryTransport(bus)
    server.serve_deferred("a/*", lambda key, payload, responder: held.append(responder))
    ends: list[int] = []
    got: list[bytes] = []
    MemoryTransport(bus).query("a/b", b"q", got.append, lambda: ends.append(1), timeout_s=0.05)
    wait_until(lambda: ends == [1], what="the end at the timeout")
    assert held[0].reply(b"late") is False and got == []
    held[0].finish()
    assert ends == [1]
    MemoryTransport(bus).query("b/c", b"q", got.append, lambda: ends.append(2), timeout_s=5)
    assert ends == [1, 2], "no queryable: over at once"


def test_replies_are_delivered_in_order_accepted_first(bus: MemoryBus, host: ServiceHost) -> None:
    request = ServiceRequest(
        "std_srvs/srv/Trigger",
        msgspec.Raw(TYPES.encode(TYPES.check_service_message("std_srvs/srv/Trigger_Request", {}))),
        1000,
        "raw",
        3,
    )
    replies = raw_query(bus, "dock", encode(request))
    assert [r.status for r in replies] == [SERVICE_ACCEPTED, SERVICE_OK]
    assert all(r.id == 3 for r in replies)


def test_the_ceddps_caller_uses_its_registry_and_its_calls_reach_the_summary() -> None:
    from arpz.ceddp.server import CeddpServer
    from arpz.core.config import CeddpConfig

    bus = MemoryBus()
    server = CeddpServer(
        CeddpConfig(fleet=FLEET, rrd="unused.rrd", metrics_period_s=0.05), MemoryTransport(bus)
    )
    server.start()
    agent = RobotAgent(
        robot_config(service("dock", "dock"), service("jammed", "jammed")), MemoryTransport(bus)
    )
    try:
        with pytest.raises(RobotGone, match="not present"):
            server.services.call("robot1", "dock", {}, 1.0, type="std_srvs/srv/Trigger")
        agent.start()
        wait_until(
            lambda: (
                (record := server.robots.get("robot1")) is not None
                and record.alive
                and record.announce is not None
            ),
            what="the robot in the CEDDP's registry",
        )
        # the type from the robot's announcement, through the registry
        assert server.services.call("robot1", "dock", {}, 2.0).message == "docked"
        with pytest.raises(ServiceFailed):
            server.services.call("robot1", "jammed", {}, 2.0)
        with pytest.raises(NoSuchService, match="it serves: dock, jammed"):
            server.services.call("robot1", "undock", {}, 2.0)
    finally:
        agent.shutdown()
        summary = server.shutdown()
    dock = summary["services"]["robot1"]["dock"]
    assert (dock["caller"]["calls"], dock["caller"]["ok"], dock["caller"]["gone"]) == (2, 1, 1)
    assert (dock["robot"]["calls"], dock["robot"]["ok"]) == (1, 1)
    jammed = summary["services"]["robot1"]["jammed"]
    assert jammed["caller"]["failed"] == jammed["robot"]["failed"] == 1
    assert summary["services"]["robot1"]["undock"]["robot"] is None
