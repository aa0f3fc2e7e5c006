"""The bytes robots sent over their lab links (robot -> access point), from the lab's nftables
counters: the proof that a cell's samples crossed the kernel links, whatever the middleware packs
into one frame (Fast DDS puts several RTPS DATA submessages in a datagram, so frames alone can be
fewer than samples). arpz.lab counts frames; this reads the bytes of the same counters."""

from __future__ import annotations

import json
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from arpz.lab import Lab


def uplink_bytes(lab: Lab) -> int:
    """Bytes every robot's uplink chain has seen since the lab was built (frames dropped by the
    profile included: they were sent)."""
    from arpz.lab import nft
    from arpz.lab.names import NFT_TABLE
    from arpz.lab.net import tool

    listing = [tool("nft"), "-j", "list", "counters", "table", "netdev", NFT_TABLE]
    done = lab.run(lab.names.ap, listing)
    wanted = {nft.seen_counter(link.up_chain) for link in lab.robots.values()}
    total = 0
    for entry in json.loads(done.stdout).get("nftables", []):
        counter = entry.get("counter") if isinstance(entry, dict) else None
        if isinstance(counter, dict) and counter.get("name") in wanted:
            total += int(counter.get("bytes") or 0)
    return total
