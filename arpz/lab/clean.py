"""``python -m arpz lab clean``: remove what labs whose owner died left behind (a SIGKILLed run,
a crashed test), and nothing else.

A lab is found by its names only (``arpzlab-<id>-*`` namespaces, ``azl<id>*`` interfaces,
``arpzlab*`` nftables tables in the host's namespace, ``/run/arpz-lab/<id>.json``). A lab whose
owner process still runs is left alone unless ``include_live`` (``--all``): a test worker's lab
beside a clean-up is not an orphan.
"""

from __future__ import annotations

import json
import subprocess
from dataclasses import dataclass, field

from arpz.lab.names import NFT_TABLE, lab_id_of_interface, lab_id_of_namespace
from arpz.lab.net import (
    RUN_DIR,
    check_available,
    kill_pids_in,
    owner_alive,
    remove_namespace,
    tool,
)


@dataclass
class CleanReport:
    labs: list[str] = field(default_factory=list)
    namespaces: list[str] = field(default_factory=list)
    interfaces: list[str] = field(default_factory=list)
    tables: list[str] = field(default_factory=list)
    killed: list[int] = field(default_factory=list)
    #: labs left alone because their owner still runs
    live: list[str] = field(default_factory=list)

    def lines(self) -> list[str]:
        if not (self.labs or self.live or self.tables):
            return ["nothing of a lab left on this machine"]
        lines = []
        if self.labs:
            lines.append(
                f"removed {len(self.labs)} lab(s) ({', '.join(self.labs)}): "
                f"{len(self.namespaces)} namespaces, {len(self.interfaces)} host interfaces, "
                f"{len(self.killed)} processes killed"
            )
        if self.tables:
            lines.append(f"removed nftables tables {', '.join(self.tables)}")
        if self.live:
            lines.append(
                f"left {len(self.live)} lab(s) whose owner still runs ({', '.join(self.live)}); "
                "--all removes them too"
            )
        return lines


def clean(*, include_live: bool = False) -> CleanReport:
    check_available()
    from pyroute2 import IPRoute, netns  # importable: check_available says so

    report = CleanReport()
    namespaces: dict[str, list[str]] = {}
    for name in netns.listnetns():
        lab_id = lab_id_of_namespace(name)
        if lab_id is not None:
            namespaces.setdefault(lab_id, []).append(name)
    with IPRoute() as ipr:
        interfaces = {
            str(link.get_attr("IFLA_IFNAME")): int(link["index"]) for link in ipr.get_links()
        }
    owned = {path.stem for path in RUN_DIR.glob("*.json")} if RUN_DIR.exists() else set()
    found = set(namespaces) | owned
    found |= {i for i in map(lab_id_of_interface, interfaces) if i is not None}
    for lab_id in sorted(found):
        if owner_alive(lab_id) and not include_live:
            report.live.append(lab_id)
            continue
        report.labs.append(lab_id)
        mine = namespaces.get(lab_id, [])
        report.killed += kill_pids_in(mine)
        for name in mine:
            remove_namespace(name)
            report.namespaces.append(name)
        with IPRoute() as ipr:
            for ifname, index in interfaces.items():
                if lab_id_of_interface(ifname) == lab_id and ipr.link_lookup(ifname=ifname):
                    ipr.link("del", index=index)
                    report.interfaces.append(ifname)
        (RUN_DIR / f"{lab_id}.json").unlink(missing_ok=True)
    if not report.live or include_live:
        report.tables = _remove_host_tables()
    return report


def _remove_host_tables() -> list[str]:
    """The lab never writes tables in the host's namespace; one named like the lab's is a
    leftover (of an older arpz), removed while no lab is running."""
    nft = tool("nft")
    done = subprocess.run(
        [nft, "-j", "list", "tables"], capture_output=True, text=True, timeout=30, check=False
    )
    if done.returncode != 0:
        return []
    removed = []
    for entry in json.loads(done.stdout).get("nftables", []):
        table = entry.get("table") if isinstance(entry, dict) else None
        if isinstance(table, dict) and str(table.get("name", "")).startswith(NFT_TABLE):
            family, name = str(table["family"]), str(table["name"])
            subprocess.run([nft, "delete", "table", family, name], timeout=30, check=False)
            removed.append(f"{family} {name}")
    return removed
