"""Service handlers a team would write, served by a real robot process from its TOML's
``[[services]]`` in tests/integration/test_services.py and test_security.py."""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

#: the robot TOML tables of the services below (``write_robot``'s ``extra``)
SERVICES = """
[[services]]
name = "dock"
type = "std_srvs/srv/Trigger"
handler = "tests.integration.service_handlers:dock"

[[services]]
name = "lamp"
type = "std_srvs/srv/SetBool"
handler = "tests.integration.service_handlers:Lamp"
options = { label = "lamp" }

[[services]]
name = "jammed"
type = "std_srvs/srv/Trigger"
handler = "tests.integration.service_handlers:jammed"

[[services]]
name = "slow"
type = "std_srvs/srv/Trigger"
handler = "tests.integration.service_handlers:slow"
"""
#: how long ``slow`` takes
SLOW_S = 1.0


def dock(request: Any) -> dict[str, object]:
    return {"success": True, "message": "docked"}


def jammed(request: Any) -> dict[str, object]:
    raise RuntimeError("the dock is blocked")


def slow(request: Any) -> dict[str, object]:
    time.sleep(SLOW_S)
    return {"success": True, "message": "late"}


class Lamp:
    """A handler class, made with its options: switches a lamp (SetBool)."""

    def __init__(self, options: Mapping[str, Any]) -> None:
        self.label = str(options["label"])

    def __call__(self, request: Any) -> dict[str, object]:
        return {"success": True, "message": f"{self.label} {'on' if request.data else 'off'}"}
