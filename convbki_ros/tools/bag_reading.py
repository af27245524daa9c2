"""Reading a rosbag2 for ``play_bag``: open it, read its messages with a damaged bag turned
into one-line errors, group them by timestamp, and convert deserialised rosbags messages into
the installed rclpy classes (for bags whose type hash differs from the installed types').

Imports no rclpy: the message classes are looked up by name when a bag needs them.
"""

from __future__ import annotations

import array
import importlib
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from convbki_core.tools.cli import UserError


def open_bag(path: str) -> Any:
    """An open rosbags Reader; a clear UserError when the bag cannot be read."""
    from rosbags.rosbag2 import Reader
    from rosbags.rosbag2.errors import ReaderError

    try:
        reader = Reader(path)
        reader.open()
    except FileNotFoundError:
        raise UserError(f"{path}: no such bag (a rosbag2 folder with metadata.yaml, or a .mcap/.db3 file)") from None
    except ReaderError as error:
        raise UserError(f"{path}: cannot read the bag ({_one_line(error)})") from None
    except Exception as error:  # a damaged file makes the reader fail in many ways (bad UTF-8, sizes, ...)
        raise UserError(f"{path}: cannot read the bag, damaged ({error.__class__.__name__}: {_one_line(error)})") \
            from None
    return reader


def _one_line(error: BaseException, limit: int = 200) -> str:
    text = " ".join(str(error).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def checked_messages(messages: Iterator[Any], path: str) -> Iterator[Any]:
    """The reader's messages; a failure inside the reader (a damaged bag) becomes a UserError.

    Only the reading is guarded: errors of the code consuming the messages pass unchanged.
    """
    iterator = iter(messages)
    count = 0
    while True:
        try:
            item = next(iterator)
        except StopIteration:
            return
        except Exception as error:  # whatever the damaged bytes made the reader trip over
            raise UserError(f"{path}: damaged bag, reading stopped after {count} messages "
                            f"({error.__class__.__name__}: {_one_line(error)})") from None
        count += 1
        yield item


def grouped(messages: Iterator[tuple[Any, int, bytes]]) -> Iterator[tuple[int, list[tuple[Any, bytes]]]]:
    """(connection, timestamp, data) in bag order -> (timestamp, [(connection, data), ...]) groups."""
    stamp, group = None, []
    for connection, timestamp, data in messages:
        if timestamp != stamp and group:
            yield stamp, group
            group = []
        stamp = timestamp
        group.append((connection, data))
    if group:
        yield stamp, group


# Rosbags messages -> rclpy messages.
_SEQUENCE_TYPECODES = {"float": "f", "double": "d", "int8": "b", "uint8": "B", "int16": "h", "uint16": "H",
                       "int32": "i", "uint32": "I", "int64": "q", "uint64": "Q"}
_NUMPY_TYPES = {"float": np.float32, "double": np.float64, "int8": np.int8, "uint8": np.uint8,
                "int16": np.int16, "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32,
                "int64": np.int64, "uint64": np.uint64}


def rclpy_message_class(msgtype: str) -> type:
    """``pkg/msg/Name`` -> the installed rclpy class (ImportError/AttributeError when absent)."""
    package, kind, name = msgtype.split("/")
    return getattr(importlib.import_module(f"{package}.{kind}"), name)


def _class_of(namespaced: Any) -> type:
    return getattr(importlib.import_module(".".join(namespaced.namespaces)), namespaced.name)


_PLANS: dict[type, list[tuple[str, Callable[[Any], Any]]]] = {}


def _value_converter(slot: Any) -> Callable[[Any], Any]:
    """A function turning a rosbags value into what the rclpy slot of type ``slot`` accepts."""
    from rosidl_parser import definition as d

    if isinstance(slot, d.NamespacedType):
        cls = _class_of(slot)
        return lambda value: to_rclpy(value, cls)
    if isinstance(slot, d.AbstractNestedType):
        inner = slot.value_type
        if isinstance(inner, d.NamespacedType):
            cls = _class_of(inner)
            return lambda values: [to_rclpy(v, cls) for v in values]
        if isinstance(inner, d.BasicType) and inner.typename in _NUMPY_TYPES:
            dtype = _NUMPY_TYPES[inner.typename]
            if isinstance(slot, d.Array):  # fixed-size numeric arrays are numpy arrays in rclpy
                return lambda values: np.array(values, dtype=dtype)
            typecode = _SEQUENCE_TYPECODES[inner.typename]

            def sequence(values: Any) -> array.array:
                out = array.array(typecode)
                out.frombytes(np.ascontiguousarray(values, dtype=dtype).tobytes())
                return out

            return sequence
        if isinstance(inner, d.BasicType) and inner.typename == "boolean":
            return lambda values: [bool(v) for v in values]
        return list
    if isinstance(slot, d.BasicType):
        if inner_kind := {"boolean": bool, "float": float, "double": float}.get(slot.typename):
            return inner_kind
        if slot.typename in _NUMPY_TYPES:
            return int
        if slot.typename == "octet":
            return lambda value: bytes([int(value)]) if not isinstance(value, bytes) else value
        if slot.typename in ("char",):
            return lambda value: value if isinstance(value, str) else chr(int(value))
    return lambda value: value  # strings and anything else pass through


def to_rclpy(msg: Any, cls: type) -> Any:
    """Convert a rosbags message (dataclass) into an instance of the rclpy class ``cls``.

    Driven by ``cls``'s field list and slot types; fields the rosbags message lacks keep
    their defaults (a bag of an older definition still converts).
    """
    plan = _PLANS.get(cls)
    if plan is None:
        names = list(cls.get_fields_and_field_types())
        plan = [(name, _value_converter(slot)) for name, slot in zip(names, cls.SLOT_TYPES)]
        _PLANS[cls] = plan
    out = cls()
    for name, convert in plan:
        value = getattr(msg, name, None)
        if value is None:
            value = getattr(msg, f"{name}_", None)
            if value is None:
                continue
        setattr(out, name, convert(value))
    return out
