"""Tracker and interpolator nodes on the simulated camera: markers, fields and contact
flow at camera rate, and a press shows up in the field where the truth says."""
from __future__ import annotations

import time
from contextlib import contextmanager

from pathlib import Path
from typing import TYPE_CHECKING, Iterator

import numpy as np
import pytest

from msgs import MarkerArray
from nodes.bus import TopicReader
from tests.conftest import dots_image
from tests.nodes.conftest import REPO, run_fv

if TYPE_CHECKING:
    from nodes.tracker import TrackerNode


def test_sim_press_reaches_field_and_contact(bus, spawn) -> None:
    scene = REPO / "launch" / "scenes" / "press_shear_slide.yaml"
    for args in (("node", "tracker"), ("node", "interpolator"),
                 ("node", "camera", "-p", "fps=15", "-p", f"scene={scene}")):
        spawn(*args)
    markers, fields, contacts = [], [], []
    with TopicReader(["/markers", "/field", "/contact", "/markers/reference"]) as reader:
        reference = None
        while len(fields) < 45:
            item = reader.recv(20.0)
            assert item is not None, f"pipeline stalled after {len(fields)} fields"
            {"/markers": markers, "/field": fields, "/contact": contacts}.get(item.topic, []).append(item.msg)
            if item.topic == "/markers/reference":
                reference = item.msg
    assert reference is not None and len(reference.ref_px) >= 200  # 16x16 grid, border markers may drop
    m = markers[-1]
    assert m.ref_px.shape == m.cur_px.shape and m.valid.mean() > 0.9
    f = fields[-1]
    assert f.field.shape == (30, 30, 3) and f.valid and np.isfinite(f.field).all()
    assert f.grid_x_px[0] < f.grid_x_px[-1] and f.grid_y_px[0] < f.grid_y_px[-1]
    # 2 N on a 10 mm sphere, then shear: several px of displacement, positive x shear
    peak = max(float(x.field[..., 2].max()) for x in fields)
    assert peak > 2.0, peak
    assert any(c.in_contact for c in contacts)
    stamps = [x.stamp_ns for x in fields]
    assert stamps == sorted(stamps)
    # each field carries the capture stamp of the frame its markers came from
    assert {x.stamp_ns for x in fields[5:]} <= {x.stamp_ns for x in markers}


def _frames_until(camera, reader: TopicReader, image: np.ndarray, done, stamp_ns=time.time_ns) -> object:
    """Publish ``image`` on /camera/image from ``camera`` until ``reader`` gets an item ``done`` accepts."""
    from msgs import Image
    for _ in range(200):
        camera.publish("/camera/image", Image(stamp_ns=stamp_ns(), data=image))
        item = reader.recv(0.05)
        if item is not None and done(item):
            return item
    raise AssertionError("the tracker never answered")


def _markers_after(restarted_ns: int):
    return lambda it: it.topic == "/markers" and it.msg.pub_ns > restarted_ns


def _is_reference(item) -> bool:
    return item.topic == "/markers/reference"


def _took_its_own_reference(m: MarkerArray) -> None:
    """`m`, the first markers of a tracker started on a sheared skin, are on its own reference (the sheared
    frame), and it took one reference and resumed none."""
    from tests.nodes.conftest import wait_status
    assert np.abs(m.cur_px[m.valid] - m.ref_px[m.valid]).max() < 0.3
    status = wait_status("tracker", lambda st: st.counters.get("references") == 1)
    assert status.counters["resumed"] == 0


def test_restarted_tracker_adopts_the_previous_reference(bus, spawn) -> None:
    """A tracker respawned while the skin is sheared must go on measuring against the
    undeformed reference of its previous process, not take the sheared frame as rest. A tracker
    whose frames are stamped before that latched reference (a recording of the session replayed on
    the same bus) takes its own reference instead."""
    from nodes.bus import PublisherSocket
    from tests.nodes.conftest import kill_group, wait_status

    camera = PublisherSocket("fake_camera", bus.address)
    assert camera.wait_connected(2.0)
    with TopicReader(["/markers", "/markers/reference"]) as reader:
        first = spawn("node", "tracker")
        reference = _frames_until(camera, reader, dots_image(0.0), _is_reference).msg
        kill_group(first)
        restarted_ns = time.time_ns()
        second = spawn("node", "tracker")
        item = _frames_until(camera, reader, dots_image(3.0), _markers_after(restarted_ns))
        m = item.msg
        assert np.allclose(m.ref_px, reference.ref_px)
        shift = np.median(m.cur_px[m.valid] - m.ref_px[m.valid], axis=0)
        assert abs(shift[0] - 3.0) < 0.3 and abs(shift[1]) < 0.3, shift
        assert wait_status("tracker", lambda st: st.counters.get("resumed") == 1).counters["references"] == 0
        kill_group(second)
        restarted_ns = time.time_ns()
        spawn("node", "tracker")
        recorded = iter(range(reference.stamp_ns - 10**9, reference.stamp_ns))  # a recording from before it
        item = _frames_until(camera, reader, dots_image(3.0), _markers_after(restarted_ns), lambda: next(recorded))
    _took_its_own_reference(item.msg)  # the replayed frame itself
    camera.close()


def test_tracker_of_a_new_launch_takes_its_own_reference(bus, spawn, monkeypatch) -> None:
    """The bus (a forwarder left running) still holds an earlier session's latched reference: a tracker
    started by a later `fv launch` does not resume it, even with the skin at rest or sheared."""
    from nodes.bus import PublisherSocket
    from nodes.node import LAUNCH_ENV
    from tests.nodes.conftest import kill_group

    camera = PublisherSocket("fake_camera", bus.address)
    assert camera.wait_connected(2.0)
    with TopicReader(["/markers", "/markers/reference"]) as reader:
        earlier = spawn("node", "tracker")
        _frames_until(camera, reader, dots_image(0.0), _is_reference)
        kill_group(earlier)
        launched_ns = time.time_ns()
        monkeypatch.setenv(LAUNCH_ENV, str(launched_ns))  # what `fv launch` gives its nodes
        spawn("node", "tracker")
        m = _frames_until(camera, reader, dots_image(3.0), _markers_after(launched_ns)).msg
    _took_its_own_reference(m)
    camera.close()


def test_a_tracker_respawned_after_a_reset_takes_a_new_reference(bus, spawn) -> None:
    """/tracker/reset came and the tracker was killed (kill -9) before its next frame: the respawned tracker
    resumed its previous process's reference, the grasp before's, and the new grasp was judged against it.
    Its first frame is now the new grasp's reference."""
    import os
    import signal

    from msgs import SlipState
    from nodes.bus import PublisherSocket
    from tests.nodes.conftest import wait_for

    camera = PublisherSocket("fake_camera", bus.address)
    gripper = PublisherSocket("gripper", bus.address)
    assert camera.wait_connected(2.0) and gripper.wait_connected(2.0)
    with TopicReader(["/markers", "/markers/reference", "/markers/grasp_start"]) as reader:
        first = spawn("node", "tracker")
        _frames_until(camera, reader, dots_image(0.0), _is_reference)
        wait_for(lambda: gripper.has_subscribers("/tracker/reset"), 5.0, "the tracker subscribed")
        gripper.publish("/tracker/reset", SlipState(stamp_ns=time.time_ns()))
        while (item := reader.recv(5.0)) is not None and item.topic != "/markers/grasp_start":
            pass
        assert item is not None, "the tracker never took the reset"
        os.killpg(first.pid, signal.SIGKILL)
        first.wait(10.0)
        restarted_ns = time.time_ns()
        spawn("node", "tracker")
        m = _frames_until(camera, reader, dots_image(3.0), _markers_after(restarted_ns)).msg
    _took_its_own_reference(m)
    camera.close()
    gripper.close()



def _numbered_frames(camera, reader: TopicReader) -> tuple:
    """(publish, answered) for a fake video camera (`camera`, a PublisherSocket) and `reader` (of the tracker's
    topics): publish(index) sends frame `index` of a video of the skin at rest on /camera/image and returns
    its stamp; answered(index, since_ns, topics) sends it until a tracker started after `since_ns` answers
    on one of `topics`, and returns that answer."""
    from msgs import Image
    frame = dots_image(0.0)

    def publish(index: int) -> int:
        stamp = time.time_ns()
        camera.publish("/camera/image", Image(stamp_ns=stamp, data=frame, frame_index=index))
        return stamp

    def answered(index: int, since_ns: int, topics: tuple[str, ...]) -> object:
        for _ in range(200):
            publish(index)
            while (item := reader.recv(0.05)) is not None:
                if item.topic in topics and item.msg.pub_ns > since_ns:
                    return item
        raise AssertionError(f"the tracker never answered frame {index} on {topics}")
    return publish, answered


@pytest.mark.parametrize("seen_by", ["tracker", "camera"])
def test_a_tracker_respawned_as_a_looped_video_starts_its_next_pass_takes_that_pass_s_reference(
        bus, spawn, seen_by: str) -> None:
    """A looped video started its next pass (frame_index back to 0) and the tracker was killed (kill -9) before
    that pass's frame `reference_frame`, after seeing its frame 0 (`seen_by` tracker) or before (camera: only
    the camera saw the pass start, which it says latched on camera/pass_start): the respawned tracker resumed
    its previous process's reference, the pass before's, and the new pass was judged as the old grasp going on
    (its grasp start, the reference's stamp, a pass back). It now waits for frame `reference_frame` of the
    pass, as a tracker that saw the pass start would have."""
    import os
    import signal

    from msgs import GraspStart
    from nodes.bus import PublisherSocket
    from tests.nodes.conftest import wait_status

    camera = PublisherSocket("fake_camera", bus.address)
    assert camera.wait_connected(2.0)
    with TopicReader(["/markers", "/markers/reference", "/unanswered"]) as reader:
        publish, answered = _numbered_frames(camera, reader)
        first = spawn("node", "tracker")
        answered(0, 0, ("/unanswered",))  # frame 0 is before reference_frame 1
        first_pass = answered(1, 0, ("/markers/reference",)).msg
        if seen_by == "tracker":
            publish(0)  # the next pass
            wait_status("tracker", lambda st: st.counters.get("source_restarts") == 1)
        else:
            answered(2, 0, ("/markers",))
        os.killpg(first.pid, signal.SIGKILL)
        first.wait(10.0)
        if seen_by == "camera":  # as the camera node says it, before the pass's frame 0
            camera.publish("/camera/pass_start", GraspStart(stamp_ns=time.time_ns(), cause="source restart"),
                           latched=True)
        restarted_ns = time.time_ns()
        second = spawn("node", "tracker")
        item = answered(0, restarted_ns, ("/markers", "/unanswered"))
        assert item.topic == "/unanswered", "frame 0 of the pass was tracked against the pass before's reference"
        item = answered(1, restarted_ns, ("/markers/reference",))
    assert item.msg.stamp_ns > first_pass.stamp_ns
    status = wait_status("tracker", lambda st: st.pid == second.pid and st.counters.get("references") == 1)
    assert status.counters["resumed"] == 0
    camera.close()


def test_a_replay_s_respawned_tracker_resumes_the_reference_of_the_pass_under_way(bus, spawn) -> None:
    """As `replay.yaml` runs the tracker (recorded_reference, the player's latched reference stamped before the
    frames): it took frame 1 of pass 1, the recording's video looped, it took frame 1 of pass 2 and was killed.
    The respawned tracker dropped pass 2's reference (the recording's, delivered after it, took its place and
    was older than the pass start) and took frame 5 as a new one. It now resumes pass 2's."""
    import os
    import signal

    from fv_algos.perception import Perception
    from nodes.bus import PublisherSocket
    from tests.nodes.conftest import wait_status

    frame = dots_image(0.0)
    player = PublisherSocket("bag_play", bus.address)
    assert player.wait_connected(2.0)
    ref = Perception().reset(frame).reference_px.astype(np.float32)
    player.publish("/recorded/markers/reference", MarkerArray(
        stamp_ns=1, ref_px=ref, cur_px=ref, valid=np.ones(len(ref), bool),
        frames_since_seen=np.zeros(len(ref), np.int32), width=frame.shape[1], height=frame.shape[0]), latched=True)
    replay_tracker = ("node", "tracker", "-p", "recorded_reference=recorded/markers/reference")
    with TopicReader(["/markers", "/markers/reference", "/unanswered"]) as reader:
        _, answered = _numbered_frames(player, reader)
        first = spawn(*replay_tracker)
        answered(0, 0, ("/unanswered",))
        answered(1, 0, ("/markers/reference",))
        answered(0, 0, ("/unanswered",))  # pass 2
        pass_2 = answered(1, 0, ("/markers/reference",)).msg
        answered(2, 0, ("/markers",))
        wait_status("tracker", lambda st: st.counters.get("references") == 2)
        os.killpg(first.pid, signal.SIGKILL)
        first.wait(10.0)
        restarted_ns = time.time_ns()
        spawn(*replay_tracker)
        item = answered(5, restarted_ns, ("/markers/reference",))
    assert item.msg.stamp_ns == pass_2.stamp_ns, "pass 2's reference was dropped: frame 5 was taken instead"
    player.close()


def test_reset_grasp_confirms_the_trackers_that_took_it(bus, spawn) -> None:
    """`reset_grasp()` sends one message and returns: a tracker that was not running (respawning) never took
    it, and nothing said so. With `confirm`, it waits for each named tracker's `GraspStart` of this reset and
    raises TimeoutError naming those that did not take it."""
    from nodes.bus import PublisherSocket
    from nodes.client import reset_grasp
    from tests.nodes.conftest import kill_group, wait_for

    tracker = spawn("node", "tracker")
    gripper = PublisherSocket("gripper", bus.address)
    wait_for(lambda: gripper.has_subscribers("/tracker/reset"), 10.0, "the tracker subscribed")
    gripper.close()
    for _ in range(3):  # each call waits for its own reset's word, not an earlier one's (latched)
        reset_grasp(confirm=["/"], timeout_s=5.0)
    for left in ("/left", "left", "left/", "/left/"):  # as a launch file writes it, or a topic
        with pytest.raises(TimeoutError, match=rf"no tracker took the reset within 0.5 s in (/, )?{left} \(on "
                                               r"(/markers/grasp_start, )?/left/markers/grasp_start\)"):
            reset_grasp(confirm=["/", left], timeout_s=0.5)
    kill_group(tracker)
    with pytest.raises(TimeoutError, match=r"in / \(on /markers/grasp_start\)"):
        reset_grasp(confirm=["/"], timeout_s=0.5)

def _skin_at_rest() -> np.ndarray:
    """A simulated camera frame (H, W) uint8 of the skin at rest, its markers undeformed."""
    from fv_algos.sim.scene import scene_from_dict
    from fv_algos.sim.sensor import SimSensor
    sensor = SimSensor(scene_from_dict({"object": {"shape": "sphere"}, "fps": 10,
                                        "steps": [{"action": "hold", "duration_s": 0.2}]}), seed=0)
    return sensor.renderer.render(np.column_stack([sensor.markers_ref_mm, np.zeros(len(sensor.markers_ref_mm))])).image


def _markers(n: int) -> MarkerArray:
    ref = np.random.default_rng(n).random((n, 2)).astype(np.float32) * 300
    return MarkerArray(stamp_ns=1, ref_px=ref, cur_px=ref, valid=np.ones(n, bool),
                       frames_since_seen=np.zeros(n, np.int32), width=320, height=240)


@contextmanager
def _tracker(params: dict) -> Iterator[tuple["TrackerNode", list, list]]:
    """A set-up TrackerNode of `params` (no bus traffic: what it publishes is kept) with the lists its
    references and its marker arrays go to; closed at the end."""
    from nodes.tracker import TrackerNode
    node = TrackerNode("tracker", params)
    references: list = []
    markers: list = []
    try:
        node.setup()
        node.reference_pub.publish = references.append
        node.markers_pub.publish = markers.append
        yield node, references, markers
    finally:
        node.close()


def test_a_dark_first_frame_is_no_reference_and_the_next_is_taken() -> None:
    """A black frame at the start (a camera warming up) raised in the tracker's callback, logged with its
    traceback; it is now warned and counted, and the next frame with markers becomes the reference."""
    from msgs import Image
    rest = _skin_at_rest()
    with _tracker({"reference_frame": 0, "resume": False}) as (node, references, _):
        node.on_image(Image(stamp_ns=1, encoding="mono8", data=np.zeros_like(rest)))
        assert node.counters["reference_retries"] == 1 and node.state == "warn" and not references
        assert "no reference in this frame (reference frame shows 0 consistent marker blobs" in node.message
        node.on_image(Image(stamp_ns=2, encoding="mono8", data=rest))
        assert len(references) == 1 and node.counters["references"] == 1 and node.state == "ok"


def test_a_frame_of_noise_is_no_reference_and_the_next_is_taken() -> None:
    """A frame of pixel noise (a camera's garbage frame) became the reference with 3,494 "markers": 1.5 s to
    build, 0.2 s a frame to track (the tracker fell to 5 frames/s) and every marker array refused by the
    interpolator (too_many_markers) until /tracker/reset. A frame of more than max_markers is no reference."""
    from msgs import Image
    rest = _skin_at_rest()
    noise = np.random.default_rng(0).integers(0, 256, rest.shape, np.uint8)
    with _tracker({"reference_frame": 0, "resume": False}) as (node, references, _):
        started = time.perf_counter()
        node.on_image(Image(stamp_ns=1, encoding="mono8", data=noise))
        noise_s = time.perf_counter() - started
        assert node.counters["reference_retries"] == 1 and node.state == "warn" and not references
        assert "markers, more than max_markers 400: noise, not a marker grid" in node.message, node.message
        node.on_image(Image(stamp_ns=2, encoding="mono8", data=rest))
        assert len(references) == 1 and node.counters["references"] == 1 and node.state == "ok"
    print(f"noise frame refused in {noise_s:.3f} s")
    with pytest.raises(ValueError, match="max_markers 2 must be >= 3"):
        _tracker({"max_markers": 2}).__enter__()


@pytest.mark.parametrize("first_seq, first_index, resumed", [(0, -1, True), (40, -1, True), (120, 0, False),
                                                              (120, 40, True)])
def test_a_replay_is_tracked_against_the_recorded_reference_from_before_its_first_frame(
        first_seq: int, first_index: int, resumed: bool) -> None:
    """A recording holds the reference of the tracker that ran as it began (latched), stamped before its
    first frame: the replay tracks against it from that frame on, as live, also when that frame is a
    respawned camera's first (seq 0). The replay took its own reference there when the first frame's
    seq was at most reference_frame (meant for an earlier session's reference, which recordings no
    longer get): a recording begun as the camera respawned, mid-grasp, had 113 of 179 replayed
    decisions differ from the live ones. A recording that starts at a video's frame 0 (frame_index: a
    looped video's pass begins there too) holds the frame the live tracker took its reference from: the
    replay takes its own there. The reference resumed is published stamped as recorded, at the live frame it
    was taken from (it was stamped at the replay's first frame: the replay's grasp started there, not where
    the live one had)."""
    from msgs import Image
    rest = _skin_at_rest()
    with _tracker({"resume": False, "recorded_reference": "recorded/markers/reference"}) as (node, references, _):
        live = node.perception.reset(rest)  # the live tracker's, stamped 24 s before the recording
        node.on_recorded_reference(MarkerArray(stamp_ns=1, ref_px=live.reference_px.astype(np.float32),
                                               cur_px=live.reference_px.astype(np.float32),
                                               valid=np.ones(len(live.valid), bool),
                                               frames_since_seen=np.zeros(len(live.valid), np.int32),
                                               width=rest.shape[1], height=rest.shape[0]))
        for k in range(3):
            index = first_index + k if first_index >= 0 else -1
            node.on_image(Image(seq=first_seq + k, stamp_ns=24_000_000_000 + k, encoding="mono8", data=rest,
                                frame_index=index))
        assert node.counters["resumed"] == int(resumed) and node.counters["references"] == int(not resumed)
        assert len(references) == 1 and references[0].stamp_ns == (1 if resumed else 24_000_000_001)


def test_a_stream_that_ends_before_the_reference_frame_is_said(caplog: pytest.LogCaptureFixture) -> None:
    """A video of one frame (or reference_frame past its end) ended the launch with status 0 and not one
    decision, without a word."""
    from msgs import Image
    from nodes.tracker import TrackerNode
    node = TrackerNode("tracker", {"resume": False})
    node.setup()
    node.on_image(Image(stamp_ns=1, encoding="mono8", data=np.full((48, 64), 128, np.uint8)))
    node.close()
    assert "1 frame(s) came and none was tracked: no reference was taken (reference_frame 1)" in caplog.text


def test_a_frame_of_another_size_is_dropped_until_a_new_reference() -> None:
    """A camera reopened at another size: its frame was tracked against the reference's marker positions
    into a wrong field taken as valid (8 of 70 markers valid, |d| 35 px with the skin at rest). It is now
    dropped, warned and counted; after /tracker/reset a frame of the new size is the reference."""
    import cv2
    from msgs import Image, SlipState
    rest = _skin_at_rest()
    big = cv2.resize(rest, (rest.shape[1] * 2, rest.shape[0] * 2))
    with _tracker({"reference_frame": 0, "resume": False}) as (node, references, markers):
        node.on_image(Image(stamp_ns=1, encoding="mono8", data=rest))
        node.on_image(Image(stamp_ns=2, encoding="mono8", data=big))
        assert len(markers) == 1 and node.counters["other_size"] == 1 and node.state == "warn"
        h, w = rest.shape[:2]
        assert f"a {2 * w}x{2 * h} frame, but the reference is {w}x{h}" in node.message
        node.on_reset(SlipState())
        node.on_image(Image(stamp_ns=3, encoding="mono8", data=big))
        assert len(references) == 2 and (references[-1].width, references[-1].height) == (2 * w, 2 * h)
        assert len(markers) == 2 and node.state == "ok" and markers[-1].valid.all()


@pytest.mark.parametrize("second_pass_from", [0, 1])
def test_each_pass_of_a_looped_video_is_tracked_from_its_own_reference_frame(second_pass_from: int) -> None:
    """A looped video went on being tracked against its first pass's reference: the next pass's stale
    frame 0 was tracked, and the slip detector judged the passes as one grasp that jumped back in time.
    A frame number that goes back (the source started over) now starts a new grasp, its reference at
    frame reference_frame of the pass, also when the pass's frame 0 never reached the tracker (its queue
    keeps the latest frame): every pass is tracked as the first."""
    from msgs import Image
    video = [dots_image(6.0), dots_image(0.0), dots_image(1.5), dots_image(3.0)]  # frame 0 stale, as in real ones
    with _tracker({"resume": False}) as (node, references, markers):
        frames = [(0, k) for k in range(len(video))] + [(1, k) for k in range(second_pass_from, len(video))]
        for stamp, (_, k) in enumerate(frames, start=1):
            node.on_image(Image(seq=stamp - 1, stamp_ns=stamp, encoding="mono8", data=video[k], frame_index=k))
        assert [r.stamp_ns for r in references] == [2, frames.index((1, 1)) + 1]
        assert node.counters["source_restarts"] == 1 and node.counters["references"] == 2
        assert len(markers) == 6
        for first, second in zip(markers[:3], markers[3:]):
            np.testing.assert_array_equal(first.cur_px, second.cur_px)
            np.testing.assert_array_equal(first.ref_px, second.ref_px)


def test_the_interpolator_refuses_more_markers_than_max_markers() -> None:
    """3000 markers stalled the interpolator 19 s (an N^3 solve per reference); more than max_markers
    are refused with a warning, and the next good MarkerArray clears it."""
    from nodes.interpolator import InterpolatorNode
    node = InterpolatorNode("interpolator", {"max_markers": 50})
    fields = []
    try:
        node.setup()
        node.field_pub.publish = fields.append
        node.contact_pub.publish = lambda msg: None
        node.on_markers(_markers(51))
        assert not fields and node.counters["too_many_markers"] == 1
        assert node.state == "warn" and "51 markers" in node.message and "max_markers 50" in node.message
        node.on_markers(_markers(40))
        assert len(fields) == 1 and node.state == "ok"
    finally:
        node.close()


@pytest.mark.parametrize("node, params, says", [
    ("interpolator", "{kernel: bogus}", "'bogus'"),
    ("interpolator", "{input_timeout_s: -1}", "input_timeout_s -1.0 must be > 0"),
    ("slip_detector", "{device: gpu}", "device 'gpu'"),
    ("slip_detector", "{input_timeout_s: -1}", "input_timeout_s -1.0 must be > 0"),
    ("slip_fusion", "{inputs: [left/slip, /left/slip]}", "two or more different topics"),
    ("camera", "{size: [320.7, 240.2]}", "is not of type list[int]"),  # it said 'not of type list' of a list
])
def test_launch_check_refuses_bad_params_by_file_node_and_value(tmp_path: Path, node: str, params: str,
                                                               says: str) -> None:
    """`fv launch --check` passed these; the launch then respawned the node for good."""
    launch = tmp_path / "bad.yaml"
    launch.write_text(f"nodes:\n  - kind: {node}\n    params: {params}\n")
    result = run_fv("launch", "--check", str(launch))
    assert result.returncode == 2, result.stdout
    assert f"{launch}:3: nodes[0] ({node}).params" in result.stderr and says in result.stderr, result.stderr


def _reference_of(ref_px: np.ndarray, image: np.ndarray, pub_ns: int) -> MarkerArray:
    """The tracker's reference message of markers `ref_px` (N, 2) px in `image`, published at `pub_ns`."""
    ref = np.asarray(ref_px, np.float32)
    return MarkerArray(stamp_ns=1, pub_ns=pub_ns, node="tracker", ref_px=ref, cur_px=ref, valid=np.ones(len(ref), bool),
                       frames_since_seen=np.zeros(len(ref), np.int32), width=image.shape[1], height=image.shape[0])


@pytest.mark.parametrize("bad, says", [("nan", "non-finite"), ("two", "2 markers"), ("none", "0 markers"),
                                       ("twice", "coincide")])
@pytest.mark.parametrize("topic", ["markers/reference", "recorded/markers/reference"])
def test_a_reference_that_cannot_be_tracked_against_is_refused_and_a_new_one_taken(bad: str, says: str,
                                                                                   topic: str) -> None:
    """A previous process's (or a recording's) reference with a NaN marker, fewer than 3 markers or a marker
    listed twice was kept: every frame then raised in the tracker's callback ('reference_px: need >= 3
    finite markers'), and not one frame was tracked for the node's life. It is now refused as it comes,
    named, warned and counted (bad_references), and the tracker takes its own reference."""
    from fv_algos.perception import Perception
    from msgs import Image
    rest = _skin_at_rest()
    with _tracker({"reference_frame": 0, "resume_wait_s": 0.0,
                   "recorded_reference": "recorded/markers/reference"}) as (node, references, markers):
        ref = Perception().reset(rest).reference_px
        ref = {"nan": np.where(np.arange(len(ref))[:, None] == 3, np.nan, ref), "two": ref[:2], "none": ref[:0],
               "twice": np.vstack([ref, ref[:1]])}[bad]
        message = _reference_of(ref, rest, node.started_ns - 1)
        node.on_reference(message) if topic == "markers/reference" else node.on_recorded_reference(message)
        assert node.counters["bad_references"] == 1 and node.state == "warn"
        assert says in node.message and "'tracker'" in node.message, node.message
        for k in range(2):
            node.on_image(Image(stamp_ns=2 + k, encoding="mono8", data=rest))
        assert len(references) == 1 and node.counters["references"] == 1 and node.counters["resumed"] == 0
        assert len(markers) == 2 and markers[-1].valid.all()


def test_a_dark_frame_met_when_resuming_is_retried_as_a_new_reference_is() -> None:
    """Resuming the previous process's reference on a dark frame (markers unknown, none to estimate them
    from) raised in the tracker's callback, logged with its traceback; it is now warned and counted as a
    reference retry (reference_retries), and the next frame resumes it."""
    from fv_algos.perception import Perception
    from msgs import Image
    rest = _skin_at_rest()
    with _tracker({"reference_frame": 0, "resume_wait_s": 0.0}) as (node, references, markers):
        node.launch_ns = 0
        node.on_reference(_reference_of(Perception().reset(rest).reference_px, rest, node.started_ns - 1))
        node.on_image(Image(stamp_ns=2, encoding="mono8", data=np.zeros_like(rest)))
        assert node.counters["reference_retries"] == 1 and node.state == "warn" and not references
        assert "no reference in this frame (reference frame shows 0 consistent marker blobs" in node.message
        node.on_image(Image(stamp_ns=3, encoding="mono8", data=rest))
        assert node.counters["resumed"] == 1 and len(references) == 1 and node.state == "ok"
        assert markers[-1].valid.all()


def test_a_resumed_reference_is_published_as_it_was_taken() -> None:
    """A respawned tracker published the reference it resumed stamped at its own first frame, the skin
    sheared there: the slip detector took it for a new grasp (its grasp start, window_stamps_ns[0] on /slip,
    moved to the respawn) and slip_fusion left the other finger out as on an earlier grasp. It now publishes
    the previous process's reference as that process took it: its stamp, its markers."""
    from fv_algos.perception import Perception
    from msgs import Image
    rest = _skin_at_rest()
    sheared = np.roll(rest, 2, axis=1)
    with _tracker({"reference_frame": 0, "resume_wait_s": 0.0}) as (node, references, markers):
        node.launch_ns = 0
        taken = _reference_of(Perception().reset(rest).reference_px, rest, node.started_ns - 1)
        node.on_reference(taken)
        node.on_image(Image(stamp_ns=5, encoding="mono8", data=sheared))
        assert node.counters["resumed"] == 1 and len(references) == 1 and len(markers) == 1
        again = references[0]
        assert again.stamp_ns == taken.stamp_ns == 1 and (again.width, again.height) == (taken.width, taken.height)
        for name in ("ref_px", "cur_px", "valid", "frames_since_seen"):
            np.testing.assert_array_equal(getattr(again, name), getattr(taken, name))
        assert markers[0].stamp_ns == 5 and np.abs(markers[0].cur_px - markers[0].ref_px)[markers[0].valid].max() > 1


def test_the_previous_process_s_last_grasp_start_keeps_only_an_older_reference_from_being_resumed() -> None:
    """The grasp a previous process of the tracker started in this launch (`markers/grasp_start`) keeps a
    reference that process published before it from being resumed, and not one published after it (the grasp
    it started goes on). After a reset the first frame is the new grasp's reference; after its source started
    over (a looped video's next pass), frame `reference_frame` of the pass, or the first frame when that is
    later in the pass. One of an earlier launch (a forwarder left running keeps the live session's as its
    recording is replayed) or of another node changes nothing: the replay's tracker refused the recording's
    reference for a live tracker's reset."""
    from fv_algos.perception import Perception
    from msgs import GraspStart, Image
    rest = _skin_at_rest()
    sheared = np.roll(rest, 2, axis=1)
    taken = Perception().reset(rest).reference_px
    # the grasp start's pub_ns after the launch, its node and cause; whose reference; the first frame's frame_index;
    # what the tracker does with the reference
    cases = [(3, "tracker", "reset", "previous", -1, "taken"), (1, "tracker", "reset", "previous", -1, "resumed"),
             (3, "left_tracker", "reset", "previous", -1, "resumed"), (-1, "tracker", "reset", "recording", -1, "resumed"),
             (3, "tracker", "source restart", "previous", 0, "waits"),
             (3, "tracker", "source restart", "previous", 1, "taken"),
             (3, "tracker", "source restart", "previous", 4, "taken"),
             (1, "tracker", "source restart", "previous", 0, "resumed")]
    for start_ns, node_name, cause, whose, index, then in cases:
        with _tracker({"resume_wait_s": 0.0, "recorded_reference": "recorded/markers/reference"}) as (
                node, references, markers):
            node.launch_ns = node.started_ns - 10
            node.on_grasp_started(GraspStart(pub_ns=node.launch_ns + start_ns, node=node_name, cause=cause))
            if whose == "previous":
                node.on_reference(_reference_of(taken, rest, node.launch_ns + 2))
            else:  # recorded in a session before this launch
                node.on_recorded_reference(_reference_of(taken, rest, node.launch_ns - 100))
            node.on_image(Image(stamp_ns=5, encoding="mono8", data=sheared, frame_index=index))
            case = (start_ns, node_name, cause, whose, index)
            if then == "waits":  # frame 0 of the pass is before reference_frame 1: frame 1 is the reference
                assert not references and not markers, case
                node.on_image(Image(stamp_ns=6, encoding="mono8", data=sheared, frame_index=1))
            resumed = then == "resumed"
            assert (node.counters["resumed"], node.counters["references"]) == ((1, 0) if resumed else (0, 1)), case
            assert len(references) == 1 and references[0].stamp_ns == (1 if resumed else markers[0].stamp_ns), case
            shift = np.abs(markers[0].cur_px - markers[0].ref_px)[markers[0].valid].max()
            assert (shift > 1) == resumed, (case, shift)



def test_a_pass_the_camera_started_while_no_tracker_process_ran_starts_its_own_grasp() -> None:
    """The previous process took pass N's reference (frame 1) and was killed near the pass's end; the video's
    next pass started before the respawned process's first frame, so no process of the tracker saw it start.
    The respawned tracker resumed pass N's reference and judged pass N+1 as that grasp going on (also after
    a reset the previous process took last: frame 0 of the pass became the reference). The camera says each
    pass's start (`camera/pass_start`): a reference whose frame came before it is not resumed, and the pass's
    frame `reference_frame` is the new one. A pass start before the reference's frame changes nothing."""
    from fv_algos.perception import Perception
    from msgs import GraspStart, Image
    rest = _skin_at_rest()
    taken = Perception().reset(rest).reference_px
    # (the previous process's last reset's pub_ns, or None; the pass start's stamp; resumed)
    for reset_ns, pass_stamp, resumed in [(None, 4, False), (2, 4, False), (None, 0, True), (0, 0, True)]:
        with _tracker({"resume_wait_s": 0.0}) as (node, references, markers):
            node.launch_ns = node.started_ns - 10
            if reset_ns is not None:
                node.on_grasp_started(GraspStart(pub_ns=node.launch_ns + reset_ns, node="tracker", cause="reset"))
            node.on_pass_start(GraspStart(stamp_ns=pass_stamp, pub_ns=node.launch_ns + 3, node="camera",
                                          cause="source restart"))
            node.on_reference(_reference_of(taken, rest, node.launch_ns + 1))  # stamped 1
            node.on_image(Image(stamp_ns=5, encoding="mono8", data=rest, frame_index=0))
            case = (reset_ns, pass_stamp)
            if resumed:
                assert node.counters["resumed"] == 1 and references[0].stamp_ns == 1, case
                continue
            assert not references and not markers, case  # frame 0 is before reference_frame 1
            node.on_image(Image(stamp_ns=6, encoding="mono8", data=rest, frame_index=1))
            assert node.counters["references"] == 1 and references[0].stamp_ns == 6 and len(markers) == 1, case


def test_a_recorded_reference_does_not_take_the_place_of_the_previous_process_s() -> None:
    """A replay (`recorded_reference`) whose tracker started a grasp (a reset, or the recording's next pass),
    took its reference and was killed: the recording's reference, delivered after the previous process's,
    took its place, was found older than that grasp's start, and the respawned tracker took a new reference
    at its first frame (the skin maybe pressed): the grasp's own reference was dropped."""
    from fv_algos.perception import Perception
    from msgs import GraspStart, Image
    rest = _skin_at_rest()
    taken = Perception().reset(rest).reference_px
    for cause in ("source restart", "reset"):
        with _tracker({"resume_wait_s": 0.0, "recorded_reference": "recorded/markers/reference"}) as (
                node, references, markers):
            node.launch_ns = node.started_ns - 10
            node.on_grasp_started(GraspStart(pub_ns=node.launch_ns + 3, node="tracker", cause=cause))
            node.on_reference(_reference_of(taken, rest, node.launch_ns + 4))  # this grasp's, after its start
            node.on_recorded_reference(_reference_of(taken, rest, node.launch_ns - 100))
            node.on_image(Image(stamp_ns=5, encoding="mono8", data=np.roll(rest, 2, axis=1), frame_index=5))
            assert (node.counters["resumed"], node.counters["references"]) == (1, 0), (cause, node.counters)


def test_a_reset_the_previous_process_took_is_followed_without_a_reference_to_resume() -> None:
    """The previous process took a /tracker/reset and was killed before its next frame, with no reference
    to resume (none taken yet, one refused): the respawned tracker's first frame was skipped as before
    `reference_frame`; it is the new grasp's reference, as it would have been for the previous process."""
    from msgs import GraspStart, Image
    rest = _skin_at_rest()
    with _tracker({"resume_wait_s": 0.0}) as (node, references, markers):
        node.launch_ns = node.started_ns - 10
        node.on_grasp_started(GraspStart(pub_ns=node.launch_ns + 3, node="tracker", cause="reset"))
        node.on_image(Image(stamp_ns=5, encoding="mono8", data=rest))
        assert len(references) == 1 and references[0].stamp_ns == 5
        node.on_reset(GraspStart(stamp_ns=6))  # its own grasps are its own: a source restart's at reference_frame
        node.on_image(Image(stamp_ns=7, encoding="mono8", data=rest, frame_index=0))
        node.on_image(Image(stamp_ns=8, encoding="mono8", data=rest, frame_index=9))
        node.on_image(Image(stamp_ns=9, encoding="mono8", data=rest, frame_index=0))  # the source started over
        node.on_image(Image(stamp_ns=10, encoding="mono8", data=rest, frame_index=1))
        assert [r.stamp_ns for r in references] == [5, 7, 10]

@pytest.mark.parametrize("ref, says", [
    (np.array([[np.nan, 0.0], [10.0, 0.0], [0.0, 10.0]]), "non-finite"),
    (np.zeros((0, 2)), "no markers"),
    (np.zeros((4, 2)), "coincide"),
    (np.array([[0.0, 0.0], [1e30, 0.0], [0.0, 10.0]]), "beyond"),
])
def test_the_interpolator_refuses_a_reference_it_cannot_interpolate_from(ref: np.ndarray, says: str) -> None:
    """A MarkerArray whose reference holds a NaN, no marker, a marker listed twice or one beyond 1e6 px (from
    the bus: `fv topic pub`, a bad bag) raised in the interpolator's callback, logged with a traceback as an
    error of the node. It is now refused, named and counted (bad_references), as too many markers are, and
    the next good MarkerArray clears the warning."""
    from nodes.interpolator import InterpolatorNode
    node = InterpolatorNode("interpolator", {})
    fields = []
    try:
        node.setup()
        node.field_pub.publish = fields.append
        node.contact_pub.publish = lambda msg: None
        bad = ref.astype(np.float32)
        node.on_markers(MarkerArray(stamp_ns=1, node="someone", ref_px=bad, cur_px=bad, valid=np.ones(len(bad), bool),
                                    frames_since_seen=np.zeros(len(bad), np.int32), width=320, height=240))
        assert not fields and node.counters["bad_references"] == 1 and node.state == "warn"
        assert says in node.message and "'someone'" in node.message, node.message
        node.on_markers(_markers(40))
        assert len(fields) == 1 and fields[0].valid and node.state == "ok"
    finally:
        node.close()


def _colour_dots(shift_px: float) -> np.ndarray:
    """(240, 320, 3) uint8 BGR: `dots_image` on a skin whose red rises and blue falls from left to right."""
    grey = dots_image(shift_px).astype(np.float32) / 200.0
    x = np.linspace(0.0, 1.0, grey.shape[1])[None, :]
    bgr = np.dstack([220 * grey * (1 - 0.8 * x), 120 * grey, 220 * grey * (0.2 + 0.8 * x)])
    return np.clip(bgr, 0, 255).astype(np.uint8)


def test_rgb8_frames_are_tracked_as_the_same_frames_in_bgr8() -> None:
    """The tracker read an rgb8 frame's channels as BGR: its luma weighed red as blue, and a skin shaded
    from blue to red gave another reference (markers up to 168 px apart by index) than the same frames
    in bgr8. The slip detector converted them; the tracker now does too."""
    from msgs import Image
    tracked = {}
    for encoding in ("bgr8", "rgb8"):
        with _tracker({"reference_frame": 0, "resume": False}) as (node, references, markers):
            for k, shift in enumerate([0.0, 1.3]):
                frame = _colour_dots(shift)
                data = frame if encoding == "bgr8" else np.ascontiguousarray(frame[..., ::-1])
                node.on_image(Image(stamp_ns=k + 1, encoding=encoding, data=data))
            tracked[encoding] = (references[0].ref_px, markers[-1].cur_px, markers[-1].valid)
    for bgr, rgb in zip(tracked["bgr8"], tracked["rgb8"]):
        np.testing.assert_array_equal(bgr, rgb)
