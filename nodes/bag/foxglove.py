"""`fv bag export --format foxglove`: a bag as one MCAP file that Foxglove reads without our codec.

Every message becomes a JSON object (MCAP message encoding ``json``) described by a JSON Schema
(schema encoding ``jsonschema``); its log time, publish time and sequence are the recorded ones, and
its channel keeps the recorded channel's metadata (publishing node, latched). The bag's metadata
records and attachments (the launch file) are copied.

- `Image` topics in one of Foxglove's well-known image schemas, ``timestamp`` the frame's stamp_ns,
  ``data`` base64 (the schema says ``contentEncoding: base64``), as `IMAGE_KINDS` says:
  "png" (default) ``foxglove.CompressedImage`` {timestamp, frame_id, data, format: "png"}, lossless:
  the pixels the markers were tracked in; "jpeg" the same with format "jpeg" (OpenCV's quality 95):
  smaller, but its 8x8 blocks and ringing around the dots are not what was recorded; "raw"
  ``foxglove.RawImage`` {timestamp, frame_id, width, height, encoding (mono8 / bgr8 / rgb8, as
  recorded), step (bytes per row), data (rows of pixels)}.
- `CameraInfo` topics in Foxglove's ``foxglove.CameraCalibration`` {timestamp, frame_id, width, height,
  distortion_model, D, K, R, P}, which its Image and 3D panels project and undistort with:
  `DISTORTION_MODELS` names our models as Foxglove does ("fisheye", OpenCV's fisheye model, is
  "kannala_brandt" with D = k1..k4; "pinhole", frames the camera node undistorted, is "plumb_bob" with D
  = (k1, k2, p1, p2, k3) all 0); K the recorded 3x3 matrix, R the identity, P = [K | 0], each a flat
  row-major list. rms_px, seq, pub_time and node have no place in it (the channel keeps the node).
- every other type with schema ``fv.<Type>`` made from its message definition: {timestamp (stamp_ns),
  pub_time (pub_ns), seq, frame_id, node, then each field}. Times are {sec, nsec}, as in Foxglove's
  schemas (an int64 of ns is past the 2**53 up to which a JSON number is exact in Foxglove). A list or
  map field (a status's counters, a param state's params) is its JSON text, as in the CSV export.
  A 1-D array is a JSON array (``/slip.window_stamps_ns[0]``: numbers, exact in the file, to about
  256 ns in Foxglove); one of two or more dimensions is
  {shape, data}, data flat in C order (a (30, 30, 3) field: ``/field.field.data[i]``, i = (row * 30 +
  column) * 3 + channel; ``np.reshape(data, shape)`` in Python). NaN and infinities, which JSON cannot
  hold, are null.

The schemas keep to the JSON Schema Foxglove parses: one type per property; objects with properties;
arrays with items of a single type that is not an array (nested lists would not load).
"""
from __future__ import annotations

import base64
import json
from pathlib import Path
from typing import IO, Any

import numpy as np
from mcap.writer import CompressionType, Writer

import msgs
from msgs import CameraInfo, Image, Message
from msgs.camera import ENCODING_CHANNELS
from msgs.wire import scalar_defaults
from nodes.bag.codec import META_LATCHED, META_NODE
from nodes.bag.export import cell
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


def _numbers(description: str, count: int | None = None) -> dict[str, Any]:
    """Schema of a JSON array of numbers, of exactly `count` items when given."""
    sized = {} if count is None else {"minItems": count, "maxItems": count}
    return {"type": "array", "items": {"type": "number"}, **sized, "description": description}


CAMERA_CALIBRATION_SCHEMA = _object("foxglove.CameraCalibration", "Camera calibration parameters", {
    "timestamp": {**TIME_SCHEMA, "description": "Timestamp of calibration data"},
    "frame_id": {"type": "string", "description": "Frame of reference for the camera"},
    "width": {"type": "integer", "minimum": 0, "description": "Image width"},
    "height": {"type": "integer", "minimum": 0, "description": "Image height"},
    "distortion_model": {"type": "string", "description": "Name of distortion model"},
    "D": _numbers("Distortion parameters"),
    "K": _numbers("Intrinsic camera matrix (3x3 row-major matrix)", 9),
    "R": _numbers("Rectification matrix (3x3 row-major matrix)", 9),
    "P": _numbers("Projection/camera matrix (3x4 row-major matrix)", 12)})
# CameraInfo.model (msgs.camera.CAMERA_MODELS) -> Foxglove's distortion_model. Foxglove's schema documents
# plumb_bob (k1, k2, p1, p2, k3), rational_polynomial and kannala_brandt (k1..k4, "matches the OpenCV fisheye
# model"); ROS calls the latter "equidistant", a name Foxglove's schema does not list.
DISTORTION_MODELS: dict[str, str] = {"fisheye": "kannala_brandt", "pinhole": "plumb_bob"}

SCALAR_TYPES: tuple[tuple[type, str], ...] = (  # bool before int: a bool is an int in Python
    (bool, "boolean"), (int, "integer"), (float, "number"), (str, "string"), (list, "string"), (dict, "string"))


def foxglove_time(ns: int) -> dict[str, int]:
    """{sec, nsec} of a time in ns since the epoch."""
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def _scalar_schema(default: Any) -> dict[str, Any]:
    for kind, name in SCALAR_TYPES:
        if isinstance(default, kind):
            return {"type": name, "description": "JSON text"} if kind in (list, dict) else {"type": name}
    raise TypeError(f"no JSON type for a field of {type(default).__name__}")


def _array_schema(type_name: str, name: str, spec: msgs.ArraySpec) -> dict[str, Any]:
    """Schema of array field `name` of `type_name`: a JSON array when 1-D, else {shape, data}."""
    if set(spec.kinds) <= set("iu"):
        item = "integer"
    elif set(spec.kinds) <= set("iuf"):
        item = "number"
    elif spec.kinds == "b":
        item = "boolean"
    else:
        raise ValueError(f"{type_name}.{name}: no JSON type for array kinds {spec.kinds!r}")
    values = {"type": "array", "items": {"type": item}}
    if item == "number":
        values["description"] = "null where NaN or infinite"
    if spec.ndim == (1,):
        return values
    return _object(f"{TYPE_PREFIX}{type_name}.{name}", "array of shape `shape`, `data` flat in C order",
                   {"shape": {"type": "array", "items": {"type": "integer"}}, "data": values})


def message_schema(type_name: str) -> dict[str, Any]:
    """The ``fv.<Type>`` JSON Schema of a registered message type (see the module's docstring)."""
    cls = msgs.message_type(type_name)
    properties: dict[str, dict[str, Any]] = {
        "timestamp": {**TIME_SCHEMA, "description": "stamp_ns: capture time of the data"},
        "pub_time": {**TIME_SCHEMA, "description": "pub_ns: time the message was published"},
        "seq": {"type": "integer", "minimum": 0}, "frame_id": {"type": "string"}, "node": {"type": "string"}}
    properties.update({name: _scalar_schema(default) for name, default in scalar_defaults(cls).items()})
    properties.update({name: _array_schema(type_name, name, spec) for name, spec in cls.ARRAYS.items()})
    doc = (cls.__doc__ or "").strip().splitlines()
    return _object(TYPE_PREFIX + type_name, doc[0] if doc else "", properties)


def _array(values: np.ndarray) -> list | dict[str, list]:
    """A 1-D array as a list, another as {shape, data}; NaN and infinities as None. A float32 value is
    written with the fewest digits that give it back (0.7703418, not 0.7703418135643005: a 30x30x3
    field's JSON 33 kB, not 56)."""
    flat = values.reshape(-1)
    if flat.dtype == np.float32:
        flat = flat.astype(str).astype(np.float64)  # numpy's shortest float32 text, read as a float64
    if flat.dtype.kind == "f" and not np.isfinite(flat).all():
        flat = np.where(np.isfinite(flat), flat.astype(object), None)
    return flat.tolist() if values.ndim == 1 else {"shape": list(values.shape), "data": flat.tolist()}


def message_json(msg: Message) -> dict[str, Any]:
    """The ``fv.<Type>`` JSON object of a message of any type but Image."""
    out: dict[str, Any] = {"timestamp": foxglove_time(msg.stamp_ns), "pub_time": foxglove_time(msg.pub_ns),
                           "seq": msg.seq, "frame_id": msg.frame_id, "node": msg.node}
    out.update({name: cell(value) for name, value in msg.scalar_fields().items()})
    out.update({name: _array(getattr(msg, name)) for name in msg.ARRAYS})
    return out


def calibration_json(info: CameraInfo) -> dict[str, Any]:
    """The foxglove.CameraCalibration object of a CameraInfo (see the module's docstring); ValueError for a
    "pinhole" one whose D is not zeros, which would be a distortion Foxglove's plumb_bob cannot hold as it is,
    and for a K or D that is not finite (JSON has no NaN, and Foxglove's numbers take no null)."""
    for field in ("K", "D"):
        if not np.isfinite(getattr(info, field)).all():
            raise ValueError(f"CameraInfo of {info.frame_id!r}: {field} {getattr(info, field).tolist()} is not finite")
    if info.model == "pinhole" and np.any(info.D):
        raise ValueError(f"CameraInfo of {info.frame_id!r}: model 'pinhole' with D {info.D.tolist()}, not zeros")
    D = info.D.tolist() if info.model == "fisheye" else [0.0] * 5  # plumb_bob's five, all 0: undistorted frames
    return {"timestamp": foxglove_time(info.stamp_ns), "frame_id": info.frame_id, "width": info.width,
            "height": info.height, "distortion_model": DISTORTION_MODELS[info.model], "D": D,
            "K": info.K.reshape(-1).tolist(),
            "R": np.eye(3).reshape(-1).tolist(), "P": np.hstack([info.K, np.zeros((3, 1))]).reshape(-1).tolist()}


def export_schema(type_name: str, images: str) -> dict[str, Any]:
    """The JSON Schema a registered message type is exported with; images: one of IMAGE_KINDS."""
    if type_name == Image.TYPE:
        return RAW_IMAGE_SCHEMA if images == "raw" else COMPRESSED_IMAGE_SCHEMA
    if type_name == CameraInfo.TYPE:
        return CAMERA_CALIBRATION_SCHEMA
    return message_schema(type_name)


def export_json(msg: Message, images: str) -> dict[str, Any]:
    """The JSON object a message is exported as, which `export_schema` describes."""
    if isinstance(msg, Image):
        return image_json(msg, images)
    if isinstance(msg, CameraInfo):
        return calibration_json(msg)
    return message_json(msg)


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
            schema = export_schema(type_name, self.images)
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

    def copy_records(self, bag: BagReader) -> None:
        """The bag's metadata records (the recording's host, command line, totals) and attachments (a
        split bag's sticky ones once)."""
        for name, data in bag.metadata().items():
            self.writer.add_metadata(name, data)
        for att in {(att.name, att.data): att for att in bag.attachments()}.values():
            self.writer.add_attachment(att.log_time_ns, att.log_time_ns, att.name, att.media_type, att.data)

    def write(self, rec: BagMessage, msg: Message) -> None:
        obj = export_json(msg, self.images)
        data = json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()
        self.writer.add_message(self._channel(rec, msg.TYPE), rec.log_time_ns, data, rec.publish_time_ns,
                                rec.sequence)


def export_foxglove(bag: BagReader, topics: list[str] | None, output: Path, images: str = "png") -> int:
    """Write `topics` of `bag` (None: every topic) to the MCAP file `output`, whole or not at all
    (`fv_algos.atomic_file`); returns the number of messages written. images: one of IMAGE_KINDS."""
    from fv_algos.atomic_file import write_atomically
    if images not in IMAGE_KINDS:
        raise ValueError(f"image kind {images!r} is not one of {list(IMAGE_KINDS)}")

    def write(tmp: Path) -> int:
        count = 0
        with open(tmp, "wb") as stream:
            out = _FoxgloveWriter(stream, images)
            out.copy_records(bag)
            for rec, msg in bag.decoded(topics):
                try:
                    out.write(rec, msg)
                except ValueError as exc:  # a message Foxglove's type cannot hold: named by its place in the bag
                    raise ValueError(f"{rec.topic} at log time {rec.log_time_ns} ns: {exc}") from None
                count += 1
            out.writer.finish()
        return count

    return write_atomically(output, write)
