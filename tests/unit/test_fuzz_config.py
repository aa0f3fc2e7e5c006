"""Fuzzing config loading: whatever a TOML file or a dict holds, only ConfigError may escape.

A robot's ``python -m arpz.robot`` must exit with code 2 and a message naming the file and the
field for ANY bad file, never with a traceback, so ``arpz.core.config.load_toml`` and ``from_dict``
may raise nothing but ``ConfigError``. The values are drawn from the config Structs' own field
types (read with ``msgspec.inspect``, so fields added later are fuzzed too), mixed with values of
the wrong type, unknown fields, and text that is not TOML at all.
"""

from __future__ import annotations

import datetime as dt
import json
import math
import tempfile
from pathlib import Path
from typing import Any

import msgspec
import msgspec.inspect as mi
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from arpz.core.config import CeddpConfig, ConfigError, RobotConfig, from_dict, load_toml

FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
KINDS: list[type[msgspec.Struct]] = [RobotConfig, CeddpConfig]

# what TOML itself can hold
toml_scalars = st.one_of(
    st.booleans(),
    st.integers(min_value=-(2**63), max_value=2**63 - 1),
    st.floats(),
    st.text(max_size=12),
    st.sampled_from(["robot1", "lab", "tcp/127.0.0.1:7447", "machine1", "pir", "replay", "sim"]),
    st.datetimes(max_value=dt.datetime(9999, 1, 1)),
    st.dates(),
)
toml_values = st.recursive(
    toml_scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=4), st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=12,
)


def for_type(t: mi.Type) -> st.SearchStrategy[Any]:
    """A value that is plausible for the field type ``t``, often at or beyond its edge."""
    if isinstance(t, mi.StructType):
        return struct_dict(t)
    if isinstance(t, mi.UnionType):
        return st.one_of([for_type(member) for member in t.types])
    if isinstance(t, mi.NoneType):
        return st.just(None)  # TOML has no null: from_dict must still say something useful
    if isinstance(t, mi.BoolType):
        return st.booleans()
    if isinstance(t, mi.IntType):
        return st.one_of(st.integers(-3, 10), st.integers(-(2**63), 2**63 - 1))
    if isinstance(t, mi.FloatType):
        return st.one_of(
            st.sampled_from([0.0, -1.0, 1e-300, 1e300, math.inf, -math.inf, math.nan]),
            st.floats(),
            st.integers(-5, 5),
        )
    if isinstance(t, mi.StrType):
        return st.one_of(
            st.sampled_from(["robot1", "r-2", "Robot One", "a/b", "*", "", "hello", "x" * 200]),
            st.text(max_size=10),
        )
    if isinstance(t, mi.LiteralType):
        return st.sampled_from(list(t.values))
    if isinstance(t, mi.EnumType):
        return st.sampled_from([member.value for member in t.cls])
    if isinstance(t, mi.ListType):
        return st.lists(for_type(t.item_type), max_size=3)
    if isinstance(t, mi.DictType):
        return st.dictionaries(st.text(max_size=6), toml_values, max_size=3)
    return toml_values


def struct_dict(t: mi.StructType) -> st.SearchStrategy[dict[str, Any]]:
    """Some of the Struct's fields (typed, or of a wrong type), sometimes an unknown one."""
    field_values = {
        f.name: st.one_of(for_type(f.type), for_type(f.type), toml_values) for f in t.fields
    }
    known = st.fixed_dictionaries({}, optional=field_values)
    unknown = st.dictionaries(
        st.sampled_from(["rate", "robot", "typo_s", ""]), toml_values, max_size=1
    )
    return st.builds(lambda a, b: {**a, **b}, known, st.one_of(st.just({}), unknown))


def config_dicts(kind: type[msgspec.Struct]) -> st.SearchStrategy[dict[str, Any]]:
    info = mi.type_info(kind)
    assert isinstance(info, mi.StructType)
    return struct_dict(info)


def _toml_value(value: Any) -> str:
    """Inline TOML for any value the strategies make (None has no TOML form: an empty array)."""
    if value is None:
        return "[]"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, dt.datetime | dt.date):
        return value.isoformat()
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return (
            "{" + ", ".join(f"{json.dumps(k)} = {_toml_value(v)}" for k, v in value.items()) + "}"
        )
    raise TypeError(type(value))


def to_toml(data: dict[str, Any]) -> str:
    return "".join(f"{json.dumps(key)} = {_toml_value(value)}\n" for key, value in data.items())


@st.composite
def corrupted(draw: st.DrawFn, text: str) -> str:
    for _ in range(draw(st.integers(1, 3))):
        at = draw(st.integers(0, len(text)))
        op = draw(st.sampled_from(["insert", "delete", "dup-line"]))
        if op == "insert":
            text = text[:at] + draw(st.text(min_size=1, max_size=4)) + text[at:]
        elif op == "delete":
            text = text[:at] + text[at + draw(st.integers(1, 20)) :]
        else:
            lines = text.splitlines(keepends=True) or [""]
            i = draw(st.integers(0, len(lines) - 1))
            text = "".join([*lines[: i + 1], lines[i], *lines[i + 1 :]])
    return text


def _check(kind: type[msgspec.Struct], load: Any) -> None:
    try:
        config = load()
    except ConfigError as exc:
        assert str(exc), "a ConfigError must say what is wrong"
        return
    assert isinstance(config, kind)


@FUZZ
@given(kind=st.sampled_from(KINDS), data=st.data())
def test_from_dict_raises_only_config_error(
    kind: type[msgspec.Struct], data: st.DataObject
) -> None:
    raw = data.draw(config_dicts(kind))
    if kind is RobotConfig and data.draw(st.booleans()):
        raw.setdefault("robot_id", "robot1")  # get past the required field more often
    overrides = data.draw(
        st.one_of(
            st.none(),
            st.dictionaries(
                st.sampled_from(["fleet", "seed", "listen", "connect", "duration_s"]),
                toml_values,
                max_size=2,
            ),
        )
    )
    _check(kind, lambda: from_dict(raw, kind, overrides, source="fuzz"))


@FUZZ
@given(kind=st.sampled_from(KINDS), data=st.data())
@example(kind=RobotConfig, data=None)
def test_load_toml_raises_only_config_error(
    kind: type[msgspec.Struct], data: st.DataObject | None
) -> None:
    if data is None:  # explicit edge: bytes that are not UTF-8
        content: bytes = b'robot_id = "\xff\xfe"\n'
    else:
        source = data.draw(st.sampled_from(["fields", "fields", "deploy", "text"]), label="source")
        if source == "fields":
            text = to_toml(data.draw(config_dicts(kind)))
        elif source == "deploy":
            name = "robot1.toml" if kind is RobotConfig else "ceddp.toml"
            text = data.draw(corrupted((DEPLOY / name).read_text()))
        else:
            text = data.draw(st.text(max_size=200))
        content = text.encode("utf-8", errors="surrogatepass")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "config.toml"
        path.write_bytes(content)
        _check(kind, lambda: load_toml(path, kind))
