"""A user-space lossy-link emulator (the kernel's netem qdisc is not available): docs/netem.md."""

from arpz.netem.model import Counters, GilbertElliott, Impairments, Outage, frames_of
from arpz.netem.proxy import NetemProxy, ProxyReport, parse_udp_endpoint

__all__ = [
    "Counters",
    "GilbertElliott",
    "Impairments",
    "NetemProxy",
    "Outage",
    "ProxyReport",
    "frames_of",
    "parse_udp_endpoint",
]
