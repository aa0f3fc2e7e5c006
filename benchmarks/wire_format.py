"""Which wire format for typed topics: the cost of encode + decode per message, in one run.

Issue 41 asks for the decision to come from this measurement: typed topics (`Imu`,
`NavSatFix`, a 360-beam `LaserScan`, a 640x480 `Image`) through

- **msgspec** (arpz's format for its own messages): msgpack of msgspec Structs generated from
  the same ROS 2 definitions; numeric arrays as msgpack lists, `uint8[]` as bytes;
- **rosbags CDR**: the ROS 2 wire format (XCDR1 little endian with its 4-byte encapsulation
  header), through rosbags' generated pure-Python (de)serialisers, numpy arrays for sequences;
- **rclpy CDR** (when ROS 2's Python packages are importable): the same bytes through
  rosidl's C type support, `rclpy.serialization` (the fastest CDR implementation found for
  Python; it needs the ROS 2 wheels, which a robot install does not have).

It prints microseconds per message (median of ``--repeats`` runs of ``--n`` encode+decode
round trips), the payload size, and each format's ratio to msgspec; rclpy's CDR read back by
rosbags is checked to carry the same values, so the comparison is between two implementations
of one format. Run: ``python benchmarks/wire_format.py`` (``--json PATH`` for the figures).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.base import Nodetype

TYPESTORE = get_typestore(Stores.ROS2_HUMBLE)
MESSAGES = (
    "sensor_msgs/msg/Imu",
    "sensor_msgs/msg/NavSatFix",
    "sensor_msgs/msg/LaserScan",
    "sensor_msgs/msg/Image",
)
_PRIMITIVE: dict[str, type] = {
    "bool": bool,
    "string": str,
    **{name: int for name in ("int8", "uint8", "int16", "uint16", "int32", "uint32")},
    **{name: int for name in ("int64", "uint64", "byte", "char")},
    "float32": float,
    "float64": float,
}


def _field_type(node: tuple[Any, Any], structs: dict[str, type]) -> Any:
    kind, desc = node
    if kind == Nodetype.BASE:
        return _PRIMITIVE[desc[0]]
    if kind == Nodetype.NAME:
        return msgspec_struct(desc, structs)
    inner, _length = desc
    if inner[0] == Nodetype.BASE and inner[1][0] in ("uint8", "byte", "char"):
        return bytes
    return list[_field_type(inner, structs)]  # type: ignore[misc]


def msgspec_struct(typename: str, structs: dict[str, type] | None = None) -> type:
    """A msgspec Struct with the ROS 2 type's fields (array_like: no field names on the wire)."""
    structs = {} if structs is None else structs
    if typename not in structs:
        _, fields = TYPESTORE.fielddefs[typename]
        specs = [(name, _field_type(node, structs)) for name, node in fields]
        structs[typename] = msgspec.defstruct(
            typename.replace("/", "_"), specs, array_like=True, frozen=True
        )
    return structs[typename]


def sample_values(typename: str) -> dict[str, Any]:
    """Plausible field values, the same for every format (a header stamped now)."""
    stamp = {"stamp": {"sec": 1_733_400_000, "nanosec": 123_456_789}, "frame_id": "base_link"}
    vector = {"x": 0.01, "y": -0.02, "z": 9.81}
    covariance = np.zeros(9, dtype=np.float64)
    if typename == "sensor_msgs/msg/Imu":
        return {
            "header": stamp,
            "orientation": {"x": 0.0, "y": 0.0, "z": 0.38, "w": 0.92},
            "orientation_covariance": covariance,
            "angular_velocity": vector,
            "angular_velocity_covariance": covariance,
            "linear_acceleration": vector,
            "linear_acceleration_covariance": covariance,
        }
    if typename == "sensor_msgs/msg/NavSatFix":
        return {
            "header": stamp,
            "status": {"status": 0, "service": 1},
            "latitude": 51.4545,
            "longitude": -2.5879,
            "altitude": 11.0,
            "position_covariance": covariance,
            "position_covariance_type": 2,
        }
    if typename == "sensor_msgs/msg/LaserScan":
        beams = 360
        ranges = np.linspace(0.2, 11.5, beams, dtype=np.float32)
        return {
            "header": stamp,
            "angle_min": -3.1415927,
            "angle_max": 3.1415927,
            "angle_increment": 2 * 3.1415927 / beams,
            "time_increment": 0.0,
            "scan_time": 0.1,
            "range_min": 0.12,
            "range_max": 12.0,
            "ranges": ranges,
            "intensities": np.zeros(beams, dtype=np.float32),
        }
    if typename == "sensor_msgs/msg/Image":
        width, height = 640, 480
        pixels = np.random.default_rng(1).integers(0, 255, width * height * 3, dtype=np.uint8)
        return {
            "header": stamp,
            "height": height,
            "width": width,
            "encoding": "rgb8",
            "is_bigendian": 0,
            "step": width * 3,
            "data": pixels,
        }
    raise ValueError(f"no sample for {typename}")


def _build(cls_of: Callable[[str], Any], typename: str, values: dict[str, Any]) -> Any:
    """An instance of ``typename`` from ``values``, nested types built the same way."""
    _, fields = TYPESTORE.fielddefs[typename]
    kwargs = {}
    for name, (kind, desc) in fields:
        value = values[name]
        kwargs[name] = _build(cls_of, desc, value) if kind == Nodetype.NAME else value
    return cls_of(typename)(**kwargs)


def _as_plain(values: Any) -> Any:
    """numpy arrays as msgpack takes them: lists of floats, bytes for uint8."""
    if isinstance(values, dict):
        return {key: _as_plain(value) for key, value in values.items()}
    if isinstance(values, np.ndarray):
        return values.tobytes() if values.dtype == np.uint8 else values.tolist()
    return values


@dataclass(frozen=True)
class Codec:
    name: str
    encode: Callable[[], bytes]
    decode: Callable[[bytes], Any]


def codecs(typename: str) -> list[Codec]:
    values = sample_values(typename)
    structs: dict[str, type] = {}
    struct_cls = msgspec_struct(typename, structs)
    as_struct = _build(lambda name: structs[name], typename, _as_plain(values))
    encoder, decoder = msgspec.msgpack.Encoder(), msgspec.msgpack.Decoder(struct_cls)
    found = [Codec("msgspec", lambda: encoder.encode(as_struct), decoder.decode)]

    as_rosbags = _build(lambda name: TYPESTORE.types[name], typename, values)
    found.append(
        Codec(
            "rosbags CDR",
            lambda: bytes(TYPESTORE.serialize_cdr(as_rosbags, typename)),
            lambda raw: TYPESTORE.deserialize_cdr(raw, typename),
        )
    )
    rclpy_codec = _rclpy_codec(typename, values)
    if rclpy_codec is not None:
        found.append(rclpy_codec)
    return found


def _rclpy_codec(typename: str, values: dict[str, Any]) -> Codec | None:
    try:
        import importlib

        from rclpy.serialization import deserialize_message, serialize_message
    except ImportError:
        return None
    package, _, name = typename.split("/")
    message_class = getattr(importlib.import_module(f"{package}.msg"), name)

    def cls_of(nested: str) -> Any:
        nested_package, _, nested_name = nested.split("/")
        return getattr(importlib.import_module(f"{nested_package}.msg"), nested_name)

    def fill(cls_name: str, fields: dict[str, Any]) -> Any:
        instance = cls_of(cls_name)()
        _, defs = TYPESTORE.fielddefs[cls_name]
        for field, (kind, desc) in defs:
            value = fields[field]
            setattr(instance, field, fill(desc, value) if kind == Nodetype.NAME else value)
        return instance

    message = fill(typename, values)
    return Codec(
        "rclpy CDR",
        lambda: serialize_message(message),
        lambda raw: deserialize_message(raw, message_class),
    )


def time_codec(codec: Codec, n: int, repeats: int) -> tuple[float, int]:
    """Median microseconds per encode+decode over ``repeats`` runs of ``n``, and the size."""
    payload = codec.encode()
    runs = []
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(n):
            codec.decode(codec.encode())
        runs.append((time.perf_counter() - start) / n * 1e6)
    return statistics.median(runs), len(payload)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=2000, help="round trips per run (small types)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--json", help="write the figures to this file")
    args = parser.parse_args(argv)
    rows: list[dict[str, Any]] = []
    print(f"{'message':28} {'format':12} {'bytes':>9} {'us/msg':>10} {'x msgspec':>10}")
    for typename in MESSAGES:
        found = codecs(typename)
        cdr = [codec.encode() for codec in found if codec.name.endswith("CDR")]
        # rclpy leaves its alignment padding unwritten: compare what rosbags reads back
        as_read = [
            bytes(TYPESTORE.serialize_cdr(TYPESTORE.deserialize_cdr(raw, typename), typename))
            for raw in cdr
        ]
        if len(as_read) == 2 and as_read[0] != as_read[1]:
            raise SystemExit(f"{typename}: rosbags and rclpy CDR carry different values")
        n = max(20, args.n // 100) if typename.endswith("Image") else args.n
        base_us = 0.0
        for codec in found:
            us, size = time_codec(codec, n, args.repeats)
            base_us = base_us or us
            ratio = us / base_us
            print(f"{typename:28} {codec.name:12} {size:9} {us:10.2f} {ratio:10.2f}", flush=True)
            rows.append(
                {"message": typename, "format": codec.name, "bytes": size, "us": us, "ratio": ratio}
            )
    if not any(row["format"] == "rclpy CDR" for row in rows):
        print("rclpy is not importable here: its CDR row is left out (pip install ros-rclpy ...)")
    if args.json:
        with open(args.json, "w") as out:
            json.dump(rows, out, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
