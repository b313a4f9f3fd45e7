"""The wire codec: round trips of every type, zero-copy decoding and the errors for bad input."""
from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest

import msgs
from msgs import (CameraInfo, ContactSummary, DisplacementField, GraspStart, Image, MarkerArray, MessageError,
                  NodeStatus, SlipState, Unanswered)
from msgs.param import ParamSet, ParamState
from msgs.wire import check_message


def _examples() -> list[msgs.Message]:
    rng = np.random.default_rng(0)
    return [
        Image(encoding="bgr8", data=rng.integers(0, 256, (4, 5, 3), dtype=np.uint8), stamp_ns=5, frame_id="cam",
              frame_index=7),
        CameraInfo(width=640, height=480, K=np.array([[300.0, 0, 320], [0, 300, 240], [0, 0, 1]]),
                   D=np.array([0.1, -0.01, 0.001, 0.0]), rms_px=0.3),
        MarkerArray(ref_px=rng.random((6, 2), dtype=np.float32), cur_px=rng.random((6, 2), dtype=np.float32),
                    valid=np.array([True, False] * 3), frames_since_seen=np.arange(6, dtype=np.int32),
                    width=640, height=480),
        DisplacementField(field=rng.random((30, 30, 3), dtype=np.float32), grid_x_px=np.linspace(0, 639, 30),
                          grid_y_px=np.linspace(0, 479, 30), valid=False, n_markers_used=40, n_markers=42,
                          method="rbf"),
        ContactSummary(in_contact=True, area_px2=12.5, area_share=0.1, centre_x_px=3.0, divergence=-0.2),
        SlipState(probability=0.75, slip=True, window_stamps_ns=np.arange(10, dtype=np.int64) * 33_000_000,
                  model="convlstm"),
        GraspStart(stamp_ns=11, frame_id="cam", cause="source restart"),
        NodeStatus(state="warn", message="camera lost", pid=42, publishes=[["/slip", "SlipState"]],
                   counters={"reopen": 2}),
        ParamSet(request_id="r1", values={"threshold": 0.7, "inputs": ["/a", "/b"]}),
        ParamState(params={"threshold": 0.7, "model": "sim"}, live=["threshold"], request_id="r1", accepted=False,
                   error="param 'model' takes effect only at start"),
        Unanswered(stamp_ns=9, frame_id="cam", topic="/camera/image"),
    ]


def _equal(a: msgs.Message, b: msgs.Message) -> bool:
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            if x.dtype != y.dtype or not np.array_equal(x, y):
                return False
        elif x != y:
            return False
    return True


def _frames(msg: msgs.Message) -> list[bytes]:
    return [bytes(f) for f in msgs.encode(msg)]


def _with_header(msg: msgs.Message, **changes: object) -> list[bytes]:
    frames = _frames(msg)
    header = msgpack.unpackb(frames[0])
    header.update(changes)
    return [msgpack.packb(header, use_bin_type=True), *frames[1:]]


def test_every_registered_type_has_an_example() -> None:
    assert sorted(m.TYPE for m in _examples()) == msgs.known_types()


@pytest.mark.parametrize("msg", _examples(), ids=lambda m: m.TYPE)
def test_round_trip_is_exact_and_zero_copy(msg: msgs.Message) -> None:
    frames = _frames(msg)
    out = msgs.decode(frames, "/t")
    assert type(out) is type(msg) and _equal(out, msg)
    for i, name in enumerate(msg.ARRAYS, start=1):
        arr = getattr(out, name)
        assert np.shares_memory(arr, np.frombuffer(frames[i], np.uint8)), f"{name} was copied"
        assert not arr.flags.writeable


def test_big_endian_arrays_decode_to_the_same_values() -> None:
    stamps = (np.arange(10) * 1_000).astype(">i8")
    out = msgs.decode(_frames(SlipState(window_stamps_ns=stamps)), "/slip")
    assert out.window_stamps_ns.dtype == np.dtype(">i8")
    assert np.array_equal(out.window_stamps_ns, np.arange(10) * 1_000)


def test_non_contiguous_array_is_sent_in_c_order() -> None:
    data = np.arange(24, dtype=np.uint8).reshape(4, 6)[:, ::2]
    out = msgs.decode(_frames(Image(data=data)), "/image")
    assert np.array_equal(out.data, data)


def test_wrong_version_names_the_field() -> None:
    with pytest.raises(MessageError) as err:
        msgs.decode(_with_header(SlipState(), version=99), "/slip")
    assert err.value.field == "version" and err.value.topic == "/slip" and err.value.type_name == "SlipState"
    assert "99" in str(err.value)


@pytest.mark.parametrize("cut", ["header", "array_frame", "array_bytes"])
def test_truncated_message(cut: str) -> None:
    frames = _frames(SlipState(window_stamps_ns=np.arange(10)))
    if cut == "header":
        frames = [frames[0][: len(frames[0]) // 2], frames[1]]
    elif cut == "array_frame":
        frames = frames[:1]
    else:
        frames[1] = frames[1][:-3]
    with pytest.raises(MessageError) as err:
        msgs.decode(frames, "/slip")
    assert err.value.field in {"header", "arrays", "window_stamps_ns"}


def test_unknown_field_is_named() -> None:
    frames = _frames(ContactSummary())
    header = msgpack.unpackb(frames[0])
    header["fields"]["pressure"] = 1.0
    with pytest.raises(MessageError, match="pressure") as err:
        msgs.decode([msgpack.packb(header)], "/contact")
    assert err.value.field == "pressure"


def test_an_image_recorded_before_frame_index_existed_decodes_without_one() -> None:
    """`Image.frame_index` was added after Image's wire version 1: a bag recorded before it still plays,
    its frames numbered -1 (not given); any other missing field is still refused."""
    frames = _frames(Image(data=np.zeros((2, 3), np.uint8), frame_index=4))
    header = msgpack.unpackb(frames[0])
    del header["fields"]["frame_index"]
    assert msgs.decode([msgpack.packb(header), *frames[1:]], "/camera/image").frame_index == -1
    del header["fields"]["encoding"]
    with pytest.raises(MessageError, match="missing") as err:
        msgs.decode([msgpack.packb(header), *frames[1:]], "/camera/image")
    assert err.value.field == "encoding"


def test_unknown_bytes_and_text_fields_together_do_not_crash() -> None:
    header = msgpack.unpackb(_frames(ContactSummary())[0])
    header["fields"].update({b"x": 1, "y": 2})
    with pytest.raises(MessageError, match="unknown field"):
        msgs.decode([msgpack.packb(header, use_bin_type=True)], "/contact")


def test_nan_in_a_float_scalar_is_rejected() -> None:
    header = msgpack.unpackb(_frames(SlipState())[0])
    header["fields"]["probability"] = float("nan")
    with pytest.raises(MessageError) as err:
        msgs.decode([msgpack.packb(header), np.zeros(0, np.int64).tobytes()], "/slip")
    assert err.value.field == "probability"


@pytest.mark.parametrize("name, value", [("slip", 1), ("n_markers", True), ("probability", True)])
def test_bool_and_int_are_not_interchangeable(name: str, value: object) -> None:
    msg = DisplacementField() if name == "n_markers" else SlipState()
    header = msgpack.unpackb(_frames(msg)[0])
    header["fields"][name] = value
    with pytest.raises(MessageError) as err:
        msgs.decode([msgpack.packb(header), *_frames(msg)[1:]], "/t")
    assert err.value.field == name


def test_int_is_accepted_for_a_float_field() -> None:
    header = msgpack.unpackb(_frames(SlipState())[0])
    header["fields"]["probability"] = 1
    out = msgs.decode([msgpack.packb(header), np.zeros(0, np.int64).tobytes()], "/slip")
    assert out.probability == 1.0 and isinstance(out.probability, float)


@pytest.mark.parametrize("dtype, shape", [("(2,", [1]), ("<U4", [1]), ("|O", [1]), ("<f4", [0, 2**63]),
                                          ("<f4", [0, 2**40, 2**40]), ("<f4", [-1])])
def test_absurd_array_specs_are_message_errors(dtype: str, shape: list) -> None:
    frames = _frames(SlipState())
    header = msgpack.unpackb(frames[0])
    header["arrays"][0][1:] = [dtype, shape]
    with pytest.raises(MessageError) as err:
        msgs.decode([msgpack.packb(header), b""], "/slip")
    assert err.value.field == "window_stamps_ns"


def test_shape_relation_is_checked_after_decoding() -> None:
    msg = MarkerArray(ref_px=np.zeros((3, 2)), cur_px=np.zeros((2, 2)), valid=np.zeros(3, bool),
                      frames_since_seen=np.zeros(3, np.int32))
    with pytest.raises(MessageError) as err:
        msgs.decode(_frames(msg), "/markers")
    assert err.value.field == "cur_px"


def test_garbage_header_and_unknown_type() -> None:
    with pytest.raises(MessageError, match="msgpack"):
        msgs.decode([b"\xc1\xff\x00garbage"], "/t")
    with pytest.raises(MessageError, match="unknown type"):
        msgs.decode(_with_header(SlipState(), type="Slippage"), "/t")
    with pytest.raises(MessageError, match="no frames"):
        msgs.decode([], "/t")


@pytest.mark.parametrize("cls", [type(m) for m in _examples() if m.ARRAYS and not isinstance(m, Image)],
                         ids=lambda c: c.TYPE)
def test_empty_arrays_round_trip(cls: type) -> None:
    msg = cls(width=1, height=1) if cls in (CameraInfo, MarkerArray) else cls()
    assert _equal(msgs.decode(_frames(msg), "/t"), msg)


@pytest.mark.parametrize("shape", [(0, 0), (0, 320, 3), (240, 0, 3)])
def test_image_without_pixels_is_refused(shape: tuple[int, ...]) -> None:
    """A 0x0 frame went through to the tracker, whose callback raised on it."""
    data = np.zeros(shape, np.uint8)
    with pytest.raises(MessageError, match="holds no pixels") as err:
        msgs.decode(_frames(Image(encoding="mono8" if len(shape) == 2 else "bgr8", data=data)), "/camera/image")
    assert err.value.field == "data"


def test_camera_info_of_an_unknown_model_is_refused() -> None:
    with pytest.raises(MessageError, match="'kannala' is not one of") as err:
        msgs.decode(_frames(CameraInfo(model="kannala", width=640, height=480)), "/camera/info")
    assert err.value.field == "model"


@pytest.mark.parametrize("width, height", [(0, 480), (640, 0), (-640, 480)])
def test_marker_array_without_a_positive_image_size_is_refused(width: int, height: int) -> None:
    """`width: 0` on /markers/reference stopped /slip until /tracker/reset; -640 was taken."""
    with pytest.raises(MessageError, match="not a positive image size") as err:
        msgs.decode(_frames(MarkerArray(width=width, height=height)), "/markers/reference")
    assert err.value.field == "width/height"


@pytest.mark.parametrize("name, value", [("seq", -1), ("seq", 2**63), ("stamp_ns", -5), ("stamp_ns", 2**64 - 1),
                                         ("pub_ns", 2**63)])
def test_header_ints_outside_int64_are_refused_by_name(name: str, value: int) -> None:
    """A seq of 2**63 - 1 let a node's gap count overflow msgpack: its status thread died."""
    frames = _with_header(SlipState(), **{name: value})
    for decode in (lambda: msgs.decode_header(frames[0], "/slip"), lambda: msgs.decode(frames, "/slip")):
        with pytest.raises(MessageError, match=r"not in \[0, 2\*\*63\)") as err:
            decode()
        assert err.value.field == name
    with pytest.raises(ValueError, match=f"{name}: "):
        SlipState(**{name: value}).validate()
    assert msgs.decode(_with_header(SlipState(), **{name: 2**63 - 1}), "/slip")  # the largest int64 is fine


@pytest.mark.parametrize("threshold", [-1.0, 1.5, float("nan")])
def test_slip_state_threshold_outside_0_1_is_refused(threshold: float) -> None:
    with pytest.raises(ValueError, match="threshold: "):
        SlipState(threshold=threshold).validate()
    if threshold == threshold:  # NaN never reaches validate on the wire: the float check refuses it first
        with pytest.raises(MessageError) as err:
            msgs.decode(_frames(SlipState(threshold=threshold)), "/slip")
        assert err.value.field == "threshold"



def test_grasp_start_of_an_unknown_cause_is_refused() -> None:
    with pytest.raises(ValueError, match="cause: 'loop'"):
        GraspStart(cause="loop").validate()
    with pytest.raises(MessageError) as err:
        msgs.decode(_frames(GraspStart(cause="loop")), "/markers/grasp_start")
    assert err.value.field == "cause"

@pytest.mark.parametrize("changes, field", [
    ({"publishes": ["x"]}, "publishes"),
    ({"subscribes": [["/a", "B", "C"]]}, "subscribes"),
    ({"subscribes": [["/a", 3]]}, "subscribes"),
    ({"counters": {"lost": "many"}}, "counters"),
    ({"state": "fine"}, "state"),
    ({"stamp_ns": 4_000_000_000_000_000_000}, "stamp_ns"),
])
def test_a_malformed_node_status_is_refused(changes: dict, field: str) -> None:
    """A latched status with `publishes: [x]` broke `fv topic list` for everyone on the bus."""
    with pytest.raises(MessageError) as err:
        msgs.decode(_frames(NodeStatus(**changes)), "/status")
    assert err.value.field == field


@pytest.mark.parametrize("name, value, text", [("slip", 1, "1 is not a bool"), ("model", b"x", "b'x' is not a str"),
                                               ("probability", "x", "'x' is not a finite float")])
def test_scalar_type_errors_say_what_was_expected(name: str, value: object, text: str) -> None:
    header = msgpack.unpackb(_frames(SlipState())[0])
    header["fields"][name] = value
    with pytest.raises(MessageError, match=text):
        msgs.decode([msgpack.packb(header, use_bin_type=True), np.zeros(0, np.int64).tobytes()], "/slip")


@pytest.mark.parametrize("msg", _examples(), ids=lambda m: m.TYPE)
def test_check_message_passes_every_decodable_message_unchanged(msg: msgs.Message) -> None:
    before = dataclasses.replace(msg)
    check_message(msg)
    assert _equal(msg, before)


@pytest.mark.parametrize("msg, field", [
    (SlipState(probability=1.5), "probability"),
    (SlipState(threshold=float("nan")), "threshold"),
    (SlipState(slip=1), "slip"),
    (DisplacementField(n_markers=True), "n_markers"),
    (SlipState(model=b"x"), "model"),
    (SlipState(frame_id=5), "frame_id"),
    (SlipState(stamp_ns=-5), "stamp_ns"),
    (MarkerArray(width=0, height=480), "width/height"),
    (Image(data=np.zeros((0, 4), np.uint8)), "data"),
    (Image(data=np.zeros((2, 4), np.uint8), frame_index=-2), "frame_index"),
    (NodeStatus(state="fine"), "state"),
    (NodeStatus(counters={"lost": "many"}), "counters"),
], ids=lambda x: x if isinstance(x, str) else type(x).__name__)
def test_check_message_refuses_what_decode_refuses_naming_type_and_field(msg: msgs.Message, field: str) -> None:
    """`advertise(...).publish(SlipState(probability=1.5))` returned normally and every subscriber dropped
    the message as malformed: the sender's check is the decoder's, with the same field named."""
    with pytest.raises(MessageError) as decoded:
        msgs.decode(_frames(msg), "/t")
    assert decoded.value.field == field
    with pytest.raises(ValueError, match=f"^{msg.TYPE}.{field}: ") as checked:
        check_message(msg)
    assert not isinstance(checked.value, MessageError)
    if field != "frame_id":  # decode_header words that one "missing or not str"
        assert str(checked.value) == f"{msg.TYPE}.{field}: {decoded.value.reason}"


def test_check_message_error_reads_as_fv_topic_pub_says_it() -> None:
    with pytest.raises(ValueError, match=r"^SlipState\.probability: 1\.5 is not in \[0, 1\]$"):
        check_message(SlipState(probability=1.5))


def test_check_message_sends_numpy_scalars_as_python_values() -> None:
    """`SlipState(slip=np.bool_(True))` failed in msgpack ("can not serialize 'numpy.bool' object"),
    naming no field."""
    msg = SlipState(slip=np.bool_(True), probability=np.float32(0.75), threshold=np.float64(0.5),
                    stamp_ns=np.int64(5), model=np.str_("m"))
    check_message(msg)
    assert [type(v) for v in (msg.slip, msg.probability, msg.threshold, msg.stamp_ns, msg.model)] == \
        [bool, float, float, int, str]
    out = msgs.decode(_frames(msg), "/slip")
    assert (out.slip, out.probability, out.threshold, out.stamp_ns, out.model) == (True, 0.75, 0.5, 5, "m")
    field = DisplacementField(n_markers=np.uint16(7), valid=np.bool_(False))
    check_message(field)
    assert (type(field.n_markers), type(field.valid)) == (int, bool)
    with pytest.raises(ValueError, match=r"^SlipState\.probability: .* is not a finite float"):
        check_message(SlipState(probability=np.complex64(1j)))
    with pytest.raises(ValueError, match=r"^SlipState\.slip: 1 is not a bool"):
        check_message(SlipState(slip=np.int8(1)))


@pytest.mark.parametrize("encoding, shape", [("mono8", (4, 5, 1)), ("bgr8", (4, 5)), ("rgb8", (4, 5, 4))])
def test_image_data_of_another_shape_than_its_encoding_s_is_refused(encoding: str, shape: tuple[int, ...]) -> None:
    """mono8 data of (H, W, 1) was taken, and the tracker refused every such frame as no image."""
    msg = Image(encoding=encoding, data=np.zeros(shape, np.uint8))
    with pytest.raises(MessageError, match=rf"shape \({shape[0]}, .*does not match encoding '{encoding}'") as err:
        msgs.decode(_frames(msg), "/camera/image")
    assert err.value.field == "data"
