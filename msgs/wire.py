"""Wire codec: a msgpack header frame followed by one raw frame per numpy array.

Frames of one message::

    [header, array_0, array_1, ...]

header is a msgpack map ``{type, version, seq, stamp_ns, pub_ns, frame_id, node,
fields: {name: value}, arrays: [[name, dtype, shape], ...]}`` where dtype is numpy's
string with byte order (``"<f4"``, ``"|u1"``). Array frames are the arrays' raw C-order
bytes, passed to ZeroMQ as buffers (no copy on send; decoded arrays are read-only
views of the received frames).
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Iterable

import msgpack
import numpy as np

from msgs.message import HEADER_FIELDS, HEADER_INTS, HEADER_KINDS, Message, MessageError, header_int_problem

MAX_NDIM = 8

_REGISTRY: dict[str, type[Message]] = {}


def register(cls: type[Message]) -> type[Message]:
    """Make a message class decodable by its TYPE name."""
    _REGISTRY[cls.TYPE] = cls
    return cls


def message_type(name: str) -> type[Message]:
    """The registered class for a type name; KeyError naming the known types."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise KeyError(f"unknown message type {name!r}; known: {sorted(_REGISTRY)}") from None


def known_types() -> list[str]:
    return sorted(_REGISTRY)


def encode(msg: Message) -> list[Any]:
    """Frames for `msg`: [header bytes, array buffers...]. Arrays are not copied when
    already C-contiguous."""
    arrays = []
    specs = []
    for name in msg.ARRAYS:
        arr = np.ascontiguousarray(getattr(msg, name))
        arrays.append(arr)
        specs.append([name, arr.dtype.str, list(arr.shape)])
    header = {
        "type": msg.TYPE,
        "version": msg.VERSION,
        "seq": int(msg.seq),
        "stamp_ns": int(msg.stamp_ns),
        "pub_ns": int(msg.pub_ns),
        "frame_id": msg.frame_id,
        "node": msg.node,
        "fields": msg.scalar_fields(),
        "arrays": specs,
    }
    return [msgpack.packb(header, use_bin_type=True), *(memoryview(a.reshape(-1).view(np.uint8)) for a in arrays)]


def _buffer(frame: Any) -> memoryview:
    buf = frame.buffer if hasattr(frame, "buffer") else frame
    return memoryview(buf).cast("B")


def decode_header(frame: Any, topic: str = "?") -> dict[str, Any]:
    """Unpack and check the header frame alone (no arrays): for tools that only need
    stamps, type and sizes."""
    try:
        header = msgpack.unpackb(_buffer(frame), raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises several unrelated types for garbage
        raise MessageError(topic, "?", "header", f"not a msgpack map ({type(exc).__name__}: {exc})") from None
    if not isinstance(header, dict):
        raise MessageError(topic, "?", "header", f"expected a map, got {type(header).__name__}")
    type_name = header.get("type")
    if not isinstance(type_name, str):
        raise MessageError(topic, "?", "type", "missing or not a string")
    if type_name not in _REGISTRY:
        raise MessageError(topic, type_name, "type", f"unknown type; known: {known_types()}")
    cls = _REGISTRY[type_name]
    if header.get("version") != cls.VERSION:
        raise MessageError(topic, type_name, "version",
                           f"wire version {header.get('version')!r}, this software reads {cls.VERSION}")
    for name, kind in (*HEADER_KINDS.items(), ("fields", dict), ("arrays", list)):
        if not _is_kind(header.get(name), kind):
            raise MessageError(topic, type_name, name, f"missing or not {kind.__name__}")
    for name in HEADER_INTS:
        reason = header_int_problem(header[name])
        if reason:
            raise MessageError(topic, type_name, name, reason)
    return header


def _check_scalar(cls: type[Message], name: str, value: Any, default: Any) -> Any:
    if isinstance(default, bool):
        ok = isinstance(value, bool)
    elif isinstance(default, float):
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        value = float(value) if ok else value
        ok = ok and math.isfinite(value)
    elif isinstance(default, int):
        ok = isinstance(value, int) and not isinstance(value, bool)
    else:
        ok = isinstance(value, type(default))
    if not ok:
        kind = "finite float" if isinstance(default, float) else type(default).__name__
        raise TypeError(f"{value!r:.80} is not {'an' if kind[0] in 'aeiou' else 'a'} {kind}")
    return value


def scalar_defaults(cls: type[Message]) -> dict[str, Any]:
    """{name: default value} of the scalar (non-header, non-array) fields of `cls`, in declaration order."""
    out = {}
    for f in dataclasses.fields(cls):
        if f.name in HEADER_FIELDS or f.name in cls.ARRAYS:
            continue
        out[f.name] = f.default if f.default is not dataclasses.MISSING else f.default_factory()
    return out


def decode(frames: Iterable[Any], topic: str = "?") -> Message:
    """Message from its frames; raises MessageError naming topic, type and field for a
    malformed, truncated or wrong-version message."""
    frames = list(frames)
    if not frames:
        raise MessageError(topic, "?", "header", "no frames")
    header = decode_header(frames[0], topic)
    type_name = header["type"]
    cls = _REGISTRY[type_name]
    kwargs: dict[str, Any] = {name: header[name] for name in HEADER_FIELDS}
    kwargs.update(_scalar_values(cls, header["fields"], topic))
    specs = header["arrays"]
    if [s[0] if isinstance(s, list) and s else None for s in specs] != list(cls.ARRAYS):
        raise MessageError(topic, type_name, "arrays", f"expected arrays {list(cls.ARRAYS)}, got {specs!r:.200}")
    if len(frames) != 1 + len(specs):
        raise MessageError(topic, type_name, "arrays",
                           f"{len(frames) - 1} array frames for {len(specs)} arrays (truncated?)")
    for spec, frame in zip(specs, frames[1:]):
        kwargs[spec[0]] = _decode_array(topic, type_name, spec, frame)
    msg = cls(**kwargs)
    _validate(msg, topic)
    return msg


def check_message(msg: Message) -> None:
    """Check a message about to be sent as `decode` checks it on arrival (header kinds, scalar field
    types, `validate()`), so that a message every subscriber would drop as malformed is refused where it
    is made. A numpy scalar (np.bool_, np.floating, np.integer...) of a non-array field is replaced, in
    place, by its plain Python value, as msgpack sends only those; so is an int of a float field by its
    float, as decoding gives it. ValueError "Type.field: reason" (`SlipState.probability: 1.5 is not in
    [0, 1]`), as `fv topic pub` says it.

    Not on the nodes' publish path: `encode` stays free of per-message checks.
    """
    try:
        for f in dataclasses.fields(msg):
            value = getattr(msg, f.name)
            if f.name not in msg.ARRAYS and isinstance(value, np.generic):
                setattr(msg, f.name, value.item())
        for name, kind in HEADER_KINDS.items():
            if not _is_kind(getattr(msg, name), kind):
                raise MessageError("?", msg.TYPE, name, f"{getattr(msg, name)!r:.40} is not {kind.__name__}")
            if kind is str:  # (the header's ints are range-checked by `_validate`)
                _check_sendable(msg, name, getattr(msg, name))
        for name, value in _scalar_values(type(msg), msg.scalar_fields()).items():
            setattr(msg, name, value)
            _check_sendable(msg, name, value)
        _validate(msg)
    except MessageError as exc:
        raise ValueError(f"{exc.type_name}.{exc.field}: {exc.reason}") from None


def _check_sendable(msg: Message, name: str, value: Any) -> None:
    """MessageError for a field `value` msgpack cannot carry: an int past 64 bits, a lone surrogate in text, a
    numpy value in a dict (they ended `publish` in msgpack's own OverflowError, UnicodeEncodeError or TypeError)."""
    try:
        msgpack.packb(value, use_bin_type=True)
    except (OverflowError, TypeError, ValueError) as exc:  # (UnicodeEncodeError is a ValueError)
        raise MessageError("?", msg.TYPE, name, f"{value!r:.40} cannot be sent ({exc})") from None


def _is_kind(value: Any, kind: type) -> bool:
    """`value` is a `kind` (a bool is no int)."""
    return isinstance(value, kind) and not isinstance(value, bool)


def _scalar_values(cls: type[Message], fields: dict[str, Any], topic: str = "?") -> dict[str, Any]:
    """The scalar (non-header, non-array) fields of a `cls` message from `fields` ({name: value}), checked
    and as decoded (an int of a float field as a float; one of `cls.ADDED` that is missing as its default);
    MessageError for a missing, mistyped or unknown one."""
    defaults = scalar_defaults(cls)
    values = {}
    for name, default in defaults.items():
        if name not in fields:
            if name in cls.ADDED:
                values[name] = default
                continue
            raise MessageError(topic, cls.TYPE, name, "missing")
        try:
            values[name] = _check_scalar(cls, name, fields[name], default)
        except TypeError as exc:
            raise MessageError(topic, cls.TYPE, name, str(exc)) from None
    extra = set(fields) - set(defaults)
    if extra:
        raise MessageError(topic, cls.TYPE, sorted(map(str, extra))[0], "unknown field")
    return values


def _validate(msg: Message, topic: str = "?") -> None:
    """`msg.validate()`, its ValueError("field: reason") raised as a MessageError naming the field."""
    try:
        msg.validate()
    except ValueError as exc:
        field, _, reason = str(exc).partition(": ")
        raise MessageError(topic, msg.TYPE, field, reason or str(exc)) from None


def _decode_array(topic: str, type_name: str, spec: list, frame: Any) -> np.ndarray:
    name = spec[0]
    if len(spec) != 3 or not isinstance(spec[1], str) or not isinstance(spec[2], list):
        raise MessageError(topic, type_name, name, f"array spec {spec!r:.100} is not [name, dtype, shape]")
    try:
        dtype = np.dtype(spec[1])
    except (TypeError, ValueError, SyntaxError):  # numpy parses "(2," with Python's parser
        raise MessageError(topic, type_name, name, f"dtype {spec[1]!r} is not a numpy dtype") from None
    if dtype.kind not in "biuf" or dtype.hasobject:
        raise MessageError(topic, type_name, name, f"dtype {spec[1]!r} is not a plain numeric dtype")
    shape = spec[2]
    if len(shape) > MAX_NDIM or not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape):
        raise MessageError(topic, type_name, name, f"shape {shape!r:.100} is not a list of sizes")
    buf = _buffer(frame)
    expected = math.prod(shape) * dtype.itemsize
    if buf.nbytes != expected:
        raise MessageError(topic, type_name, name,
                           f"frame holds {buf.nbytes} bytes, dtype {spec[1]} shape {shape} needs {expected}")
    try:
        return np.frombuffer(buf, dtype=dtype).reshape(shape)
    except ValueError as exc:  # an empty frame with an absurd shape such as [0, 2**63]
        raise MessageError(topic, type_name, name, f"shape {shape!r:.100}: {exc}") from None
