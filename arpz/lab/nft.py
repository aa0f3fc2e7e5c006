"""The nftables text of the lab's radio impairments. Pure: the lab pipes it to ``nft -f -``.

Loss is applied where a radio loses a frame: on the **receiving** end of each direction, in a
``netdev`` table's ingress hook (the first thing the receiving interface does with a frame), so
the sender's kernel sees its frame leave normally and learns nothing, as on WiFi:

- uplink (robot -> CEDDP): ingress of the access point's end of the robot's veth, chain
  ``up_r<N>`` in the access point's namespace;
- downlink (CEDDP -> robot): ingress of the robot's own end, chain ``down_r<N>`` in the robot's
  namespace.

Each chain counts what it sees and what it drops in named counters (kept across the chain's
rewrites, so they add up over a whole run). A loss of P % is ``numgen random mod 1000 < 10 P
drop``: per-frame, independent, in steps of 0.1 %. A dead zone is a plain ``drop``. A change
flushes the chain and writes it again in one ``nft -f`` transaction, so no frame sees half a
change.
"""

from __future__ import annotations

from arpz.lab.names import NFT_TABLE

#: numgen's modulus: loss in steps of 0.1 %
MODULUS = 1000


def permille(loss_pct: float) -> int:
    return round(loss_pct * MODULUS / 100)


def seen_counter(chain: str) -> str:
    return f"{chain}_seen"


def dropped_counter(chain: str) -> str:
    return f"{chain}_dropped"


def table_ruleset(chains: dict[str, str]) -> str:
    """The lab's table in one namespace: an ingress chain per ``{chain: device}``, each
    accepting everything (and counting it) until ``chain_update`` says otherwise. The table is
    deleted first if it exists (``add`` then ``delete``: a no-op table to delete)."""
    lines = [
        f"add table netdev {NFT_TABLE}",
        f"delete table netdev {NFT_TABLE}",
        f"table netdev {NFT_TABLE} {{",
    ]
    for chain, device in chains.items():
        lines += [
            f"  counter {seen_counter(chain)} {{ }}",
            f"  counter {dropped_counter(chain)} {{ }}",
            f"  chain {chain} {{",
            f'    type filter hook ingress device "{device}" priority filter; policy accept;',
            f'    counter name "{seen_counter(chain)}"',
            "  }",
        ]
    lines.append("}")
    return "\n".join(lines) + "\n"


def chain_update(chain: str, *, loss_pct: float, dead: bool) -> str:
    """Rewrite ``chain``: count, then drop everything (``dead``), ``loss_pct`` % at random, or
    nothing."""
    lines = [
        f"flush chain netdev {NFT_TABLE} {chain}",
        f'add rule netdev {NFT_TABLE} {chain} counter name "{seen_counter(chain)}"',
    ]
    drop = f'counter name "{dropped_counter(chain)}" drop'
    if dead or permille(loss_pct) >= MODULUS:  # 100 %: numgen has no value < 1000 to spare
        lines.append(f"add rule netdev {NFT_TABLE} {chain} {drop}")
    elif permille(loss_pct) > 0:
        lines.append(
            f"add rule netdev {NFT_TABLE} {chain} "
            f"numgen random mod {MODULUS} < {permille(loss_pct)} {drop}"
        )
    return "\n".join(lines) + "\n"


def parse_counters(listing: dict[str, object]) -> dict[str, int]:
    """``{counter name: packets}`` from ``nft -j list counters table netdev arpzlab``."""
    found: dict[str, int] = {}
    entries = listing.get("nftables", [])
    assert isinstance(entries, list)
    for entry in entries:
        counter = entry.get("counter") if isinstance(entry, dict) else None
        if isinstance(counter, dict):
            found[str(counter["name"])] = int(counter["packets"])
    return found
