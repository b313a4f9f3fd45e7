"""How bus messages sit in an MCAP bag: payload layout, schemas and channel metadata.

A bus message is the frames ``[header, array_0, array_1, ...]`` (see `msgs.wire`). In a
bag its MCAP payload is those frames concatenated as they arrived::

    payload = header (one msgpack map) + array_0 bytes + array_1 bytes + ...

(message encoding ``fv-msgpack``). The header is self-delimiting and lists each
array's dtype and shape, so `split_payload` cuts the payload back into the original
frames without copying or decoding the arrays. Each channel's schema is named after
the message type (`Image`, `SlipState`...) with encoding ``fv-msgpack`` and, as data,
a JSON description of the type's version, scalar fields and arrays. A channel is one
(topic, type, publishing node, latched) tuple, so the MCAP `sequence` of a channel is
its publisher's header `seq`, gap-free when nothing was lost.
"""
from __future__ import annotations

import dataclasses
import json
import math
from typing import Any, Iterable

import msgpack
import numpy as np

import msgs
from msgs import MessageError
from msgs.message import HEADER_FIELDS

MESSAGE_ENCODING = "fv-msgpack"
SCHEMA_ENCODING = "fv-msgpack"
HEADER_PROBE_B = 512

META_NODE = "node"
META_LATCHED = "latched"
RECORDING_META = "fv_recording"  # metadata record of a recording: host, start, software, command line, topics
RECORDING_END_META = "fv_recording_end"  # metadata record of a finished recording: totals, per-topic counts and times
LATCHED_ENTRY = "latched"  # the entry of RECORDING_META that says which latched messages a recorder got as it began
LATCHED_OF_RUNNING = "of running publishers"  # its value (a recording without it may hold gone publishers' too)


def join_frames(frames: Iterable[Any]) -> bytes:
    """The MCAP payload of one bus message: its frames (bytes, buffers or zmq.Frame)
    concatenated, one copy, nothing decoded."""
    return b"".join(f.buffer if hasattr(f, "buffer") else f for f in frames)


def split_payload(data: bytes | memoryview, topic: str = "?") -> tuple[dict[str, Any], list[memoryview]]:
    """(checked header, frames) of a payload; the frames are views of `data`.

    Raises MessageError (naming the topic) when the header is not a valid message header
    or the array bytes do not add up to what the header lists.
    """
    view = memoryview(data).cast("B")
    unpacker = msgpack.Unpacker(raw=False, strict_map_key=True)
    probe = HEADER_PROBE_B
    while True:
        unpacker.feed(view[probe - HEADER_PROBE_B:probe])
        try:
            unpacker.unpack()
            break
        except msgpack.OutOfData:
            if probe >= view.nbytes:
                raise MessageError(topic, "?", "header",
                                   f"payload of {view.nbytes} bytes ends inside the header") from None
            probe += HEADER_PROBE_B
        except Exception as exc:  # msgpack raises several unrelated types for garbage
            raise MessageError(topic, "?", "header", f"not a msgpack map ({type(exc).__name__}: {exc})") from None
    end = unpacker.tell()
    header = msgs.decode_header(view[:end], topic)
    frames = [view[:end]]
    for spec in header["arrays"]:
        try:
            size = math.prod(spec[2]) * np.dtype(spec[1]).itemsize
        except (TypeError, IndexError, ValueError):
            raise MessageError(topic, header["type"], "arrays",
                               f"array spec {spec!r:.100} is not [name, dtype, shape]") from None
        frames.append(view[end:end + size])
        end += size
    if end != view.nbytes:
        raise MessageError(topic, header["type"], "arrays",
                           f"payload holds {view.nbytes} bytes, header and arrays need {end}")
    return header, frames


def schema_data(type_name: str) -> bytes:
    """JSON description of a registered message type for its MCAP schema record."""
    cls = msgs.message_type(type_name)
    scalars = {f.name: getattr(f.type, "__name__", str(f.type)) for f in dataclasses.fields(cls)
               if f.name not in cls.ARRAYS and f.name not in HEADER_FIELDS}
    arrays = {name: {"kinds": spec.kinds, "ndim": list(spec.ndim)} for name, spec in cls.ARRAYS.items()}
    doc = (cls.__doc__ or "").strip().splitlines()
    return json.dumps({"type": cls.TYPE, "version": cls.VERSION, "header": list(HEADER_FIELDS),
                       "fields": scalars, "arrays": arrays, "doc": doc[0] if doc else "",
                       "payload": "msgpack header map, then each array's raw C-order bytes in header order"},
                      sort_keys=True).encode()
