"""`fv bag export --format foxglove`: a recorded bag as an MCAP of JSON messages with JSON Schemas, read back
with the mcap library and checked against the schemas it carries (`conforms`: the part of JSON Schema the
export writes), images decoded back to their recorded pixels."""
from __future__ import annotations

import base64
import json
import math
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
from mcap.reader import make_reader

import msgs
from msgs import CameraInfo, ContactSummary, DisplacementField, Image, MarkerArray, NodeStatus, SlipState
from nodes.bag import foxglove
from nodes.bag.export import export
from nodes.bag.reader import BagError, BagReader
from nodes.cli import main
from tests.nodes.test_bag import T0_NS, sample_messages, write_bag

JSON_TYPES: dict[str, Any] = {
    "object": lambda v: isinstance(v, dict), "array": lambda v: isinstance(v, list),
    "string": lambda v: isinstance(v, str), "boolean": lambda v: isinstance(v, bool), "null": lambda v: v is None,
    "integer": lambda v: isinstance(v, int) and not isinstance(v, bool),
    "number": lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)}


def conforms(value: Any, schema: dict[str, Any], path: str = "$") -> list[str]:
    """Where `value` breaks `schema` (type, one or a list; properties; required; items; minItems; maxItems;
    minimum; maximum; contentEncoding base64): [] when it does not."""
    types = schema.get("type", [])
    types = [types] if isinstance(types, str) else types
    if types and not any(JSON_TYPES[t](value) for t in types):
        return [f"{path}: {value!r:.60} is not {' or '.join(types)}"]
    problems = []
    if isinstance(value, dict):
        problems += [f"{path}.{name}: missing" for name in schema.get("required", []) if name not in value]
        for name, sub in schema.get("properties", {}).items():
            if name in value:
                problems += conforms(value[name], sub, f"{path}.{name}")
    if isinstance(value, list):
        if not schema.get("minItems", 0) <= len(value) <= schema.get("maxItems", math.inf):
            problems.append(f"{path}: {len(value)} items, not [{schema.get('minItems')}, {schema.get('maxItems')}]")
        for i, item in enumerate(value if "items" in schema else []):
            problems += conforms(item, schema["items"], f"{path}[{i}]")
    if JSON_TYPES["number"](value):
        if value < schema.get("minimum", -math.inf) or value > schema.get("maximum", math.inf):
            problems.append(f"{path}: {value} is out of [{schema.get('minimum')}, {schema.get('maximum')}]")
    if schema.get("contentEncoding") == "base64":
        try:
            base64.b64decode(value, validate=True)
        except ValueError:
            problems.append(f"{path}: not base64")
    return problems


FOXGLOVE_TYPES = ("boolean", "string", "number", "integer", "object", "array")


def foxglove_loads(schema: dict[str, Any], path: str = "$") -> list[str]:
    """Why Foxglove's JSON Schema parser (@foxglove/mcap-support parseJsonSchema) would refuse `schema`, []
    when it would not: an object's every property needs one type of FOXGLOVE_TYPES, an object its
    properties, an array items of one of those types but array."""
    if schema.get("type") != "object" or not isinstance(schema.get("properties"), dict):
        return [f"{path}: not an object with properties"]
    problems = []
    for name, sub in schema["properties"].items():
        where = f"{path}.{name}"
        if sub.get("type") not in FOXGLOVE_TYPES:
            problems.append(f"{where}: type {sub.get('type')!r}")
        elif sub["type"] == "object":
            problems += foxglove_loads(sub, where)
        elif sub["type"] == "array":
            items = sub.get("items", {})
            if items.get("type") not in FOXGLOVE_TYPES or items["type"] == "array":
                problems.append(f"{where}: items of type {items.get('type')!r}")
            elif items["type"] == "object":
                problems += foxglove_loads(items, f"{where}[]")
    return problems


def nulls(msg: msgs.Message) -> list[str]:
    """What `conforms` says of each NaN or infinity in `msg`'s float arrays, which JSON holds as null."""
    out = []
    for name in msg.ARRAYS:
        values = getattr(msg, name)
        if values.dtype.kind == "f":
            data = "" if values.ndim == 1 else ".data"
            out += [f"$.{name}{data}[{i}]: None is not number" for i in np.flatnonzero(~np.isfinite(values))]
    return out


def test_the_checkers_find_what_breaks_a_schema() -> None:
    schema = foxglove.message_schema("SlipState")
    good = foxglove.message_json(SlipState(stamp_ns=T0_NS, probability=0.5, window_stamps_ns=np.arange(2)))
    assert conforms(good, schema) == []
    assert conforms({**good, "probability": "0.5"}, schema) == ["$.probability: '0.5' is not number"]
    assert conforms({**good, "timestamp": {"sec": 1, "nsec": 10**9}}, schema)[0].startswith("$.timestamp.nsec")
    assert conforms({**good, "window_stamps_ns": [1.5]}, schema) == ["$.window_stamps_ns[0]: 1.5 is not integer"]
    assert conforms({k: v for k, v in good.items() if k != "slip"}, schema) == ["$.slip: missing"]
    assert conforms({"data": "no base64!"}, foxglove.COMPRESSED_IMAGE_SCHEMA)[-1] == "$.data: not base64"
    assert conforms({"K": [1.0] * 8}, foxglove.CAMERA_CALIBRATION_SCHEMA)[-1] == "$.K: 8 items, not [9, 9]"
    assert foxglove_loads(schema) == []
    nested = {"type": "array", "items": {"type": "array", "items": {"type": "number"}}}
    assert foxglove_loads({**schema, "properties": {"a": nested, "b": {"type": ["number", "null"]},
                                                    "c": {"type": "object"}}}) == [
        "$.a: items of type 'array'", "$.b: type ['number', 'null']", "$.c: not an object with properties"]


def recorded(rng: np.random.Generator) -> list[tuple[str, bool, msgs.Message, int]]:
    """`sample_messages` (a latched CameraInfo; mono8 frames, fields, slip states) with a bgr8 and an rgb8
    camera, markers, a contact, a status with counters and a field holding NaN and infinities."""
    out = sample_messages(6, rng)
    t = out[-1][3]
    bad = rng.normal(0, 1, (4, 5, 3)).astype(np.float32)
    bad[0, 0, 0], bad[1, 2, 1], bad[3, 4, 2] = np.nan, np.inf, -np.inf
    for i, encoding in enumerate(("bgr8", "rgb8")):
        out.append((f"/{encoding}/image", False, Image(stamp_ns=t + i, encoding=encoding, frame_id=encoding,
                                                       data=rng.integers(0, 255, (20, 30, 3), dtype=np.uint8),
                                                       frame_index=i), t + 10 + i))
    out += [("/markers", False, MarkerArray(stamp_ns=t, ref_px=rng.normal(0, 9, (7, 2)).astype(np.float32),
                                            cur_px=rng.normal(0, 9, (7, 2)).astype(np.float32),
                                            valid=rng.random(7) > 0.5, frames_since_seen=np.arange(7),
                                            width=32, height=24), t + 20),
            ("/contact", False, ContactSummary(stamp_ns=t, in_contact=True, area_px2=12.5), t + 30),
            ("/status", True, NodeStatus(stamp_ns=t, counters={"lost": 1, "odd": 2.5},
                                         publishes=[["/slip", "SlipState"]]), t + 40),
            ("/field", False, DisplacementField(stamp_ns=t + 50, field=bad, grid_x_px=np.arange(5.0),
                                                grid_y_px=np.arange(4.0)), t + 50)]
    return out


@pytest.fixture
def bag(tmp_path: Path) -> Path:
    """A bag split in files, each with the launch file attached."""
    write_bag(tmp_path / "run", recorded(np.random.default_rng(3)), chunk_size_b=4_000, max_bag_size_b=6_000)
    assert len(BagReader(tmp_path / "run").files) > 1
    return tmp_path / "run"


def read_export(path: Path) -> list[tuple[Any, Any, Any, dict[str, Any]]]:
    """(schema, channel, message record, parsed JSON) of every message of an exported file, in log-time order."""
    with open(path, "rb") as f:
        return [(s, c, m, json.loads(m.data)) for s, c, m in make_reader(f).iter_messages(log_time_order=True)]


def test_every_topic_is_json_that_its_schema_describes_at_the_recorded_times(bag: Path, tmp_path: Path) -> None:
    count, out = export(bag, None, tmp_path / "fox.mcap")
    source = list(BagReader(bag).decoded())
    exported = read_export(out)
    assert count == len(exported) == len(source) == 25
    schemas = {}
    for (rec, msg), (schema, channel, m, obj) in zip(source, exported):
        assert (channel.topic, m.log_time, m.publish_time, m.sequence) == (
            rec.topic, rec.log_time_ns, rec.publish_time_ns, rec.sequence)
        assert (channel.message_encoding, schema.encoding) == ("json", "jsonschema")
        assert channel.metadata == {"node": rec.node, "latched": "true" if rec.latched else "false"}
        described = json.loads(schema.data)
        assert described["title"] == schema.name
        assert foxglove_loads(described) == []
        assert conforms(obj, described) == ([] if isinstance(msg, Image) else nulls(msg)), rec.topic
        assert set(obj) == set(described["properties"])  # every field, none other
        assert obj["timestamp"] == {"sec": msg.stamp_ns // 10**9, "nsec": msg.stamp_ns % 10**9}
        schemas[rec.topic] = schema.name
    with open(out, "rb") as f:
        reader = make_reader(f)
        assert {m.name: m.metadata for m in reader.iter_metadata()} == {"fv_recording": {"host": "test"}}
        assert [(a.name, a.data) for a in reader.iter_attachments()] == [("launch.yaml", b"nodes: []\n")]
    assert schemas == {"/camera/info": "foxglove.CameraCalibration", "/camera/image": "foxglove.CompressedImage",
                       "/bgr8/image": "foxglove.CompressedImage", "/rgb8/image": "foxglove.CompressedImage",
                       "/field": "fv.DisplacementField", "/slip": "fv.SlipState", "/markers": "fv.MarkerArray",
                       "/contact": "fv.ContactSummary", "/status": "fv.NodeStatus"}


def test_values_come_back_as_recorded(bag: Path, tmp_path: Path) -> None:
    """PNG frames decode to the recorded pixels (an rgb8 frame's channels in their order), slip states keep
    their probability, arrays their shape and every float32 value, NaN and infinities as null, lists and
    maps their JSON text."""
    _, out = export(bag, None, tmp_path / "fox.mcap")
    frames = 0
    for (_rec, msg), (_s, _c, _m, obj) in zip(BagReader(bag).decoded(), read_export(out)):
        if isinstance(msg, Image):
            assert obj["format"] == "png" and obj["frame_id"] == msg.frame_id
            pixels = cv2.imdecode(np.frombuffer(base64.b64decode(obj["data"]), np.uint8), cv2.IMREAD_UNCHANGED)
            assert np.array_equal(pixels[..., ::-1] if msg.encoding == "rgb8" else pixels, msg.data)
            frames += 1
        elif isinstance(msg, SlipState):
            assert obj["probability"] == msg.probability and obj["slip"] is msg.slip
            assert obj["window_stamps_ns"] == msg.window_stamps_ns.tolist()
            assert obj["pub_time"] == {"sec": msg.pub_ns // 10**9, "nsec": msg.pub_ns % 10**9}
        elif isinstance(msg, DisplacementField):
            assert obj["field"]["shape"] == list(msg.field.shape)
            field = np.array([math.nan if v is None else v for v in obj["field"]["data"]], np.float32)
            finite = np.isfinite(msg.field.reshape(-1))
            assert np.array_equal(field[finite], msg.field.reshape(-1)[finite]) and np.isnan(field[~finite]).all()
            assert obj["grid_x_px"] == msg.grid_x_px.tolist()
        elif isinstance(msg, MarkerArray):
            assert np.array_equal(np.reshape(obj["cur_px"]["data"], obj["cur_px"]["shape"]).astype(np.float32),
                                  msg.cur_px)
            assert obj["valid"] == msg.valid.tolist() and obj["width"] == 32
        elif isinstance(msg, NodeStatus):
            assert json.loads(obj["counters"]) == {"lost": 1, "odd": 2.5}
            assert json.loads(obj["publishes"]) == [["/slip", "SlipState"]]
    assert frames == 8


def test_raw_and_jpeg_images(bag: Path, tmp_path: Path) -> None:
    frames = {msg.stamp_ns: msg for _t, msg, _ in BagReader(bag).read() if isinstance(msg, Image)}
    _, raw = export(bag, ["/camera/image", "/rgb8/image"], tmp_path / "raw.mcap", images="raw")
    exported = read_export(raw)
    assert {c.topic for _s, c, _m, _o in exported} == {"/camera/image", "/rgb8/image"} and len(exported) == 7
    for schema, _c, _m, obj in exported:
        img = frames[obj["timestamp"]["sec"] * 10**9 + obj["timestamp"]["nsec"]]
        assert schema.name == "foxglove.RawImage" and conforms(obj, json.loads(schema.data)) == []
        assert (obj["width"], obj["height"], obj["encoding"]) == (img.width, img.height, img.encoding)
        assert obj["step"] == img.data.nbytes // img.height
        assert base64.b64decode(obj["data"]) == img.data.tobytes()
    _, jpeg = export(bag, ["/bgr8/image"], tmp_path / "jpeg.mcap", images="jpeg")
    [(schema, _c, _m, obj)] = read_export(jpeg)
    assert schema.name == "foxglove.CompressedImage" and obj["format"] == "jpeg"
    pixels = cv2.imdecode(np.frombuffer(base64.b64decode(obj["data"]), np.uint8), cv2.IMREAD_UNCHANGED)
    assert pixels.shape == (20, 30, 3)  # lossy: the recorded size, not the recorded pixels


def test_every_message_type_has_a_schema_its_messages_meet() -> None:
    for type_name in msgs.known_types():
        if type_name == Image.TYPE:
            continue
        schema = foxglove.export_schema(type_name, "png")
        assert schema["title"] == ("foxglove.CameraCalibration" if type_name == CameraInfo.TYPE else f"fv.{type_name}")
        assert foxglove_loads(schema) == []
        assert conforms(foxglove.export_json(msgs.message_type(type_name)(), "png"), schema) == []


def test_camera_info_is_a_foxglove_camera_calibration(tmp_path: Path) -> None:
    """A fisheye and an undistorted camera's CameraInfo come out as Foxglove's CameraCalibration, field by
    field: distortion model and coefficients as Foxglove names them, K row-major, R the identity, P = [K | 0]."""
    K = np.array([[310.5, 0.0, 161.25], [0.0, 305.0, 118.75], [0.0, 0.0, 1.0]])
    fisheye = CameraInfo(stamp_ns=T0_NS + 1_500_000_001, frame_id="left_cam", model="fisheye", width=320,
                         height=240, K=K, D=np.array([0.05, -0.01, 0.002, -0.0003]), rms_px=0.4)
    pinhole = CameraInfo(stamp_ns=T0_NS + 7, frame_id="right_cam", model="pinhole", width=160, height=120,
                         K=K / 2 + np.diag([0, 0, 0.5]))
    write_bag(tmp_path / "cams", [("/left/camera/info", True, fisheye, T0_NS), ("/right/camera/info", True, pinhole,
                                                                                   T0_NS + 1)])
    count, out = export(tmp_path / "cams", None, tmp_path / "cams.mcap")
    exported = {c.topic: (s, obj) for s, c, _m, obj in read_export(out)}
    assert count == 2 and set(exported) == {"/left/camera/info", "/right/camera/info"}
    for topic, info, model, D in (("/left/camera/info", fisheye, "kannala_brandt", [0.05, -0.01, 0.002, -0.0003]),
                                  ("/right/camera/info", pinhole, "plumb_bob", [0.0] * 5)):
        schema, obj = exported[topic]
        described = json.loads(schema.data)
        assert schema.name == described["title"] == "foxglove.CameraCalibration"
        assert foxglove_loads(described) == [] and conforms(obj, described) == []
        assert obj == {"timestamp": {"sec": info.stamp_ns // 10**9, "nsec": info.stamp_ns % 10**9},
                       "frame_id": info.frame_id, "width": info.width, "height": info.height,
                       "distortion_model": model, "D": D, "K": [info.K[r, c] for r in range(3) for c in range(3)],
                       "R": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
                       "P": [*info.K[0], 0.0, *info.K[1], 0.0, *info.K[2], 0.0]}, topic
    assert exported["/left/camera/info"][1]["K"][:3] == [310.5, 0.0, 161.25]  # row-major: fx, 0, cx


def test_a_pinhole_camera_info_with_distortion_is_refused(tmp_path: Path) -> None:
    """plumb_bob's coefficients are not our four: a "pinhole" CameraInfo is undistorted, D zeros, and one
    that is not stops the export by name rather than lose its distortion."""
    bent = CameraInfo(stamp_ns=T0_NS, frame_id="cam", model="pinhole", width=32, height=24, D=np.array([0.1, 0, 0, 0]))
    write_bag(tmp_path / "bent", [("/camera/info", True, bent, T0_NS)])
    with pytest.raises(ValueError, match=r"CameraInfo of 'cam': model 'pinhole' with D \[0.1, 0.0, 0.0, 0.0\]"):
        export(tmp_path / "bent", None, tmp_path / "bent.mcap")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bent"]


def test_a_camera_info_that_is_not_finite_is_refused_by_its_place(tmp_path: Path) -> None:
    """JSON has no NaN, and Foxglove's CameraCalibration numbers take no null: a K with NaN stopped the export
    with json's "Out of range float values are not JSON compliant", naming nothing. Now the topic, log time,
    camera and field are named, and nothing is written."""
    nan_k = CameraInfo(stamp_ns=T0_NS, frame_id="cam", model="fisheye", width=32, height=24,
                       K=np.array([[np.nan, 0, 16], [0, 30, 12], [0, 0, 1]]))
    write_bag(tmp_path / "nan", [("/camera/info", True, nan_k, T0_NS + 5)])
    with pytest.raises(ValueError, match=rf"^/camera/info at log time {T0_NS + 5} ns: CameraInfo of 'cam': K "
                                         r"\[\[nan, 0.0, 16.0\], .* is not finite$"):
        export(tmp_path / "nan", None, tmp_path / "nan.mcap")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["nan"]


def test_every_camera_model_has_a_foxglove_distortion_model() -> None:
    from msgs.camera import CAMERA_MODELS
    from nodes.bag.foxglove import DISTORTION_MODELS
    assert set(DISTORTION_MODELS) == set(CAMERA_MODELS)


def test_the_command_picks_topics_and_refuses_bad_input(bag: Path, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "out.mcap"  # .mcap: foxglove without --format
    assert main(["bag", "export", str(bag), "--topic", "/slip", "--topic", "/field", "-o", str(out)]) == 0
    assert capsys.readouterr().out == f"exported 13 messages of /slip, /field to {out}\n"
    assert {c.topic for _s, c, _m, _o in read_export(out)} == {"/slip", "/field"}
    assert main(["bag", "export", str(bag), "-o", str(out)]) == 2  # exists
    assert "pass --force" in capsys.readouterr().err
    assert main(["bag", "export", str(bag), "-o", str(out), "--force"]) == 0
    assert "exported 25 messages of every topic" in capsys.readouterr().out
    assert len(read_export(out)) == 25

    for argv, error in (
            (["--topic", "/nope", "--topic", "/slip", "-o", str(tmp_path / "a.mcap")],
             f"bag {bag}: has no topic '/nope'; topics: ["),
            (["-o", str(tmp_path / "a.csv")], "export to csv takes one --topic, not 0"),
            (["--topic", "/slip", "--topic", "/field", "-o", str(tmp_path / "a.npz")], "takes one --topic, not 2"),
            (["--topic", "/slip", "-o", str(out), "--force", "--format", "foxglove"], None)):
        code = main(["bag", "export", str(bag), *argv])
        err = capsys.readouterr().err
        if error is None:
            assert code == 0
            continue
        assert code == 2 and error in err and err.count("\n") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.mcap", "run"]

    not_a_bag = tmp_path / "notes.mcap"
    not_a_bag.write_text("not a bag\n")
    assert main(["bag", "export", str(not_a_bag), "-o", str(tmp_path / "b.mcap")]) == 2
    assert f"bag {not_a_bag}: not an MCAP file" in capsys.readouterr().err
    with pytest.raises(BagError, match="message encoding 'json', not 'fv-msgpack'"):  # an export is no bag
        export(out, None, tmp_path / "again.mcap")


def test_a_failed_export_leaves_no_file(bag: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The file appears whole or not at all: a frame that cannot be encoded midway leaves nothing, not a
    truncated MCAP that Foxglove would refuse or show in part."""
    encode = foxglove.image_json
    written = []

    def failing(img: Image, kind: str) -> dict[str, Any]:
        if written:
            raise RuntimeError("OpenCV cannot encode")
        written.append(img)
        return encode(img, kind)

    monkeypatch.setattr(foxglove, "image_json", failing)
    with pytest.raises(RuntimeError, match="cannot encode"):
        export(bag, None, tmp_path / "fox.mcap")
    assert written and sorted(p.name for p in tmp_path.iterdir()) == ["run"]
