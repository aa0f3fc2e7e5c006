#!/usr/bin/env python3
"""Make the certificates and Zenoh configurations of one arpz fleet with openssl.

    python deploy/tls/make_fleet_certs.py --out fleet-tls --fleet lab \\
        --server-name ceddp.lab --server-ip 192.168.1.10 robot1 robot2 robot3

writes into ``--out``:

- ``ca.pem`` / ``ca.key``: the fleet CA. Keep ``ca.key`` off the robots (and ideally offline):
  whoever holds it can mint a certificate for any robot id.
- ``ceddp.pem`` / ``ceddp.key``: the CEDDP's server certificate, valid for every ``--server-name``
  and ``--server-ip`` (robots check that the address they dial is in it).
- ``{robot}.pem`` / ``{robot}.key`` for each robot, with CN = the robot id (and the same for
  each ``--observer``: a read-only client such as a dashboard or a logger; and for each
  ``--operator``: an observer that may also call the robots' services, ``arpz service call``).
  The router's access control matches this CN, so the CN IS the robot's identity: a robot
  holding ``robot2.pem`` can only ever speak as robot2.
- ``zenoh/ceddp-router.json5`` and ``zenoh/{robot}-client.json5``: the router configuration
  (mutual TLS + access control, one subject per robot, because Zenoh cannot substitute the CN
  into a key expression; listening on ``quic/`` and ``tls/``) and each robot's client
  configuration (connecting over ``quic/``, the link that holds latency on a lossy radio:
  docs/deploy.md). ``--paths-on-hosts /etc/arpz/tls``
  writes the paths the files will have once installed instead of the ``--out`` paths.
- with ``--usrpwd``: ``passwords.txt`` (the router's user:password dictionary, random passwords),
  ``zenoh/ceddp-router-usrpwd.json5`` (server-only TLS + user/password + the same access control
  by username) and ``zenoh/{robot}-client-usrpwd.json5``.

Running it again keeps the CA and every existing certificate and key (so adding ``robot4`` later
does not invalidate the others) and rewrites the Zenoh files for the robots named. Only openssl
(>= 1.1.1) and the Python standard library are needed, so it runs on the server or on a laptop.
``deploy/zenoh/*.json5`` in the repository are this script's output for fleet ``lab`` with
``--paths-on-hosts /etc/arpz/tls`` (a test keeps them in step).
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import re
import secrets
import subprocess
import sys
import tempfile
from pathlib import Path

_CHUNK = re.compile(r"^[a-z0-9][a-z0-9_\-]*$")
#: every message kind the access control knows (zenoh 1.x)
ALL_MESSAGES = [
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "liveliness_query",
    "declare_liveliness_subscriber",
]
#: what a robot may send into the router on its own keys
ROBOT_SENDS = ["put", "delete", "liveliness_token"]
#: what a robot may declare to receive something
ROBOT_SUBSCRIBES = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"]
#: what the router may hand to a robot on the keys it receives
ROBOT_RECEIVES = ["put", "delete", "liveliness_token"]
#: what a robot sends to serve its services (``srv/*``: docs/nodes.md "Services"), and what a
#: caller is handed back (the robots' queryables, so that its session routes the call, and
#: their replies)
SERVES = ["declare_queryable", "reply"]


class CertError(RuntimeError):
    """openssl failed, or an argument cannot be used; the message says which and why."""


def _openssl(*args: str) -> None:
    try:
        done = subprocess.run(["openssl", *args], capture_output=True, text=True, check=False)
    except FileNotFoundError:
        raise CertError("openssl is not installed (apt install openssl)") from None
    if done.returncode != 0:
        raise CertError(f"openssl {' '.join(args[:2])} failed: {done.stderr.strip()}")


def _new_key(path: Path) -> None:
    """An ECDSA P-256 key: small, fast to verify on a Raspberry Pi, accepted by rustls."""
    _openssl(
        "genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", "-out", str(path)
    )
    path.chmod(0o600)


def make_ca(out: Path, fleet: str, days: int) -> None:
    key, cert = out / "ca.key", out / "ca.pem"
    if key.exists() and cert.exists():
        return
    _new_key(key)
    _openssl(
        "req", "-x509", "-new", "-key", str(key), "-out", str(cert), "-days", str(days),
        "-subj", f"/O=arpz/CN=arpz fleet {fleet} CA",
        "-addext", "basicConstraints=critical,CA:TRUE,pathlen:0",
        "-addext", "keyUsage=critical,keyCertSign,cRLSign",
        "-addext", "subjectKeyIdentifier=hash",
    )  # fmt: skip


def make_leaf(
    out: Path, name: str, common_name: str, *, server: bool, sans: list[str], days: int
) -> None:
    """A certificate signed by the fleet CA; an existing one is kept."""
    key, cert = out / f"{name}.key", out / f"{name}.pem"
    if key.exists() and cert.exists():
        return
    _new_key(key)
    usage = "serverAuth,clientAuth" if server else "clientAuth"
    ext_lines = [
        "basicConstraints=critical,CA:FALSE",
        "keyUsage=critical,digitalSignature",
        f"extendedKeyUsage={usage}",
        "subjectKeyIdentifier=hash",
        "authorityKeyIdentifier=keyid",
    ]
    if sans:
        ext_lines.append("subjectAltName=" + ",".join(sans))
    with tempfile.TemporaryDirectory() as tmp:
        csr, ext = Path(tmp) / "req.csr", Path(tmp) / "ext.cnf"
        ext.write_text("\n".join(ext_lines) + "\n", encoding="utf-8")
        _openssl(
            "req", "-new", "-key", str(key), "-out", str(csr), "-subj", f"/O=arpz/CN={common_name}"
        )
        _openssl(
            "x509", "-req", "-in", str(csr), "-CA", str(out / "ca.pem"),
            "-CAkey", str(out / "ca.key"), "-set_serial", str(secrets.randbits(63)),
            "-days", str(days), "-sha256", "-extfile", str(ext), "-out", str(cert),
        )  # fmt: skip


# ------------------------------------------------------------------------------ Zenoh files


def _rule(rule_id: str, messages: list[str], flow: str, key_exprs: list[str]) -> dict[str, object]:
    return {
        "id": rule_id,
        "messages": messages,
        "flows": [flow],
        "permission": "allow",
        "key_exprs": key_exprs,
    }


def access_control(
    fleet: str,
    robots: list[str],
    *,
    by: str,
    observers: list[str],
    operators: list[str] | None = None,
) -> dict[str, object]:
    """Deny by default; each robot may send only under its own subtree and receive only its own
    ``cmd`` keys, the reliable channel's control traffic of its own keys and the fleet-wide
    ``ceddp`` keys.

    Commands travel through the reliable channel, so a robot's command readers must send their
    ACKNACKs (``cmd/{name}/rel/an/**``) and reader tokens (``cmd/{name}/rel/r/**``), and its
    reader of the QoS assignment does the same under ``ceddp/qos/rel/``. A robot is allowed
    exactly the keys it writes, so a wildcard put (``robot/robotN/*/velocity``) is included in no
    allow rule and falls to the default deny. What only the CEDDP may send is also denied
    explicitly: the command data (``cmd/*``) and the command writers' own traffic (writer
    tokens, heartbeats, resends and GAPs).

    A robot serves its services on ``robot/{robot}/srv/*``: it may declare that queryable and
    reply there, and be handed the queries on it.

    An observer (``--observer``) may subscribe to every key of the fleet, liveliness tokens
    included, and query the CEDDP's clock; it may put, delete and declare nothing, so the arpz
    tools it runs read without writing (docs/security.md, "The observer"). It is not shown the
    robots' service queryables either, so its call of a service ends at once with no reply: an
    observer must not act. An operator (``--operator``) is an observer that may also call the
    robots' services (query ``robot/*/srv/*``, be shown those queryables and get their replies).

    The CEDDP's own session lives inside the router and is not a remote subject, so no rule
    applies to it: it sees and may send everything. ``by`` is ``cert_common_names`` (mTLS) or
    ``usernames`` (user/password).
    """
    rules: list[dict[str, object]] = []
    subjects: list[dict[str, object]] = []
    policies: list[dict[str, object]] = []
    fleet_root = f"arpz/{fleet}"
    clock = f"{fleet_root}/ceddp/clock"
    # what the CEDDP's planners send, asked once at a robot's start (docs/nodes.md)
    contract = f"{fleet_root}/ceddp/commands"
    services = f"{fleet_root}/robot/*/srv/*"
    for robot in robots:
        own = f"{fleet_root}/robot/{robot}"
        qos_reader = f"{fleet_root}/ceddp/qos/rel"
        # Exactly the keys a robot writes (docs/protocol.md), not its whole subtree: an allow
        # applies to a put whose key expression it includes, so with `{own}/**` a wildcard put
        # such as `{own}/*/velocity` was allowed while the `cmd/*` deny (which does not include
        # it) did not apply. Zenoh's `**` also matches nothing: `{own}/stats/**` covers `stats`
        # and its reliable-channel traffic below it.
        sends = [
            *(
                f"{own}/{kind}/**"
                for kind in ("sensor", "frames", "stats", "announce", "telemetry", "qos")
            ),
            f"{own}/presence",
            f"{own}/mode/*",
            # the command readers' ACKNACKs and tokens; the QoS assignment reader's
            f"{own}/cmd/*/rel/an/**",
            f"{own}/cmd/*/rel/r/**",
            f"{qos_reader}/an/**",
            f"{qos_reader}/r/**",
        ]
        receives = [
            f"{own}/cmd/**",
            f"{own}/*/rel/**",
            f"{own}/*/*/rel/**",
            f"{fleet_root}/ceddp/**",
            # its own presence token: a second process with its robot_id is refused at start
            # (docs/operations.md)
            f"{own}/presence",
        ]
        commands_only_from_the_ceddp = [
            f"{own}/cmd/*",
            f"{own}/cmd/*/rel/w/**",
            f"{own}/cmd/*/rel/hb/**",
            f"{own}/cmd/*/rel/rx/**",
        ]
        own_rules = [
            _rule(f"{robot}-send", ROBOT_SENDS, "ingress", sends),
            # an explicit deny wins over an allow: only the CEDDP commands a robot
            {
                **_rule(f"{robot}-no-cmd", ROBOT_SENDS, "ingress", commands_only_from_the_ceddp),
                "permission": "deny",
            },
            # the CEDDP's subscriptions (wildcards over the whole fleet, so not inside the robot's
            # subtree) must reach the robot, or its publishers, which send only while a
            # subscriber matches, would stay silent
            _rule(
                f"{robot}-see-subscribers", ["declare_subscriber"], "egress", [f"{fleet_root}/**"]
            ),
            _rule(f"{robot}-subscribe", ROBOT_SUBSCRIBES, "ingress", receives),
            _rule(f"{robot}-receive", ROBOT_RECEIVES, "egress", receives),
            # the clock exchange (docs/operations.md, "Clock offsets"): a query to the CEDDP's
            # clock and its reply, nothing else
            _rule(f"{robot}-clock-query", ["query"], "ingress", [clock, contract]),
            _rule(
                f"{robot}-clock-reply", ["declare_queryable", "reply"], "egress", [clock, contract]
            ),
            # its services: the queryable on its own srv/* and its replies, and the calls
            # (queries) the router hands it there
            _rule(f"{robot}-serve", SERVES, "ingress", [f"{own}/srv/*"]),
            _rule(f"{robot}-be-called", ["query"], "egress", [f"{own}/srv/*"]),
        ]
        rules.extend(own_rules)
        subjects.append({"id": robot, by: [robot]})
        policies.append(
            {"id": f"{robot}-policy", "rules": [r["id"] for r in own_rules], "subjects": [robot]}
        )
    callers = set(operators or [])
    for observer in [*observers, *(operators or [])]:
        # Read-only: `arpz topic`, `record`, `doctor`, a dashboard, a logger. It may subscribe
        # to the whole fleet, its liveliness tokens included, and put nothing: no sample, no
        # command, no token, no ACKNACK, so it cannot even acknowledge a sample in another
        # reader's name. The arpz tools read in a way that needs no more (BEST_EFFORT readers,
        # plain subscriptions: docs/security.md). Its one request is the clock exchange, for
        # `arpz topic delay`: a query to the CEDDP's clock and its reply, which change nothing.
        watch = [f"{fleet_root}/**"]
        own_rules = [
            _rule(f"{observer}-subscribe", ROBOT_SUBSCRIBES, "ingress", watch),
            _rule(f"{observer}-receive", ROBOT_RECEIVES, "egress", watch),
            _rule(f"{observer}-clock-query", ["query"], "ingress", [clock]),
            _rule(f"{observer}-clock-reply", ["declare_queryable", "reply"], "egress", [clock]),
        ]
        if observer in callers:
            # an operator: an observer that may also call the robots' services
            own_rules += [
                _rule(f"{observer}-call", ["query"], "ingress", [services]),
                _rule(f"{observer}-call-reply", SERVES, "egress", [services]),
            ]
        rules.extend(own_rules)
        subjects.append({"id": observer, by: [observer]})
        policies.append(
            {
                "id": f"{observer}-policy",
                "rules": [r["id"] for r in own_rules],
                "subjects": [observer],
            }
        )
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def _header(what: str, argv: list[str]) -> str:
    argv = [a for i, a in enumerate(argv) if a != "--out" and (i == 0 or argv[i - 1] != "--out")]
    return (
        f"// {what}\n"
        "// Made by deploy/tls/make_fleet_certs.py: re-run it to add robots, do not edit by hand.\n"
        f"// {' '.join(['make_fleet_certs.py', '--out DIR', *argv])}\n"
        "// The arpz TOML's listen/connect endpoints are applied on top of this file.\n"
    )


def _write_json5(path: Path, header: str, config: dict[str, object]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(header + json.dumps(config, indent=2) + "\n", encoding="utf-8")


def router_config(
    fleet: str,
    robots: list[str],
    observers: list[str],
    tls: str,
    *,
    usrpwd: bool,
    operators: list[str] | None = None,
) -> dict[str, object]:
    tls_conf: dict[str, object] = {
        "root_ca_certificate": f"{tls}/ca.pem",
        "listen_private_key": f"{tls}/ceddp.key",
        "listen_certificate": f"{tls}/ceddp.pem",
        "enable_mtls": not usrpwd,
    }
    transport: dict[str, object] = {"link": {"tls": tls_conf}}
    if usrpwd:
        transport["auth"] = {"usrpwd": {"dictionary_file": f"{tls}/passwords.txt"}}
    return {
        "mode": "router",
        # QUIC first: on a lossy radio it holds latency where TLS over TCP stalls for seconds
        # (benchmarks/RESULTS.md "Link types on a lossy radio"); TLS beside it for networks
        # that block UDP. Both with the same certificates and access control.
        "listen": {"endpoints": ["quic/0.0.0.0:7447", "tls/0.0.0.0:7447"]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": transport,
        "access_control": access_control(
            fleet,
            robots,
            by="usernames" if usrpwd else "cert_common_names",
            observers=observers,
            operators=operators,
        ),
    }


def client_config(name: str, server: str, tls: str, *, password: str | None) -> dict[str, object]:
    tls_conf: dict[str, object] = {"root_ca_certificate": f"{tls}/ca.pem"}
    transport: dict[str, object] = {"link": {"tls": tls_conf}}
    if password is None:
        tls_conf.update(
            {
                "enable_mtls": True,
                "connect_private_key": f"{tls}/{name}.key",
                "connect_certificate": f"{tls}/{name}.pem",
            }
        )
    else:
        transport["auth"] = {"usrpwd": {"user": name, "password": password}}
    return {
        "mode": "client",
        "connect": {"endpoints": [f"quic/{server}:7447"]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": transport,
    }


def _passwords(out: Path, robots: list[str]) -> dict[str, str]:
    """Keep existing passwords; draw new ones for new robots."""
    path = out / "passwords.txt"
    known: dict[str, str] = {}
    if path.exists():
        for line in path.read_text(encoding="utf-8").splitlines():
            user, sep, password = line.partition(":")
            if sep:
                known[user] = password
    for robot in robots:
        known.setdefault(robot, secrets.token_urlsafe(18))
    path.write_text("".join(f"{u}:{p}\n" for u, p in sorted(known.items())), encoding="utf-8")
    path.chmod(0o600)
    return known


def make_fleet(
    out: Path,
    fleet: str,
    robots: list[str],
    *,
    server_names: list[str],
    server_ips: list[str],
    days: int = 825,
    paths_on_hosts: str | None = None,
    usrpwd: bool = False,
    observers: list[str] | None = None,
    operators: list[str] | None = None,
    argv: list[str] | None = None,
) -> None:
    observers = observers or []
    operators = operators or []
    clients = [*robots, *observers, *operators]
    for name in [fleet, *clients]:
        if not _CHUNK.match(name):
            raise CertError(
                f"{name!r} is not a valid arpz name: lowercase letters, digits, '_' or '-'"
            )
    if len(set(clients)) != len(clients):
        raise CertError("robot, observer and operator names must all be different")
    if "ceddp" in clients or "ca" in clients:
        raise CertError("'ceddp' and 'ca' are the server's and the CA's file names, not robot ids")
    for ip in server_ips:
        ipaddress.ip_address(ip)
    out.mkdir(parents=True, exist_ok=True)
    make_ca(out, fleet, days * 4)
    sans = [f"DNS:{n}" for n in server_names] + [f"IP:{ip}" for ip in server_ips]
    make_leaf(out, "ceddp", "ceddp", server=True, sans=sans, days=days)
    for name in clients:
        make_leaf(out, name, name, server=False, sans=[], days=days)
    tls = paths_on_hosts or out.resolve().as_posix()
    server = (server_names + server_ips)[0]
    zdir, args = out / "zenoh", argv or []
    _write_json5(
        zdir / "ceddp-router.json5",
        _header(f"CEDDP router of fleet '{fleet}': mutual TLS + access control", args),
        router_config(fleet, robots, observers, tls, usrpwd=False, operators=operators),
    )
    for name in clients:
        _write_json5(
            zdir / f"{name}-client.json5",
            _header(f"{name} of fleet '{fleet}': mutual TLS client", args),
            client_config(name, server, tls, password=None),
        )
    if usrpwd:
        passwords = _passwords(out, clients)
        _write_json5(
            zdir / "ceddp-router-usrpwd.json5",
            _header(f"CEDDP router of fleet '{fleet}': TLS + user/password + access control", args),
            router_config(fleet, robots, observers, tls, usrpwd=True, operators=operators),
        )
        for name in clients:
            path = zdir / f"{name}-client-usrpwd.json5"
            _write_json5(
                path,
                _header(f"{name} of fleet '{fleet}': TLS + user/password client", args),
                client_config(name, server, tls, password=passwords[name]),
            )
            path.chmod(0o600)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    parser = argparse.ArgumentParser(
        prog="make_fleet_certs.py",
        description=__doc__,
        formatter_class=argparse.RawTextHelpFormatter,
    )
    parser.add_argument("robots", nargs="+", help="robot ids (each becomes a certificate CN)")
    parser.add_argument(
        "--out", type=Path, required=True, help="folder for keys, certificates, configs"
    )
    parser.add_argument("--fleet", default="default", help="the fleet name of the arpz TOML files")
    parser.add_argument("--server-name", action="append", default=[], help="DNS name of the CEDDP")
    parser.add_argument("--server-ip", action="append", default=[], help="IP address of the CEDDP")
    parser.add_argument("--days", type=int, default=825, help="validity of the leaf certificates")
    parser.add_argument(
        "--paths-on-hosts", help="folder the files will be installed in, e.g. /etc/arpz/tls"
    )
    parser.add_argument(
        "--usrpwd", action="store_true", help="also write the user/password variant"
    )
    parser.add_argument(
        "--observer",
        action="append",
        default=[],
        help="a read-only client (dashboard, logger) that may subscribe to the whole fleet",
    )
    parser.add_argument(
        "--operator",
        action="append",
        default=[],
        help="an observer that may also call the robots' services (arpz service call)",
    )
    args = parser.parse_args(argv)
    if not args.server_name and not args.server_ip:
        args.server_ip = ["127.0.0.1"]
        args.server_name = ["localhost"]
    try:
        make_fleet(
            args.out,
            args.fleet,
            args.robots,
            server_names=args.server_name,
            server_ips=args.server_ip,
            days=args.days,
            paths_on_hosts=args.paths_on_hosts,
            usrpwd=args.usrpwd,
            observers=args.observer,
            operators=args.operator,
            argv=argv,
        )
    except (CertError, ValueError) as exc:
        print(f"make_fleet_certs: {exc}", file=sys.stderr)
        return 2
    print(f"make_fleet_certs: fleet {args.fleet!r}, {len(args.robots)} robot(s) in {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
