"""The message types a fleet speaks: every standard ROS 2 type, and a team's own.

A topic's type is named as a ROS 2 user names it (``sensor_msgs/msg/NavSatFix``). The
definitions come from rosbags' typestore of a ROS 2 distribution (every message of the standard
interface packages, no ROS 2 installed), and a team adds its own from ``.msg`` files laid out as
ROS 2 lays them out (``msg_paths = ["msg/"]`` holding ``mylab/msg/Battery.msg``) or from a
Python class (``register_class``). The type hash (RIHS01) is the one ROS 2 computes, so a
topic's announcement names exactly the definition its bytes follow.

On arpz's wire a typed message is msgpack of a msgspec Struct generated from the definition,
``array_like`` (fields in definition order, no names), the format arpz's own messages use:
``benchmarks/wire_format.py`` measured CDR (rosbags) 4.4-11x slower than this for ``Imu`` and
``NavSatFix`` and within 2x only for a ``LaserScan`` and an ``Image`` (benchmarks/RESULTS.md,
"Wire format"), so CDR is made only where ROS 2 needs it: the bridge and the recorder
(``to_cdr`` / ``from_cdr``, exact both ways).

A driver hands a message in as an instance of the generated Struct, as a dict of its fields, or
as any object with the fields as attributes (a rosbags or rclpy message); ``check`` turns each
into the Struct or raises ``MessageValueError`` naming the field: a missing or unknown field, a
wrong type, an integer out of its type's range, and a NaN or infinity in a scalar float field
(``nan = "refuse"``, the default: REP 117 lets a ``LaserScan``'s ranges hold inf and NaN, so
sequences pass), in any float field (``"refuse_all"``) or in none (``"pass"``). A message whose type
has a ``std_msgs/msg/Header`` named ``header`` may leave it out: the robot stamps it.
"""

from __future__ import annotations

import array
import difflib
import math
import struct
import threading
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, ClassVar, Final, Literal, get_args, get_origin, get_type_hints

import msgspec
from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from arpz.core.errors import ArpzError, ConfigError

#: the ROS 2 distribution whose standard definitions arpz knows (the LTS rmw_zenoh supports)
DEFAULT_DISTRIBUTION: Final = "humble"
DISTRIBUTIONS: Final[dict[str, Stores]] = {
    "humble": Stores.ROS2_HUMBLE,
    "jazzy": Stores.ROS2_JAZZY,
    "kilted": Stores.ROS2_KILTED,
}
#: where a NaN or infinity is refused: scalar float fields ("refuse", the default: REP 117 lets a
#: LaserScan's ranges hold inf and NaN), every float field ("refuse_all"), or nowhere ("pass")
NanPolicy = Literal["refuse", "refuse_all", "pass"]
NAN_POLICIES: Final[tuple[str, ...]] = ("refuse", "refuse_all", "pass")

_INT_RANGES: Final[dict[str, tuple[int, int]]] = {
    "int8": (-(2**7), 2**7 - 1),
    "uint8": (0, 2**8 - 1),
    "byte": (0, 2**8 - 1),
    "char": (0, 2**8 - 1),
    "int16": (-(2**15), 2**15 - 1),
    "uint16": (0, 2**16 - 1),
    "int32": (-(2**31), 2**31 - 1),
    "uint32": (0, 2**32 - 1),
    "int64": (-(2**63), 2**63 - 1),
    "uint64": (0, 2**64 - 1),
}
_FLOATS: Final = frozenset({"float32", "float64"})
_BYTES: Final = frozenset({"uint8", "byte", "char"})
HEADER: Final = "std_msgs/msg/Header"
_F32: Final = struct.Struct("<f")
#: the field ROS 2 gives a message with none (``std_msgs/msg/Empty``, a ``Trigger``'s request)
_EMPTY_PLACEHOLDER: Final = "structure_needs_at_least_one_member"

#: the service types every arpz process knows, as ROS 2 Humble defines them (``.srv`` text:
#: the request's fields, ``---``, the response's): std_srvs and the services of
#: common_interfaces. rosbags' typestore holds messages only; a team adds its own services
#: from ``.srv`` files (``MessageTypes.add_srv_paths``)
STANDARD_SERVICES: Final[dict[str, str]] = {
    "std_srvs/srv/Empty": "---\n",
    "std_srvs/srv/SetBool": "bool data\n---\nbool success\nstring message\n",
    "std_srvs/srv/Trigger": "---\nbool success\nstring message\n",
    "nav_msgs/srv/GetMap": "---\nnav_msgs/OccupancyGrid map\n",
    "nav_msgs/srv/GetPlan": (
        "geometry_msgs/PoseStamped start\ngeometry_msgs/PoseStamped goal\nfloat32 tolerance\n"
        "---\nnav_msgs/Path plan\n"
    ),
    "nav_msgs/srv/LoadMap": (
        "string map_url\n---\nuint8 RESULT_SUCCESS=0\nuint8 RESULT_MAP_DOES_NOT_EXIST=1\n"
        "uint8 RESULT_INVALID_MAP_DATA=2\nuint8 RESULT_INVALID_MAP_METADATA=3\n"
        "uint8 RESULT_UNDEFINED_FAILURE=255\nnav_msgs/OccupancyGrid map\nuint8 result\n"
    ),
    "nav_msgs/srv/SetMap": (
        "nav_msgs/OccupancyGrid map\ngeometry_msgs/PoseWithCovarianceStamped initial_pose\n"
        "---\nbool success\n"
    ),
    "sensor_msgs/srv/SetCameraInfo": (
        "sensor_msgs/CameraInfo camera_info\n---\nbool success\nstring status_message\n"
    ),
    "diagnostic_msgs/srv/AddDiagnostics": (
        "string load_namespace\n---\nbool success\nstring message\n"
    ),
    "diagnostic_msgs/srv/SelfTest": (
        "---\nstring id\nbyte passed\ndiagnostic_msgs/DiagnosticStatus[] status\n"
    ),
}


class MessageTypeError(ConfigError):
    """A type name arpz does not know, or a ``.msg`` definition it cannot use (a configuration
    error: the type is named in a TOML, the definition found through its ``msg_paths``)."""


class MessageValueError(ArpzError, ValueError):
    """A message that does not fit its type (the text names the field)."""


@dataclass(frozen=True)
class _Shape:
    """What ``check`` needs to know about one type beyond what msgspec validates."""

    scalar_floats: tuple[str, ...]
    float_sequences: tuple[str, ...]
    #: float32 fields: held at float32 precision, so that value -> CDR -> value is exact
    float32_scalars: tuple[str, ...]
    float32_sequences: tuple[str, ...]
    nested: tuple[tuple[str, str], ...]  # (field, type) of fields of a message type
    nested_sequences: tuple[tuple[str, str], ...]
    byte_fields: tuple[str, ...]
    has_header: bool


@dataclass(frozen=True)
class FieldDef:
    """One field of a definition, as arpz reads rosbags' descriptors: a primitive (``base``),
    a message (``message``), or an array (``length`` > 0, fixed) / sequence (``length`` = 0, or
    its bound with ``bounded``) of either."""

    name: str
    base: str | None  # the primitive type, for a primitive or an array of primitives
    message: str | None  # the message type, for a message or an array of messages
    sequence: bool  # an array or a sequence
    length: int = 0
    fixed: bool = False  # ``T[N]``: exactly ``length``; otherwise at most ``length`` (0: any)


def _field_defs(fielddefs: Any, name: str) -> list[FieldDef]:
    defs = []
    for field, (kind, desc) in fielddefs[name][1]:
        if kind == Nodetype.BASE:
            defs.append(FieldDef(field, base=desc[0], message=None, sequence=False))
        elif kind == Nodetype.NAME:
            defs.append(FieldDef(field, base=None, message=desc, sequence=False))
        else:
            (item_kind, item_desc), length = desc
            item_message = item_desc if item_kind == Nodetype.NAME else None
            item_base = item_desc[0] if item_kind == Nodetype.BASE else None
            defs.append(
                FieldDef(
                    field,
                    base=item_base,
                    message=item_message,
                    sequence=True,
                    length=int(length),
                    fixed=kind == Nodetype.ARRAY,
                )
            )
    return defs


class MessageTypes:
    """A registry of message definitions, their generated Structs, hashes and codecs.

    Thread-safe: a robot's sensor threads and the CEDDP's workers share one registry; a type's
    Struct and decoder are generated on first use and kept."""

    def __init__(self, distribution: str = DEFAULT_DISTRIBUTION) -> None:
        if distribution not in DISTRIBUTIONS:
            known = ", ".join(DISTRIBUTIONS)
            raise MessageTypeError(f"unknown ROS 2 distribution {distribution!r}: use {known}")
        self.distribution = distribution
        self._store = get_typestore(DISTRIBUTIONS[distribution])
        self._lock = threading.RLock()
        self._structs: dict[str, type[msgspec.Struct]] = {}
        self._forms: dict[str, type[msgspec.Struct]] = {}
        self._shapes: dict[str, _Shape] = {}
        self._decoders: dict[str, msgspec.msgpack.Decoder[Any]] = {}
        self._encoder = msgspec.msgpack.Encoder()
        #: service name -> its ``.srv`` text (the standard ones and those added), and the services
        #: whose request and response types are registered as messages already
        self._services: dict[str, str] = dict(STANDARD_SERVICES)
        self._services_registered: set[str] = set()

    # -- what is known ------------------------------------------------------------------------

    def names(self) -> list[str]:
        """Every message type known, sorted (services' request and response types included)."""
        return sorted(self._store.types)

    def known(self, name: str) -> bool:
        return name in self._store.fielddefs

    def require(self, name: str) -> None:
        """Raise ``MessageTypeError`` naming close matches when ``name`` is not known."""
        if self.known(name):
            return
        if name.count("/") != 2 or "/msg/" not in name:
            raise MessageTypeError(
                f"message type {name!r} is not a ROS 2 type name: write package/msg/Name, "
                "for example sensor_msgs/msg/NavSatFix"
            )
        package, _, base = name.split("/")
        same_package = [n.split("/")[2] for n in self.names() if n.startswith(package + "/msg/")]
        close = difflib.get_close_matches(base, same_package, n=3, cutoff=0.75)
        if close:
            hint = f": did you mean {' or '.join(f'{package}/msg/{c}' for c in close)}?"
        elif same_package:
            hint = f"; {package} has {', '.join(same_package)}"
        else:
            hint = "; add it from a .msg file (msg_paths) or a Python class"
        raise MessageTypeError(f"unknown message type {name!r}{hint}")

    def type_hash(self, name: str) -> str:
        """The RIHS01 hash ROS 2 computes for ``name`` (what rmw_zenoh puts in its keys)."""
        self.require(name)
        with self._lock:
            return str(self._store.hash_rihs01(name))

    def definition(self, name: str) -> str:
        """The ``.msg`` text of ``name`` with its nested definitions, as rosbag2 stores it in
        an MCAP schema (``ros2msg`` encoding)."""
        self.require(name)
        with self._lock:
            text, _ = self._store.generate_msgdef(name, ros_version=2)
        return str(text)

    def fields(self, name: str) -> list[str]:
        self.require(name)
        return [field.name for field in self.field_defs(name)]

    def field_defs(self, name: str) -> list[FieldDef]:
        self.require(name)
        return _field_defs(self._store.fielddefs, name)

    # -- adding a team's types ----------------------------------------------------------------

    def add_msg_paths(self, paths: Iterable[str | Path]) -> list[str]:
        """Add every ``PACKAGE/msg/NAME.msg`` under the given folders; the names added."""
        found: dict[str, tuple[str, Path]] = {}
        for root in paths:
            root_path = Path(root)
            if not root_path.is_dir():
                raise MessageTypeError(f"msg_paths: {root_path} is not a folder")
            for file in sorted(root_path.rglob("*.msg")):
                if file.parent.name != "msg":
                    raise MessageTypeError(
                        f"{file}: a .msg file must stand in PACKAGE/msg/ (ROS 2's layout)"
                    )
                name = f"{file.parent.parent.name}/msg/{file.stem}"
                found[name] = (file.read_text(), file)
        self._register({name: text for name, (text, _) in found.items()}, origin=found)
        return sorted(found)

    def add_definition(self, name: str, text: str) -> None:
        """Add one type from its ``.msg`` text."""
        self._register({name: text}, origin={})

    def register_class(self, cls: type) -> str:
        """Add a type from a Python class: a dataclass or msgspec Struct whose ``ros_type``
        class attribute names it (``mylab/msg/Battery``) and whose annotated fields are
        ``float`` (float64), ``int`` (int64), ``bool``, ``str``, ``bytes`` (uint8[]),
        ``list[float]``/``list[int]``/``list[str]`` or another registered class."""
        name = getattr(cls, "ros_type", None)
        if not isinstance(name, str):
            raise MessageTypeError(f"{cls.__name__} needs a ros_type = 'package/msg/Name'")
        lines = []
        for field, annotation in get_type_hints(cls).items():
            if field == "ros_type" or get_origin(annotation) is ClassVar:
                continue
            lines.append(f"{self._msg_type_of(annotation, where=f'{name}.{field}')} {field}")
        self.add_definition(name, "\n".join(lines))
        return name

    def _msg_type_of(self, annotation: Any, *, where: str) -> str:
        simple = {float: "float64", int: "int64", bool: "bool", str: "string", bytes: "uint8[]"}
        if annotation in simple:
            return simple[annotation]
        if get_origin(annotation) is list:
            (item,) = get_args(annotation)
            return self._msg_type_of(item, where=where) + "[]"
        nested = getattr(annotation, "ros_type", None)
        if isinstance(nested, str) and self.known(nested):
            return nested.replace("/msg/", "/")
        raise MessageTypeError(f"{where}: no ROS 2 field type for {annotation!r}")

    def _register(self, texts: Mapping[str, str], origin: Mapping[str, tuple[str, Path]]) -> None:
        parsed: dict[str, Any] = {}
        for name, text in texts.items():
            where = str(origin[name][1]) if name in origin else name
            if name.count("/") != 2 or "/msg/" not in name:
                raise MessageTypeError(f"{where}: a type name is package/msg/Name, got {name!r}")
            try:
                parsed.update(get_types_from_msg(text, name))
            except Exception as exc:  # rosbags raises its own parser errors
                raise MessageTypeError(f"{where}: not a valid .msg definition: {exc}") from None
        with self._lock:
            self._store.register(parsed)
            for name in parsed:
                self._check_references(name, origin)

    def _check_references(self, name: str, origin: Mapping[str, tuple[str, Path]]) -> None:
        where = str(origin[name][1]) if name in origin else name
        for field in _field_defs(self._store.fielddefs, name):
            if field.message is not None and field.message not in self._store.fielddefs:
                raise MessageTypeError(
                    f"{where}: field {field.name!r} names type {field.message!r}, which is not "
                    "known (a typo of a primitive type such as float32, or a .msg file missing)"
                )

    # -- the generated Structs ----------------------------------------------------------------

    def struct(self, name: str) -> type[msgspec.Struct]:
        """The wire Struct of ``name`` (array_like, in definition order)."""
        with self._lock:
            if name not in self._structs:
                self.require(name)
                self._generate(name)
            return self._structs[name]

    def _generate(self, name: str) -> None:
        wire: list[tuple[str, Any]] = []
        form: list[tuple[str, Any]] = []
        scalar_floats: list[str] = []
        float_sequences: list[str] = []
        float32_scalars: list[str] = []
        float32_sequences: list[str] = []
        byte_fields: list[str] = []
        nested: list[tuple[str, str]] = []
        nested_sequences: list[tuple[str, str]] = []
        for field in _field_defs(self._store.fielddefs, name):
            if field.message is not None:
                item_wire: Any = self.struct(field.message)
                item_form: Any = self._forms[field.message]
                (nested_sequences if field.sequence else nested).append((field.name, field.message))
            else:
                assert field.base is not None
                item_wire = item_form = self._primitive(field.base)
                floats = scalar_floats if not field.sequence else float_sequences
                if field.base in _FLOATS:
                    floats.append(field.name)
                if field.base == "float32":
                    (float32_sequences if field.sequence else float32_scalars).append(field.name)
            if not field.sequence:
                wire.append((field.name, item_wire))
                form.append((field.name, item_form))
                continue
            meta = (
                msgspec.Meta(min_length=field.length, max_length=field.length)
                if field.fixed
                else msgspec.Meta(max_length=field.length or None)
            )
            if field.base in _BYTES:
                byte_fields.append(field.name)
                wire.append((field.name, Annotated[bytes, meta]))
                form.append((field.name, Annotated[bytes, meta]))
            else:
                wire.append((field.name, Annotated[list[item_wire], meta]))
                form.append((field.name, Annotated[list[item_form], meta]))
        constants = {const: value for const, _, value in self._store.fielddefs[name][0]}
        class_name = name.replace("/msg/", "_").replace("/", "_")
        self._structs[name] = msgspec.defstruct(
            class_name, wire, array_like=True, namespace=constants
        )
        self._forms[name] = msgspec.defstruct(
            class_name + "_form", form, forbid_unknown_fields=True, frozen=True
        )
        self._shapes[name] = _Shape(
            scalar_floats=tuple(scalar_floats),
            float_sequences=tuple(float_sequences),
            float32_scalars=tuple(float32_scalars),
            float32_sequences=tuple(float32_sequences),
            nested=tuple(nested),
            nested_sequences=tuple(nested_sequences),
            byte_fields=tuple(byte_fields),
            has_header=any(field == "header" and t == HEADER for field, t in nested),
        )

    @staticmethod
    def _primitive(name: str) -> Any:
        if name in _FLOATS:
            return float
        if name == "bool":
            return bool
        if name in ("string", "wstring"):
            return str
        low, high = _INT_RANGES[name]
        return Annotated[int, msgspec.Meta(ge=low, le=high)]

    # -- a driver's message in, the wire out ---------------------------------------------------

    def check(
        self,
        name: str,
        message: object,
        *,
        nan: NanPolicy = "refuse",
        stamp_ns: int | None = None,
        frame_id: str = "",
    ) -> msgspec.Struct:
        """``message`` as the wire Struct of ``name``, or ``MessageValueError`` naming the field.

        ``stamp_ns`` fills a left-out ``header`` (the robot's read time) with ``frame_id``."""
        cls = self.struct(name)
        if type(message) is cls:
            checked = message
        else:
            shape = self._shapes[name]
            if isinstance(message, Mapping):
                if shape.has_header and "header" not in message and stamp_ns is not None:
                    message = {**message, "header": _header(stamp_ns, frame_id)}
                try:
                    form = msgspec.convert(_plain(message), self._forms[name])
                except msgspec.ValidationError as exc:
                    raise MessageValueError(f"{name}: {exc}") from None
                checked = msgspec.convert(form, cls, from_attributes=True)
            else:
                try:
                    checked = msgspec.convert(_Attributes(message), cls, from_attributes=True)
                except msgspec.ValidationError as exc:
                    raise MessageValueError(f"{name}: {exc}") from None
        try:
            self._to_float32(name, checked)
        except OverflowError:
            raise MessageValueError(
                f"{name}: a float32 field holds a value beyond float32"
            ) from None
        if nan != "pass":
            self._check_finite(name, checked, sequences=nan == "refuse_all", path=name)
        return checked

    def _to_float32(self, name: str, message: Any) -> None:
        """Round float32 fields to float32 in place (a Python float is a float64)."""
        shape = self._shapes[name]
        for field in shape.float32_scalars:
            setattr(message, field, _F32.unpack(_F32.pack(getattr(message, field)))[0])
        for field in shape.float32_sequences:
            values = getattr(message, field)
            if values:
                setattr(message, field, array.array("f", values).tolist())
        for field, nested in shape.nested:
            self._to_float32(nested, getattr(message, field))
        for field, nested in shape.nested_sequences:
            for item in getattr(message, field):
                self._to_float32(nested, item)

    def _check_finite(self, name: str, message: Any, *, sequences: bool, path: str) -> None:
        shape = self._shapes[name]
        for field in shape.scalar_floats:
            if not math.isfinite(getattr(message, field)):
                raise MessageValueError(
                    f"{path}.{field} is {getattr(message, field)}: a NaN or infinity is refused "
                    '(the sensor\'s nan option: "pass" lets it through)'
                )
        if sequences:
            for field in shape.float_sequences:
                if not all(map(math.isfinite, getattr(message, field))):
                    raise MessageValueError(
                        f'{path}.{field} holds a NaN or infinity: refused (nan = "refuse")'
                    )
        for field, nested in shape.nested:
            self._check_finite(
                nested, getattr(message, field), sequences=sequences, path=f"{path}.{field}"
            )
        for field, nested in shape.nested_sequences:
            for i, item in enumerate(getattr(message, field)):
                self._check_finite(nested, item, sequences=sequences, path=f"{path}.{field}[{i}]")

    def encode(self, message: msgspec.Struct) -> bytes:
        return self._encoder.encode(message)

    def decode(self, name: str, payload: bytes | memoryview | msgspec.Raw) -> Any:
        """The wire Struct of ``name`` from its msgpack bytes (``msgspec.ValidationError`` or
        ``msgspec.DecodeError`` when they do not fit)."""
        decoder = self._decoders.get(name)
        if decoder is None:
            with self._lock:
                decoder = self._decoders.setdefault(
                    name, msgspec.msgpack.Decoder(self.struct(name))
                )
        return decoder.decode(payload)

    def to_builtins(self, message: msgspec.Struct) -> dict[str, Any]:
        """The message as a dict of plain values, nested messages as dicts (``topic echo``)."""
        return {field: _builtins(getattr(message, field)) for field in message.__struct_fields__}

    # -- services ----------------------------------------------------------------------------

    def service_names(self) -> list[str]:
        """Every service type known (``std_srvs/srv/Trigger``), sorted: the standard ones of
        ``STANDARD_SERVICES`` and those added from ``.srv`` files."""
        with self._lock:
            return sorted(self._services)

    def known_service(self, name: str) -> bool:
        with self._lock:
            return name in self._services

    def require_service(self, name: str) -> None:
        """Raise ``MessageTypeError`` naming close matches when ``name`` is not a service type
        known here."""
        if self.known_service(name):
            return
        parts = name.split("/")
        if len(parts) != 3 or parts[1] != "srv" or not all(parts):
            raise MessageTypeError(
                f"service type {name!r} is not a ROS 2 service type name: write "
                "package/srv/Name, for example std_srvs/srv/Trigger"
            )
        package, base = parts[0], parts[2]
        names = self.service_names()
        same_package = [n.split("/")[2] for n in names if n.startswith(package + "/srv/")]
        close = difflib.get_close_matches(base, same_package, n=3, cutoff=0.75)
        if close:
            hint = f": did you mean {' or '.join(f'{package}/srv/{c}' for c in close)}?"
        elif same_package:
            hint = f"; {package} has {', '.join(same_package)}"
        else:
            hint = (
                "; add it from a .srv file (package/srv/Name.srv under msg_paths); known: "
                + ", ".join(names)
            )
        raise MessageTypeError(f"unknown service type {name!r}{hint}")

    def service_types(self, name: str) -> tuple[str, str]:
        """The request and response message types of service ``name`` (``std_srvs/srv/
        Trigger`` -> ``std_srvs/srv/Trigger_Request``, ``std_srvs/srv/Trigger_Response``, as
        ROS 2 names them), registered as message types on first use: ``check``, ``encode``,
        ``decode``, ``to_cdr`` and ``type_hash`` then take them like any message type."""
        self.require_service(name)
        request, response = f"{name}_Request", f"{name}_Response"
        with self._lock:
            if name not in self._services_registered:
                self._register_service(name, self._services[name])
                self._services_registered.add(name)
        return request, response

    def check_service_message(self, name: str, message: object) -> msgspec.Struct:
        """``check`` of a service's request or response type (``name`` as ``service_types``
        gives it), with ``nan = "pass"`` (a call carries what its caller sent), and an empty
        message (``std_srvs/srv/Trigger_Request``: ``{}``) given the one placeholder field ROS 2
        adds to an empty structure."""
        if isinstance(message, Mapping) and not message:
            fields = self.fields(name)
            if fields == [_EMPTY_PLACEHOLDER]:
                message = {_EMPTY_PLACEHOLDER: 0}
        return self.check(name, message, nan="pass")

    def add_service_definition(self, name: str, text: str) -> None:
        """Add service ``name`` (``package/srv/Name``) from its ``.srv`` text: the request's
        fields, a line ``---``, the response's."""
        parts = name.split("/")
        if len(parts) != 3 or parts[1] != "srv" or not all(parts):
            raise MessageTypeError(f"{name}: a service type name is package/srv/Name")
        self._register_service(name, text)
        with self._lock:
            self._services[name] = text
            self._services_registered.add(name)

    def add_srv_paths(self, paths: Iterable[str | Path]) -> list[str]:
        """Add every ``PACKAGE/srv/NAME.srv`` under the given folders (the ``msg_paths`` of a
        robot's or the CEDDP's TOML: ROS 2 lays a package's ``msg/`` and ``srv/`` side by
        side); the names added."""
        added = []
        for root in paths:
            root_path = Path(root)
            if not root_path.is_dir():
                raise MessageTypeError(f"msg_paths: {root_path} is not a folder")
            for file in sorted(root_path.rglob("*.srv")):
                if file.parent.name != "srv":
                    raise MessageTypeError(
                        f"{file}: a .srv file must stand in PACKAGE/srv/ (ROS 2's layout)"
                    )
                name = f"{file.parent.parent.name}/srv/{file.stem}"
                try:
                    self.add_service_definition(name, file.read_text())
                except MessageTypeError as exc:
                    raise MessageTypeError(f"{file}: {exc}") from None
                added.append(name)
        return sorted(added)

    def _register_service(self, name: str, text: str) -> None:
        """Parse ``.srv`` text into its request and response message types and register both.
        rosbags parses message names only (``package/msg/Name``): each half is parsed under
        that form, so relative field types resolve in the service's package (``Path`` in
        ``nav_msgs/srv/GetPlan`` is ``nav_msgs/msg/Path``), then registered under the
        service's names."""
        lines = text.splitlines()
        cuts = [i for i, line in enumerate(lines) if line.split("#")[0].strip() == "---"]
        if len(cuts) != 1:
            raise MessageTypeError(
                f"{name}: a .srv definition has the request's fields, one line '---', then the "
                f"response's (found {len(cuts)} such lines)"
            )
        halves = {
            "Request": "\n".join(lines[: cuts[0]]),
            "Response": "\n".join(lines[cuts[0] + 1 :]),
        }
        package, _, base = name.split("/")
        parsed: dict[str, Any] = {}
        for half, body in halves.items():
            as_message = f"{package}/msg/{base}_{half}"
            try:
                found = get_types_from_msg(body, as_message)
            except Exception as exc:  # rosbags raises its own parser errors
                raise MessageTypeError(f"{name}: not a valid .srv definition: {exc}") from None
            parsed[f"{name}_{half}"] = found[as_message]
        with self._lock:
            self._store.register(parsed)
            for message in parsed:
                self._check_references(message, {})

    # -- CDR, for the ROS 2 side --------------------------------------------------------------

    def to_cdr(self, name: str, message: msgspec.Struct) -> bytes:
        """The message as ROS 2's CDR bytes (little endian, with the encapsulation header)."""
        ros = self._to_rosbags(name, message)
        return bytes(self._store.serialize_cdr(ros, name))

    def from_cdr(self, name: str, raw: bytes | memoryview) -> msgspec.Struct:
        ros = self._store.deserialize_cdr(bytes(raw), name)
        return self.check(name, ros, nan="pass")

    def _to_rosbags(self, name: str, message: Any) -> Any:
        import numpy as np

        kwargs: dict[str, Any] = {}
        for field in _field_defs(self._store.fielddefs, name):
            value = getattr(message, field.name)
            if field.message is not None:
                nested = field.message
                value = (
                    [self._to_rosbags(nested, item) for item in value]
                    if field.sequence
                    else self._to_rosbags(nested, value)
                )
            elif field.sequence and field.base in _BYTES:
                value = np.frombuffer(value, dtype=np.uint8)
            elif field.sequence and field.base not in ("string", "wstring"):
                assert field.base is not None
                value = np.asarray(value, dtype=_NUMPY_TYPES[field.base])
            kwargs[field.name] = value
        return self._store.types[name](**kwargs)


_NUMPY_TYPES: Final[dict[str, str]] = {
    "bool": "bool",
    "float32": "float32",
    "float64": "float64",
    **{name: name for name in ("int8", "uint8", "int16", "uint16", "int32", "uint32")},
    **{name: name for name in ("int64", "uint64")},
}


def as_dict(message: msgspec.Struct) -> dict[str, Any]:
    """A message as a dict of plain values, nested messages as dicts (``topic echo``, JSON)."""
    return {field: _builtins(getattr(message, field)) for field in message.__struct_fields__}


def same_message(a: object, b: object, deadband: Mapping[str, float] | None = None) -> bool:
    """Two messages equal but for their header's stamp (what the local cache and cache control
    hold back: a sensor re-reading the same fix stamps it anew), a number field named in
    ``deadband`` (a top-level field, or a dotted path such as ``position.x``) counting as
    equal within its band."""
    if type(a) is not type(b) or not isinstance(a, msgspec.Struct):
        return False
    bands = deadband or {}
    for field in a.__struct_fields__:
        x, y = getattr(a, field), getattr(b, field)
        if field == "header" and hasattr(x, "frame_id"):
            if x.frame_id != getattr(y, "frame_id", None):
                return False
        elif field in bands:
            if not abs(x - y) <= bands[field]:
                return False
        elif any(path.startswith(field + ".") for path in bands):
            inner = {p[len(field) + 1 :]: v for p, v in bands.items() if p.startswith(field + ".")}
            if not same_message(x, y, inner):
                return False
        elif x != y:
            return False
    return True


def _header(stamp_ns: int, frame_id: str) -> dict[str, Any]:
    return {
        "stamp": {"sec": stamp_ns // 1_000_000_000, "nanosec": stamp_ns % 1_000_000_000},
        "frame_id": frame_id,
    }


def _plain(value: Any) -> Any:
    """numpy arrays and tuples as msgspec takes them (uint8 arrays as bytes)."""
    if isinstance(value, Mapping):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(item) for item in value]
    tolist: Callable[[], Any] | None = getattr(value, "tolist", None)
    if tolist is not None and hasattr(value, "dtype"):
        return value.tobytes() if str(value.dtype) == "uint8" else tolist()
    return value


class _Attributes:
    """An object's attributes with numpy arrays turned into what msgspec takes (for
    ``from_attributes``: a rosbags or rclpy message)."""

    __slots__ = ("_obj",)

    def __init__(self, obj: object) -> None:
        self._obj = obj

    def __getattr__(self, name: str) -> Any:
        value = getattr(self._obj, name)
        if hasattr(value, "dtype") and hasattr(value, "tolist"):
            return _plain(value)
        if isinstance(value, (list, tuple)):
            return [_Attributes(v) if _is_message(v) else _plain(v) for v in value]
        if _is_message(value):
            return _Attributes(value)
        return value


def _is_message(value: object) -> bool:
    """A nested message object (anything but a plain value, a container or an array)."""
    plain = (int, float, str, bytes, bytearray, memoryview, Sequence, Mapping)
    return not isinstance(value, plain) and not hasattr(value, "dtype")


def _builtins(value: Any) -> Any:
    if isinstance(value, msgspec.Struct):
        return {field: _builtins(getattr(value, field)) for field in value.__struct_fields__}
    if isinstance(value, list):
        return [_builtins(item) for item in value]
    return value
