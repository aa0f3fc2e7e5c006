"""Exact conversion between arpz sensor readings and the standard ROS 2 messages, and CDR.

Why exact: a recording (``arpz record``) stores the ROS 2 message, and ``arpz play`` and the
replay camera turn it back into the arpz reading; a planner fed a replay must see the very
values the robots sent. The rules, field by field, are in docs/protocol.md "ROS 2 message
types"; in short:

- float64 fields (Imu, Temperature, Illuminance) carry the value unchanged;
- LaserScan and Range are float32 in ROS 2: the value goes out as the nearest float32 and comes
  back as the SHORTEST decimal that names that float32 (``str(np.float32(x))``), so a reading
  with at most 6 significant digits (every arpz driver's: 1 cm LIDAR steps, 0.3 cm ultrasonic
  steps) comes back bit for bit; ``is_exact`` tells when a value has more digits than float32
  keeps (the recorder counts those);
- the ultrasonic reading is in centimetres, ROS 2's Range in metres (REP 103): the division by
  100 is undone in decimal arithmetic, exactly;
- the string and boolean kinds map to two documented values each; camera frames and point
  clouds keep their bytes.

ROS 2 -> arpz -> ROS 2 gives the same message for every message this module makes. Everything
here is pure (rosbags' typestore and numpy, no I/O).
"""

from __future__ import annotations

import math
from decimal import Decimal
from typing import Any, Final, NamedTuple

import numpy as np
from rosbags.typesys import Stores, get_typestore

from arpz.core.errors import ArpzError
from arpz.core.messages import SensorValue
from arpz.core.rosmsg.types import ros_type_for

#: the ROS 2 distribution whose message definitions arpz writes (sensor_msgs has not changed
#: the types used here since Foxy)
STORE: Final = get_typestore(Stores.ROS2_HUMBLE)
#: the CDR encapsulation header of little-endian plain CDR (ROS 2's default)
CDR_LE_HEADER: Final = b"\x00\x01\x00\x00"

#: light: the photosensitive module is a comparator with one output; "light" is sent as this
#: illuminance and any illuminance at or above DARK_BELOW_LX reads back as "light"
LIGHT_LX: Final = 100.0
DARK_LX: Final = 0.0
DARK_BELOW_LX: Final = 1.0
#: the HC-SR04 datasheet: 15 degrees field of view, 2 cm to 4 m
ULTRASONIC_FOV_RAD: Final = math.radians(15.0)
ULTRASONIC_MIN_M: Final = 0.02
ULTRASONIC_MAX_M: Final = 4.0
#: the camera's pixel encoding (SimCamera: RGB, row-major)
CAMERA_ENCODING: Final = "rgb8"
#: frame sizes tried, in order, to give a camera frame its width and height from its length
COMMON_CAMERA_SIZES: Final = ((640, 480), (320, 240), (1280, 720), (1920, 1080), (160, 120))
#: sensor_msgs/msg/PointField FLOAT32
_FLOAT32: Final = 7
_NOT_PROVIDED: Final = np.array([-1.0] + [0.0] * 8, dtype=np.float64)
_UNKNOWN_COVARIANCE: Final = np.zeros(9, dtype=np.float64)


class ConversionError(ArpzError, ValueError):
    """A value or a message that has no counterpart in the other form; the message says which."""


class RosReading(NamedTuple):
    """An arpz reading recovered from a ROS 2 message. ``stamp_ns`` and ``frame_id`` are None
    for ``std_msgs/msg/Bool``, which has no header (a recording keeps the stamp as log time)."""

    value: SensorValue
    stamp_ns: int | None
    frame_id: str | None


# -- float32 and stamps ----------------------------------------------------------------------


def to_float32(value: float) -> float:
    """The float32 a ROS 2 float32 field holds for ``value`` (as a Python float)."""
    return float(np.float32(value))


def from_float32(value: float) -> float:
    """The shortest decimal that names the float32 ``value``: the arpz reading back."""
    return float(str(np.float32(value)))


def is_exact(kind: str, value: SensorValue) -> bool:
    """True when ``value`` of ``kind`` comes back from its ROS 2 message unchanged (only the
    float32 kinds can fail: a value with more significant digits than float32 keeps)."""
    if kind == "lidar" and isinstance(value, float):
        return from_float32(to_float32(value)) == value or math.isnan(value)
    if kind == "ultrasonic" and isinstance(value, float):
        return _cm_back(_cm_to_m(value)) == value or math.isnan(value)
    return True


def _cm_to_m(value_cm: float) -> float:
    return to_float32(value_cm / 100.0)


def _cm_back(range_m: float) -> float:
    text = str(np.float32(range_m))
    if text in ("nan", "inf", "-inf"):
        return float(text)
    return float(Decimal(text) * 100)


def _stamp(stamp_ns: int) -> Any:
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    if not -(2**31) <= sec < 2**31:
        raise ConversionError(
            f"stamp {stamp_ns} ns is outside builtin_interfaces/Time (int32 seconds)"
        )
    return STORE.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)


def _header(stamp_ns: int, frame_id: str) -> Any:
    return STORE.types["std_msgs/msg/Header"](stamp=_stamp(stamp_ns), frame_id=frame_id)


def _unheader(message: Any) -> tuple[int, str]:
    stamp = message.header.stamp
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec), str(message.header.frame_id)


def camera_size(n_bytes: int) -> tuple[int, int]:
    """(width, height) of an RGB frame of ``n_bytes``: the first common size that fits, else one
    row of pixels (a frame of another size still converts, exactly, just not as a picture)."""
    for width, height in COMMON_CAMERA_SIZES:
        if width * height * 3 == n_bytes:
            return width, height
    if n_bytes % 3:
        raise ConversionError(f"a camera frame of {n_bytes} bytes is not whole RGB pixels")
    return n_bytes // 3, 1


# -- arpz -> ROS 2 ---------------------------------------------------------------------------


def to_ros(
    kind: str,
    value: SensorValue,
    *,
    stamp_ns: int,
    frame_id: str,
    size: tuple[int, int] | None = None,
) -> Any:
    """The ROS 2 message (a rosbags typestore object) of one reading. ``size``: a camera
    frame's (width, height), guessed from its length when not given."""
    typename = ros_type_for(kind)
    types = STORE.types
    if kind in ("flame", "pir"):
        if kind == "flame" and isinstance(value, bool):
            return types[typename](data=value)
        if kind == "pir" and value in ("detect", "not detect"):
            return types[typename](data=value == "detect")
        raise ConversionError(f"{kind} value {value!r} has no std_msgs/msg/Bool")
    header = _header(stamp_ns, frame_id)
    if kind == "camera" and isinstance(value, bytes):
        width, height = size or camera_size(len(value))
        if width * height * 3 != len(value):
            raise ConversionError(f"{width}x{height} RGB is not a frame of {len(value)} bytes")
        return types[typename](
            header=header,
            height=height,
            width=width,
            encoding=CAMERA_ENCODING,
            is_bigendian=0,
            step=width * 3,
            data=np.frombuffer(value, dtype=np.uint8),
        )
    if kind == "pointcloud" and isinstance(value, bytes):
        if len(value) % 12:
            raise ConversionError(f"a point cloud of {len(value)} bytes is not whole xyz points")
        field = types["sensor_msgs/msg/PointField"]
        return types[typename](
            header=header,
            height=1,
            width=len(value) // 12,
            fields=[
                field(name=name, offset=4 * i, datatype=_FLOAT32, count=1)
                for i, name in enumerate("xyz")
            ],
            is_bigendian=False,
            point_step=12,
            row_step=len(value),
            data=np.frombuffer(value, dtype=np.uint8),
            is_dense=True,
        )
    if kind == "light" and value in ("light", "dark"):
        lux = LIGHT_LX if value == "light" else DARK_LX
        return types[typename](header=header, illuminance=lux, variance=0.0)
    if not isinstance(value, float):
        raise ConversionError(f"{kind} value {value!r} is not a float")
    if kind == "lidar":
        return types[typename](
            header=header,
            angle_min=0.0,
            angle_max=0.0,
            angle_increment=0.0,
            time_increment=0.0,
            scan_time=0.0,
            range_min=0.0,
            range_max=math.inf,
            ranges=np.array([value], dtype=np.float32),
            intensities=np.array([], dtype=np.float32),
        )
    if kind == "ultrasonic":
        return types[typename](
            header=header,
            radiation_type=0,  # ULTRASOUND
            field_of_view=ULTRASONIC_FOV_RAD,
            min_range=ULTRASONIC_MIN_M,
            max_range=ULTRASONIC_MAX_M,
            range=_cm_to_m(value),
        )
    if kind == "dht11":
        return types[typename](header=header, temperature=value, variance=0.0)
    if kind == "imu":
        vector = types["geometry_msgs/msg/Vector3"]
        return types[typename](
            header=header,
            orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=_NOT_PROVIDED.copy(),
            angular_velocity=vector(x=0.0, y=0.0, z=0.0),
            angular_velocity_covariance=_NOT_PROVIDED.copy(),
            linear_acceleration=vector(x=0.0, y=0.0, z=value),
            linear_acceleration_covariance=_UNKNOWN_COVARIANCE.copy(),
        )
    raise ConversionError(f"{kind} value {value!r} has no {typename}")


# -- ROS 2 -> arpz ---------------------------------------------------------------------------


def from_ros(kind: str, message: Any) -> RosReading:
    """The arpz reading a ROS 2 message of ``kind``'s type carries."""
    typename = ros_type_for(kind)
    if getattr(message, "__msgtype__", None) != typename:
        raise ConversionError(
            f"a {kind} reading is a {typename}, got {getattr(message, '__msgtype__', message)!r}"
        )
    if kind == "flame":
        return RosReading(bool(message.data), None, None)
    if kind == "pir":
        return RosReading("detect" if message.data else "not detect", None, None)
    stamp_ns, frame_id = _unheader(message)
    value: SensorValue
    if kind in ("camera", "pointcloud"):
        value = bytes(np.asarray(message.data, dtype=np.uint8).tobytes())
    elif kind == "light":
        value = "light" if message.illuminance >= DARK_BELOW_LX else "dark"
    elif kind == "lidar":
        if len(message.ranges) != 1:
            raise ConversionError(f"an arpz lidar reading is one beam, got {len(message.ranges)}")
        value = from_float32(float(message.ranges[0]))
    elif kind == "ultrasonic":
        value = _cm_back(float(message.range))
    elif kind == "dht11":
        value = float(message.temperature)
    else:  # imu: the magnitude of the linear acceleration (z alone when x = y = 0)
        acc = message.linear_acceleration
        x, y, z = float(acc.x), float(acc.y), float(acc.z)
        value = z if x == 0.0 and y == 0.0 else math.hypot(x, y, z)
    return RosReading(value, stamp_ns, frame_id)


# -- CDR -------------------------------------------------------------------------------------


def serialize(message: Any) -> bytes:
    """Little-endian CDR with its 4-byte encapsulation header, as rosbag2 stores it."""
    return bytes(STORE.serialize_cdr(message, message.__msgtype__, little_endian=True))


def deserialize(data: bytes, typename: str) -> Any:
    """The message of ``typename`` in CDR ``data`` (either byte order)."""
    try:
        return STORE.deserialize_cdr(data, typename)
    except Exception as exc:  # rosbags raises plain errors (struct.error, IndexError, ...)
        raise ConversionError(f"not a CDR {typename}: {exc}") from None


def to_cdr(
    kind: str,
    value: SensorValue,
    *,
    stamp_ns: int,
    frame_id: str,
    size: tuple[int, int] | None = None,
) -> bytes:
    """One reading as the CDR bytes of its ROS 2 message."""
    return serialize(to_ros(kind, value, stamp_ns=stamp_ns, frame_id=frame_id, size=size))


def from_cdr(kind: str, data: bytes) -> RosReading:
    """The reading in the CDR bytes of ``kind``'s ROS 2 message."""
    return from_ros(kind, deserialize(data, ros_type_for(kind)))


def message_definition(typename: str) -> str:
    """The full ``ros2msg`` definition of ``typename`` with every type it uses, as rosbag2
    writes it into an MCAP schema."""
    text, _ = STORE.generate_msgdef(typename, ros_version=2)
    return str(text)
