"""What the kernel lab calls things: its errors, the names of its namespaces and interfaces, its
addresses. Pure (no I/O), so the rules are unit-tested.

Every name starts with the lab prefix and the run's id, so ``python -m arpz lab clean`` can find
what a crashed run left and touch nothing else:

- namespaces ``arpzlab-<id>-ap`` (the access point and router), ``arpzlab-<id>-ceddp``,
  ``arpzlab-<id>-<robot>``;
- interfaces ``azl<id><role>`` (Linux allows 15 characters): ``b0`` / ``b1`` the two access
  point bridges (two subnets, for roaming), ``c`` / ``ca`` the CEDDP's veth and its access point
  end, ``r<N>`` / ``r<N>a`` robot N's veth and its access point end.
"""

from __future__ import annotations

import re
import secrets
from dataclasses import dataclass

from arpz.core.errors import ArpzError

#: every namespace of every lab starts with this
NS_PREFIX = "arpzlab-"
#: every interface of every lab starts with this (namespace names are free, interface names
#: have 15 characters)
IF_PREFIX = "azl"
#: the nftables table of a lab, in each of its namespaces
NFT_TABLE = "arpzlab"
#: Linux's limit on an interface name (IFNAMSIZ - 1)
IFNAME_MAX = 15
#: robots per lab: one /24 per access point, addresses .11 up
MAX_ROBOTS = 240
#: the wired server subnet (CEDDP and the access point's router port)
SERVER_NET = "10.77.0"
#: the access points' subnets: bridge b0 and bridge b1 (the one a robot roams to)
WIFI_NETS = ("10.77.1", "10.77.2")
PREFIXLEN = 24

_ID = re.compile(r"^[0-9a-f]{6}$")
_NS = re.compile(rf"^{NS_PREFIX}([0-9a-f]{{6}})-")
_IF = re.compile(rf"^{IF_PREFIX}([0-9a-f]{{6}})")


class LabError(ArpzError, RuntimeError):
    """Building, changing or tearing down a lab failed; the message says which step."""


class LabUnavailable(LabError):
    """This machine cannot run the lab: the message names what is missing (root or
    CAP_NET_ADMIN/CAP_SYS_ADMIN, ``nft``, ``ip``, pyroute2, Linux)."""


class LabInterrupted(LabError):
    """SIGINT or SIGTERM arrived while a lab was up (``interrupt_on_signals``): raised so that
    the lab is torn down on the way out."""


def new_lab_id() -> str:
    """Six random hex digits: unique enough per machine, short enough for interface names."""
    return secrets.token_hex(3)


def lab_id_of_namespace(name: str) -> str | None:
    match = _NS.match(name)
    return match.group(1) if match else None


def lab_id_of_interface(name: str) -> str | None:
    match = _IF.match(name)
    return match.group(1) if match else None


@dataclass(frozen=True)
class LabNames:
    """Every name of the lab with id ``lab_id``."""

    lab_id: str

    def __post_init__(self) -> None:
        if not _ID.match(self.lab_id):
            raise ValueError(f"a lab id is 6 lowercase hex digits, got {self.lab_id!r}")

    def namespace(self, role: str) -> str:
        """``ap``, ``ceddp`` or a robot's name."""
        return f"{NS_PREFIX}{self.lab_id}-{role}"

    def interface(self, role: str) -> str:
        name = f"{IF_PREFIX}{self.lab_id}{role}"
        if len(name) > IFNAME_MAX:
            raise ValueError(f"interface name {name!r} is longer than {IFNAME_MAX} characters")
        return name

    @property
    def ap(self) -> str:
        return self.namespace("ap")

    @property
    def ceddp(self) -> str:
        return self.namespace("ceddp")

    def bridge(self, subnet: int) -> str:
        return self.interface(f"b{subnet}")

    def robot_if(self, index: int) -> str:
        """Robot ``index``'s end of its veth (in its namespace)."""
        return self.interface(f"r{index}")

    def robot_ap_if(self, index: int) -> str:
        """The access point's end of robot ``index``'s veth (a port of a bridge)."""
        return self.interface(f"r{index}a")


def robot_address(index: int, subnet: int) -> str:
    """Robot ``index`` (1-based) on access point ``subnet`` (0 or 1)."""
    if not 1 <= index <= MAX_ROBOTS:
        raise ValueError(f"robot index must be 1..{MAX_ROBOTS}, got {index}")
    return f"{WIFI_NETS[subnet]}.{10 + index}"


def gateway(subnet: int) -> str:
    """The access point's address on ``subnet``: the robots' default route."""
    return f"{WIFI_NETS[subnet]}.1"


CEDDP_ADDRESS = f"{SERVER_NET}.2"
AP_SERVER_ADDRESS = f"{SERVER_NET}.1"


def check_robot_names(robots: list[str]) -> None:
    """Robot names become namespace names: lowercase letters, digits, '_' and '-', unique."""
    if not 1 <= len(robots) <= MAX_ROBOTS:
        raise ValueError(f"a lab has 1..{MAX_ROBOTS} robots, got {len(robots)}")
    if len(set(robots)) != len(robots):
        raise ValueError(f"robot names must be unique: {robots}")
    for name in robots:
        if not re.match(r"^[a-z0-9][a-z0-9_\-]{0,31}$", name) or name in ("ap", "ceddp"):
            raise ValueError(
                f"robot name {name!r}: 1-32 lowercase letters, digits, '_' or '-', "
                "and not 'ap' or 'ceddp'"
            )
