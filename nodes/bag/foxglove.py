"""`fv bag export --format foxglove`: a bag as one MCAP file that Foxglove reads without our codec.

Every message becomes a JSON object (MCAP message encoding ``json``) described by a JSON Schema
(schema encoding ``jsonschema``); its log time, publish time and sequence are the recorded ones, and
its channel keeps the recorded channel's metadata (publishing node, latched).

- `Image` topics in one of Foxglove's well-known image schemas, ``timestamp`` the frame's stamp_ns,
  ``data`` base64 (the schema says ``contentEncoding: base64``), as `IMAGE_KINDS` says:
  "png" (default) ``foxglove.CompressedImage`` {timestamp, frame_id, data, format: "png"}, lossless:
  the pixels the markers were tracked in; "jpeg" the same with format "jpeg" (OpenCV's quality 95):
  smaller, but its 8x8 blocks and ringing around the dots are not what was recorded; "raw"
  ``foxglove.RawImage`` {timestamp, frame_id, width, height, encoding (mono8 / bgr8 / rgb8, as
  recorded), step (bytes per row), data (rows of pixels)}.
- every other type with schema ``fv.<Type>`` made from its message definition: {timestamp (stamp_ns),
  pub_time (pub_ns), seq, frame_id, node, then each scalar field as its JSON type and each array field
  as nested lists (a (H, W, 3) field: H lists of W lists of 3 numbers, so that Foxglove's message
  paths index it as ``/field.field[12][3][2]`` and ``np.asarray`` gives it back; NaN and infinities,
  which JSON cannot hold, as null)}. Times are {sec, nsec}, as in Foxglove's schemas (an int64 of ns
  is past the 2**53 that a JSON number holds exactly in Foxglove).
"""
from __future__ import annotations

import base64
import json
import math
from pathlib import Path
from typing import IO, Any

import numpy as np
from mcap.writer import CompressionType, Writer

import msgs
from msgs import Image, Message
from msgs.camera import ENCODING_CHANNELS
from msgs.wire import scalar_defaults
from nodes.bag.codec import META_LATCHED, META_NODE
from nodes.bag.reader import BagMessage, BagReader

MESSAGE_ENCODING = "json"
SCHEMA_ENCODING = "jsonschema"
IMAGE_KINDS = ("png", "jpeg", "raw")
TYPE_PREFIX = "fv."  # schema names of our own types: fv.SlipState ...
CHUNK_B = 1 << 20
# zlib level of the PNG frames. On 300 frames of a 320x240 bgr8 recording (peanuts 8), per frame: OpenCV's
# default 3.8 ms, 101 kB (100 kB in the file's zstd chunks); 4: 9 ms, 81 kB (81 kB); 6: 19 ms, 77 kB (77 kB).
# The raw pixels in base64 take 78 kB in the chunks too, but 307 kB in each message Foxglove parses and holds.
PNG_LEVEL = 4

TIME_SCHEMA: dict[str, Any] = {
    "type": "object", "title": "time",
    "properties": {"sec": {"type": "integer", "minimum": 0},
                   "nsec": {"type": "integer", "minimum": 0, "maximum": 999_999_999}},
    "required": ["sec", "nsec"]}
BASE64: dict[str, Any] = {"type": "string", "contentEncoding": "base64"}
FRAME_ID: dict[str, Any] = {"type": "string", "description": "Frame of reference for the image"}


def _object(title: str, description: str, properties: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """A JSON Schema of an object with `properties`, every one required."""
    return {"title": title, "description": description, "type": "object", "properties": properties,
            "required": list(properties)}


COMPRESSED_IMAGE_SCHEMA = _object("foxglove.CompressedImage", "A compressed image", {
    "timestamp": {**TIME_SCHEMA, "description": "Timestamp of image"}, "frame_id": FRAME_ID,
    "data": {**BASE64, "description": "Compressed image data"},
    "format": {"type": "string", "description": "Image format"}})
RAW_IMAGE_SCHEMA = _object("foxglove.RawImage", "A raw image", {
    "timestamp": {**TIME_SCHEMA, "description": "Timestamp of image"}, "frame_id": FRAME_ID,
    "width": {"type": "integer", "minimum": 0, "description": "Image width"},
    "height": {"type": "integer", "minimum": 0, "description": "Image height"},
    "encoding": {"type": "string", "description": "Encoding of the raw image data"},
    "step": {"type": "integer", "minimum": 0, "description": "Byte length of a single row"},
    "data": {**BASE64, "description": "Raw image data"}})

SCALAR_TYPES: tuple[tuple[type, str], ...] = (  # bool before int: a bool is an int in Python
    (bool, "boolean"), (int, "integer"), (float, "number"), (str, "string"), (list, "array"), (dict, "object"))


def foxglove_time(ns: int) -> dict[str, int]:
    """{sec, nsec} of a time in ns since the epoch."""
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _scalar_type(default: Any) -> str:
    for kind, name in SCALAR_TYPES:
        if isinstance(default, kind):
            return name
    raise TypeError(f"no JSON type for a field of {type(default).__name__}")


def _array_schema(type_name: str, name: str, spec: msgs.ArraySpec) -> dict[str, Any]:
    """Nested-list schema of array field `name` of `type_name`: one "array" level per dimension."""
    if len(spec.ndim) != 1:
        raise ValueError(f"{type_name}.{name}: an array of {' or '.join(map(str, spec.ndim))} dimensions "
                         "has no one JSON schema")
    if set(spec.kinds) <= set("iu"):
        schema: dict[str, Any] = {"type": "integer"}
    elif set(spec.kinds) <= set("iuf"):
        schema = {"type": ["number", "null"]}  # null: NaN or an infinity
    elif spec.kinds == "b":
        schema = {"type": "boolean"}
    else:
        raise ValueError(f"{type_name}.{name}: no JSON type for array kinds {spec.kinds!r}")
    for _ in range(spec.ndim[0]):
        schema = {"type": "array", "items": schema}
    return schema


def message_schema(type_name: str) -> dict[str, Any]:
    """The JSON Schema of a registered message type other than Image (see the module's docstring)."""
    cls = msgs.message_type(type_name)
    properties: dict[str, dict[str, Any]] = {
        "timestamp": {**TIME_SCHEMA, "description": "stamp_ns: capture time of the data"},
        "pub_time": {**TIME_SCHEMA, "description": "pub_ns: time the message was published"},
        "seq": {"type": "integer", "minimum": 0}, "frame_id": {"type": "string"}, "node": {"type": "string"}}
    properties.update({name: {"type": _scalar_type(default)} for name, default in scalar_defaults(cls).items()})
    properties.update({name: _array_schema(type_name, name, spec) for name, spec in cls.ARRAYS.items()})
    doc = (cls.__doc__ or "").strip().splitlines()
    return _object(TYPE_PREFIX + type_name, doc[0] if doc else "", properties)


def _plain(value: Any) -> Any:
    """`value` (a scalar field's: number, text, list, map) with NaN and infinities, at any depth, as None."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


def _array(values: np.ndarray) -> list:
    """Nested lists of an array, NaN and infinities as None. A float32 value is written with the fewest
    digits that give it back (0.7703418, not 0.7703418135643005: a 30x30x3 field's JSON 33 kB, not 56)."""
    if values.dtype == np.float32:
        values = values.astype(str).astype(np.float64)  # numpy's shortest float32 text, read as a float64
    if values.dtype.kind == "f" and not np.isfinite(values).all():
        values = np.where(np.isfinite(values), values.astype(object), None)
    return values.tolist()


def message_json(msg: Message) -> dict[str, Any]:
    """The JSON object of a message of any type but Image."""
    out: dict[str, Any] = {"timestamp": foxglove_time(msg.stamp_ns), "pub_time": foxglove_time(msg.pub_ns),
                           "seq": msg.seq, "frame_id": msg.frame_id, "node": msg.node}
    out.update({name: _plain(value) for name, value in msg.scalar_fields().items()})
    out.update({name: _array(getattr(msg, name)) for name in msg.ARRAYS})
    return out


def image_json(img: Image, kind: str) -> dict[str, Any]:
    """The foxglove.CompressedImage ("png", "jpeg") or foxglove.RawImage ("raw") object of a frame."""
    head = {"timestamp": foxglove_time(img.stamp_ns), "frame_id": img.frame_id}
    if kind == "raw":
        data = np.ascontiguousarray(img.data)
        return {**head, "width": img.width, "height": img.height, "encoding": img.encoding,
                "step": img.width * ENCODING_CHANNELS[img.encoding], "data": base64.b64encode(data).decode()}
    import cv2
    pixels = img.data[..., ::-1] if img.encoding == "rgb8" else img.data  # OpenCV writes BGR or grey
    params = [cv2.IMWRITE_PNG_COMPRESSION, PNG_LEVEL] if kind == "png" else []
    ok, encoded = cv2.imencode(f".{kind}", np.ascontiguousarray(pixels), params)
    if not ok:
        raise RuntimeError(f"OpenCV cannot encode a {img.width}x{img.height} {img.encoding} frame as {kind}")
    return {**head, "data": base64.b64encode(encoded).decode(), "format": kind}


class _FoxgloveWriter:
    """Schemas and channels of the output, registered as their first message comes."""

    def __init__(self, stream: IO[bytes], images: str) -> None:
        self.images = images
        self.writer = Writer(stream, chunk_size=CHUNK_B, compression=CompressionType.ZSTD)
        self.writer.start()
        self._schemas: dict[str, int] = {}
        self._channels: dict[tuple[str, str, str, bool], int] = {}

    def _schema(self, type_name: str) -> int:
        if type_name not in self._schemas:
            if type_name == Image.TYPE:
                schema = RAW_IMAGE_SCHEMA if self.images == "raw" else COMPRESSED_IMAGE_SCHEMA
            else:
                schema = message_schema(type_name)
            self._schemas[type_name] = self.writer.register_schema(
                schema["title"], SCHEMA_ENCODING, json.dumps(schema).encode())
        return self._schemas[type_name]

    def _channel(self, rec: BagMessage, type_name: str) -> int:
        key = (rec.topic, type_name, rec.node, rec.latched)
        if key not in self._channels:
            self._channels[key] = self.writer.register_channel(
                rec.topic, MESSAGE_ENCODING, self._schema(type_name),
                {META_NODE: rec.node, META_LATCHED: "true" if rec.latched else "false"})
        return self._channels[key]

    def write(self, rec: BagMessage, msg: Message) -> None:
        obj = image_json(msg, self.images) if isinstance(msg, Image) else message_json(msg)
        data = json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()
        self.writer.add_message(self._channel(rec, msg.TYPE), rec.log_time_ns, data, rec.publish_time_ns,
                                rec.sequence)


def export_foxglove(bag: BagReader, topics: list[str] | None, output: Path, images: str = "png") -> int:
    """Write `topics` of `bag` (None: every topic) to the MCAP file `output`, whole or not at all
    (`fv_algos.atomic_file`); returns the number of messages written. images: one of IMAGE_KINDS."""
    from fv_algos.atomic_file import write_atomically
    if images not in IMAGE_KINDS:
        raise ValueError(f"image kind {images!r} is not one of {list(IMAGE_KINDS)}")
    count = 0

    def write(tmp: Path) -> None:
        nonlocal count
        with open(tmp, "wb") as stream:
            out = _FoxgloveWriter(stream, images)
            for rec, msg in bag.decoded(topics):
                out.write(rec, msg)
                count += 1
            out.writer.finish()

    write_atomically(output, write)
    return count
