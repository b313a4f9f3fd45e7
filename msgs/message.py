"""Message base class: header fields shared by every type, array specs and validation.

Every message is a keyword-only dataclass. Header fields (`seq`, `stamp_ns`, `pub_ns`,
`frame_id`, `node`) live on the base class; a subclass declares its type name, its wire
version and, for each numpy field, an `ArraySpec` that decoding checks.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np


class MessageError(ValueError):
    """A message that does not match its type: names the topic, the type and the field."""

    def __init__(self, topic: str, type_name: str, field: str, reason: str) -> None:
        self.topic = topic
        self.type_name = type_name
        self.field = field
        self.reason = reason
        super().__init__(f"bad message on topic {topic!r}, type {type_name!r}, field {field!r}: {reason}")


@dataclass(frozen=True)
class ArraySpec:
    """What an array field may hold.

    kinds: allowed numpy dtype kinds ("u" unsigned, "i" signed, "f" float, "b" bool).
    ndim: allowed numbers of dimensions.
    """

    kinds: str
    ndim: tuple[int, ...]

    def check(self, value: Any) -> str | None:
        """Return why `value` does not fit this spec, or None when it does."""
        if not isinstance(value, np.ndarray):
            return f"expected a numpy array, got {type(value).__name__}"
        if value.dtype.kind not in self.kinds:
            return f"dtype {value.dtype} is not one of kinds {self.kinds!r}"
        if value.ndim not in self.ndim:
            return f"shape {value.shape} has {value.ndim} dims, expected {self.ndim}"
        return None


HEADER_KINDS: dict[str, type] = {"seq": int, "stamp_ns": int, "pub_ns": int, "frame_id": str, "node": str}
HEADER_FIELDS = tuple(HEADER_KINDS)
HEADER_INTS = tuple(name for name, kind in HEADER_KINDS.items() if kind is int)  # int64 on the wire, in [0, 2**63)
INT64_LIMIT = 2**63


def header_int_problem(value: object) -> str | None:
    """Why `value` is no header int (seq, stamp_ns, pub_ns: an int in [0, 2**63)), or None when it is one.
    Beyond that range msgpack or numpy's int64 fail later, far from the message (a node's status thread
    died of an OverflowError re-encoding a counter a seq of 2**63 - 1 had inflated)."""
    if not isinstance(value, int) or isinstance(value, bool):
        return f"{value!r:.40} is not an int"
    if not 0 <= value < INT64_LIMIT:
        return f"{value} is not in [0, 2**63)"
    return None


@dataclass(kw_only=True)
class Message:
    """Base of every message type.

    seq: per-publisher, per-topic sequence number (set by the publisher).
    stamp_ns: capture time of the data this message derives from (ns since the epoch).
    pub_ns: time the message was published (ns since the epoch, set by the publisher).
    frame_id: coordinate frame / sensor the data refers to.
    node: name of the publishing node (set by the publisher).
    """

    TYPE: ClassVar[str] = ""
    VERSION: ClassVar[int] = 1
    ARRAYS: ClassVar[dict[str, ArraySpec]] = {}
    # scalar fields added since the type's wire version: a message without one (recorded by an earlier
    # release) decodes with the field's default, so that its bags still play
    ADDED: ClassVar[frozenset[str]] = frozenset()

    seq: int = 0
    stamp_ns: int = 0
    pub_ns: int = 0
    frame_id: str = ""
    node: str = ""

    def validate(self) -> None:
        """Raise ValueError("field: reason") when the fields are inconsistent.

        The base checks the header ints and array specs; subclasses add relations between fields.
        """
        for name in HEADER_INTS:
            reason = header_int_problem(getattr(self, name))
            if reason:
                raise ValueError(f"{name}: {reason}")
        for name, spec in self.ARRAYS.items():
            reason = spec.check(getattr(self, name))
            if reason:
                raise ValueError(f"{name}: {reason}")

    def scalar_fields(self) -> dict[str, Any]:
        """Non-array, non-header fields as plain msgpack-able values."""
        out: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            if f.name in HEADER_FIELDS or f.name in self.ARRAYS:
                continue
            out[f.name] = getattr(self, f.name)
        return out


def require_same_length(msg: Message, names: tuple[str, ...]) -> None:
    """Raise ValueError unless the arrays named all have the same first dimension."""
    first = getattr(msg, names[0]).shape[0]
    for name in names[1:]:
        n = getattr(msg, name).shape[0]
        if n != first:
            raise ValueError(f"{name}: has {n} rows but {names[0]} has {first}")


def require_image_size(width: int, height: int) -> None:
    """Raise ValueError unless `width` x `height` (px) is a positive image size: a width of 0 stopped a
    window model's slip detector (no frame width) and one of 1 scaled its fields 640-fold."""
    if width <= 0 or height <= 0:
        raise ValueError(f"width/height: {width}x{height} is not a positive image size")
