"""arpz's own messages as ``diagnostic_msgs/msg/DiagnosticArray``, and back, exactly.

A robot's reports (``Announce``, ``RobotStats``, ``QosAck``, ``Telemetry``) and its liveliness
tokens have no ROS 2 type of their own; ``DiagnosticArray`` is the standard type of "a component
says how it is", which every ROS 2 tool reads (``ros2 topic echo``, rqt_robot_monitor,
Foxglove's Diagnostics panel, rosbag2). ``arpz record`` writes them so (docs/tools.md, "What is
in the file"), and ``arpz play`` turns them back into the arpz messages it publishes.

One report is one ``DiagnosticStatus``: ``name`` says whose report it is (``robot1/stats``),
``hardware_id`` the robot, ``message`` a short sentence, ``level`` OK (STALE for a liveliness
token that vanished), and ``values`` every field of the message as a key/value pair of text:

- nested fields are joined with ``.`` and list items indexed: ``topics.lidar.sent``,
  ``sensors[0].kind``; an empty list or map keeps its field as ``sensors[]`` / ``inbound{}``
  (value ""); a map key with ``.``, ``[``, ``]``, ``{``, ``}`` or ``%`` in it is %-escaped;
- a value is its text: strings as they are, ``true``/``false``, integers in decimal, floats
  as Python's ``repr`` (the shortest text that gives the same float back; ``inf``, ``nan``),
  ``null`` for None, bytes in base64.

``to_fields`` / ``from_fields`` are the same fields as plain Python values (a struct's field
names, not msgpack's arrays), for the JSON form of ``arpz record --include-internal``. Going
back, the text is read by the message type itself (``msgspec.convert`` in its lax mode), so
``from_fields(T, to_fields(m)) == m`` and ``report_from_ros(T, report_to_ros(m, ...)) == m``
for every arpz message (tested with each of them); a struct encoded as a msgpack array
(``array_like``) is handled at the top level, which is the only place arpz has one.
"""

from __future__ import annotations

import base64
import re
from collections.abc import Iterable, Mapping
from typing import Any, Final, TypeVar

import msgspec

from arpz.core.rosmsg.convert import STORE, ConversionError, deserialize, serialize

DIAGNOSTIC_ARRAY: Final = "diagnostic_msgs/msg/DiagnosticArray"
#: diagnostic_msgs/msg/DiagnosticStatus levels
OK: Final = 0
WARN: Final = 1
ERROR: Final = 2
STALE: Final = 3

T = TypeVar("T", bound=msgspec.Struct)

_ESCAPED: Final = re.compile(r"[%.\[\]{}]")
_SEGMENT: Final = re.compile(r"\.?([^.\[\]{}]+)|\[(\d+)\]|(\[\]|\{\})")
_EMPTY_LIST: Final = "[]"
_EMPTY_MAP: Final = "{}"


class _Empty(str):
    """An empty list or map marker parsed from a key: a str subclass, so that a field whose
    escaped name is ``{}`` or ``[]`` (a ``str``) is never taken for one."""


_EMPTY_LIST_MARK: Final = _Empty(_EMPTY_LIST)
_EMPTY_MAP_MARK: Final = _Empty(_EMPTY_MAP)
#: where an empty list or map sits in the tree ``unflatten`` builds: not a str, so no field name
_EMPTY_SLOT: Final = object()


# -- a message's fields ----------------------------------------------------------------------


def to_fields(message: msgspec.Struct) -> dict[str, Any]:
    """The fields of ``message`` as plain values, by name, nested structs included (msgpack's
    ``array_like`` layout does not show here: every struct is a map of its fields)."""
    return _plain(message)  # type: ignore[no-any-return]


def _plain(value: Any) -> Any:
    if isinstance(value, msgspec.Struct):
        return {name: _plain(getattr(value, name)) for name in value.__struct_fields__}
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


def from_fields(message_type: type[T], fields: Mapping[str, Any], *, strict: bool = True) -> T:
    """The ``message_type`` whose fields are ``fields`` (``to_fields``' output, or the same
    with every value as text when ``strict`` is False). ``ConversionError`` names what does
    not fit."""
    data: Any = dict(fields)
    if message_type.__struct_config__.array_like:
        data = _as_array(message_type, data)
    try:
        return msgspec.convert(data, message_type, strict=strict)
    except msgspec.ValidationError as exc:
        raise ConversionError(f"not a {message_type.__name__}: {exc}") from None


def _as_array(message_type: type[msgspec.Struct], fields: dict[str, Any]) -> list[Any]:
    """The msgpack array of an ``array_like`` struct: its fields in order, up to the last
    given (the ones after it take their defaults)."""
    names = message_type.__struct_fields__
    unknown = set(fields) - set(names)
    if unknown:
        raise ConversionError(f"not a {message_type.__name__}: no field {sorted(unknown)[0]!r}")
    given = [name in fields for name in names]
    last = max((i for i, g in enumerate(given) if g), default=-1)
    missing = [names[i] for i in range(last + 1) if not given[i]]
    if missing:
        raise ConversionError(f"not a {message_type.__name__}: field {missing[0]!r} is missing")
    return [fields[name] for name in names[: last + 1]]


# -- fields <-> key/value text ---------------------------------------------------------------


def _escape(key: str) -> str:
    return _ESCAPED.sub(lambda m: f"%{ord(m.group()):02X}", key)


def _unescape(key: str) -> str:
    return re.sub(r"%([0-9A-F]{2})", lambda m: chr(int(m.group(1), 16)), key)


def _text(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)  # the shortest text of the same float; inf, -inf, nan
    if isinstance(value, int | str):
        return str(value)
    if isinstance(value, bytes | bytearray):
        return base64.b64encode(value).decode()  # as JSON writes bytes, and msgspec reads them
    raise ConversionError(f"a {type(value).__name__} has no text form in a KeyValue")


def flatten(fields: Mapping[str, Any]) -> list[tuple[str, str]]:
    """``to_fields``' output as (key, value) text pairs, in field order."""
    out: list[tuple[str, str]] = []

    def walk(value: Any, path: str) -> None:
        if isinstance(value, Mapping):
            if not value:
                out.append((path + _EMPTY_MAP, ""))
            for k, v in value.items():
                walk(v, f"{path}.{_escape(k)}" if path else _escape(k))
        elif isinstance(value, list):
            if not value:
                out.append((path + _EMPTY_LIST, ""))
            for i, v in enumerate(value):
                walk(v, f"{path}[{i}]")
        else:
            out.append((path, _text(value)))

    walk(fields, "")
    return out


def _path(key: str) -> list[str | int]:
    segments: list[str | int] = []
    pos = 0
    while pos < len(key):
        match = _SEGMENT.match(key, pos)
        if match is None or (match.group(1) is not None and pos and key[pos] != "."):
            raise ConversionError(f"KeyValue key {key!r} is not a field path")
        name, index, empty = match.groups()
        if empty is not None and match.end() != len(key):
            raise ConversionError(f"KeyValue key {key!r}: {empty} must end it")
        if name is not None:
            segments.append(_unescape(name))
        elif index:
            segments.append(int(index))
        else:
            segments.append(_EMPTY_LIST_MARK if empty == _EMPTY_LIST else _EMPTY_MAP_MARK)
        pos = match.end()
    if not segments or not isinstance(segments[0], str) or isinstance(segments[0], _Empty):
        raise ConversionError(f"KeyValue key {key!r} does not start with a field name")
    return segments


def unflatten(pairs: Iterable[tuple[str, str]]) -> dict[str, Any]:
    """``flatten``'s pairs back into nested fields (every leaf value text)."""
    root: dict[Any, Any] = {}
    for key, value in pairs:
        *parents, last = _path(key)
        node: Any = root
        for segment in parents:
            node = node.setdefault(segment, {})
            if not isinstance(node, dict):
                raise ConversionError(f"KeyValue key {key!r} goes below a value")
        empty: list[Any] | dict[str, Any] | None = None
        if last is _EMPTY_LIST_MARK:
            empty = []
        elif last is _EMPTY_MAP_MARK:
            empty = {}
        slot = _EMPTY_SLOT if empty is not None else last
        if slot in node:
            raise ConversionError(f"KeyValue key {key!r} is given twice")
        node[slot] = value if empty is None else empty
    return _lists(root)  # type: ignore[no-any-return]


def _lists(node: Any) -> Any:
    """Maps whose keys are list indices become lists; the empty markers their value."""
    if not isinstance(node, dict):
        return node
    if _EMPTY_SLOT in node:
        return node[_EMPTY_SLOT]
    if node and all(isinstance(k, int) for k in node):
        if sorted(node) != list(range(len(node))):
            raise ConversionError(f"list indices {sorted(node)} are not 0..{len(node) - 1}")
        return [_lists(node[i]) for i in range(len(node))]
    if any(isinstance(k, int) for k in node):
        raise ConversionError("a field is both a list and a map")
    return {k: _lists(v) for k, v in node.items()}


# -- DiagnosticArray -------------------------------------------------------------------------


def report_to_ros(
    fields: Mapping[str, Any],
    *,
    name: str,
    hardware_id: str,
    message: str,
    stamp_ns: int,
    level: int = OK,
) -> Any:
    """A ``DiagnosticArray`` (a rosbags typestore object) of one status holding ``fields``."""
    types = STORE.types
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    if not -(2**31) <= sec < 2**31:
        raise ConversionError(f"stamp {stamp_ns} ns is outside builtin_interfaces/Time")
    key_value = types["diagnostic_msgs/msg/KeyValue"]
    status = types["diagnostic_msgs/msg/DiagnosticStatus"](
        level=level,
        name=name,
        message=message,
        hardware_id=hardware_id,
        values=[key_value(key=k, value=v) for k, v in flatten(fields)],
    )
    header = types["std_msgs/msg/Header"](
        stamp=types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=""
    )
    return types[DIAGNOSTIC_ARRAY](header=header, status=[status])


def report_cdr(
    message: msgspec.Struct,
    *,
    name: str,
    hardware_id: str,
    summary: str,
    stamp_ns: int,
    level: int = OK,
) -> bytes:
    """An arpz message as the CDR of its ``DiagnosticArray``."""
    return serialize(
        report_to_ros(
            to_fields(message),
            name=name,
            hardware_id=hardware_id,
            message=summary,
            stamp_ns=stamp_ns,
            level=level,
        )
    )


class Report(msgspec.Struct, frozen=True):
    """What one ``DiagnosticArray`` of ``report_to_ros`` says."""

    name: str
    hardware_id: str
    message: str
    level: int
    stamp_ns: int
    #: the fields, every leaf as text
    fields: dict[str, Any]


def report_from_cdr(data: bytes) -> Report:
    """The one status of a ``DiagnosticArray`` in CDR ``data``."""
    array = deserialize(data, DIAGNOSTIC_ARRAY)
    if len(array.status) != 1:
        raise ConversionError(f"an arpz report is one DiagnosticStatus, got {len(array.status)}")
    status = array.status[0]
    stamp = array.header.stamp
    return Report(
        name=str(status.name),
        hardware_id=str(status.hardware_id),
        message=str(status.message),
        level=int(status.level),
        stamp_ns=int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec),
        fields=unflatten((str(kv.key), str(kv.value)) for kv in status.values),
    )


def message_from_cdr(message_type: type[T], data: bytes) -> T:
    """The arpz message in a ``DiagnosticArray`` made by ``report_cdr``."""
    return from_fields(message_type, report_from_cdr(data).fields, strict=False)
