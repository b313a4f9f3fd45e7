"""Slip-detector node: one SlipState per field once the window is full, stamps of the
judged fields, flagged (not NaN) output for a bad window, a clear refusal of a field grid
the model was not trained for; with the trial model, a replayed real grasp judged frame by
frame exactly as offline, and grey images refused by name."""
from __future__ import annotations

import argparse
import contextlib
import time
from pathlib import Path
from typing import Any, Iterator

import numpy as np
import pytest

from msgs import DisplacementField, MarkerArray, SlipState
from nodes.bus import PublisherSocket, TopicReader
from nodes.cli import build_parser
from nodes.process_stop import stop_process
from nodes.shipped_models import model_path, shipped_models
from tests.conftest import dots_image, write_raw_mini
from tests.nodes.conftest import EVERY_FRAME_FPS, REPO, poll_until, wait_status

LAUNCH_RUNS = 3  # live launches of a video, again while one drops a frame (`_launched_running_p_slip`)


def _field(stamp_ns: int, value: float, grid: int = 30) -> DisplacementField:
    field = np.zeros((grid, grid, 3), np.float32)
    field[..., 0] = value
    field[..., 2] = abs(value)
    axis = np.linspace(0.0, 300.0, grid, dtype=np.float32)
    return DisplacementField(stamp_ns=stamp_ns, field=field, grid_x_px=axis, grid_y_px=axis)


def _reference(stamp_ns: int, width: int, markers: int = 40) -> MarkerArray:
    """A tracker's reference of `markers` markers in a `width` px wide 4:3 frame."""
    ref = np.zeros((markers, 2), np.float32)
    return MarkerArray(stamp_ns=stamp_ns, ref_px=ref, cur_px=ref, valid=np.ones(markers, bool),
                       frames_since_seen=np.zeros(markers, np.int32), width=width, height=width * 3 // 4)


def test_unknown_model_name_lists_the_shipped_ones() -> None:
    with pytest.raises(FileNotFoundError, match="gelsight") as error:
        model_path("no_such_model")
    assert "'gelsight'" in str(error.value) and "'gelsight_windows'" in str(error.value)


@pytest.mark.parametrize("command, option", [(["eval"], "--model"), (["eval-trials"], "--model"),
                                             (["bench", "slip"], "--model"), (["bench", "soak"], "--model"),
                                             (["real", "cv"], "--init")])
def test_every_model_option_lists_every_shipped_model(command: list[str], option: str) -> None:
    """`fv eval --help` named `sim, gelsight` only, not the pipeline's default sim_cnn_lstm nor gelsight_online:
    the names come from the weights folder, as the slip detector's."""
    parser = build_parser()
    for name in command:
        parser = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices[name]
    help_text = " ".join(next(a for a in parser._actions if option in a.option_strings).help.split())
    assert {"sim", "sim_cnn_lstm", "gelsight", "gelsight_trial", "gelsight_online"} <= set(shipped_models())
    for name in shipped_models():
        assert f"{name}," in help_text or f"{name})" in help_text, (name, help_text)


def test_a_model_path_under_home_is_found(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`model:=~/mine.pt`: a shell leaves the ~ after := as it is."""
    monkeypatch.setenv("HOME", str(tmp_path))
    (tmp_path / "mine.pt").write_bytes(model_path("gelsight").read_bytes())
    assert model_path("~/mine.pt") == tmp_path / "mine.pt"


def test_gelsight_names_one_model_for_the_node_and_fv_eval() -> None:
    """`model:=gelsight` in a launch file runs the model `fv eval --trials --model gelsight` judges (the
    whole-grasp trial model), not the window ConvLSTM, which is at chance on unseen objects."""
    from nodes.slip_detector import SlipDetectorNode
    assert model_path("gelsight") == model_path("gelsight_trial")
    node = SlipDetectorNode("slip_detector", {"model": "gelsight"})
    try:
        node.setup()
        assert hasattr(node, "judge") and not hasattr(node, "classifier")
    finally:
        node.close()


def test_decisions_per_field_with_window_stamps(bus, spawn) -> None:
    spawn("node", "slip_detector", "-p", "model=gelsight_windows")
    wait_status("slip_detector", timeout_s=30.0)
    pub = PublisherSocket("test_fields")
    assert pub.wait_connected(5.0)
    with TopicReader(["/slip"]) as reader:
        poll_until(lambda: pub.has_subscribers("/field") and pub.has_subscribers("/markers/reference"), 10.0,
                   period_s=0.05)
        pub.publish("/markers/reference", _reference(900_000_000, 320), latched=True)
        time.sleep(0.3)
        stamps = [1_000_000_000 + i * 66_000_000 for i in range(14)]
        states = []  # 14 fields, window 10: 5 decisions
        for i, stamp in enumerate(stamps):
            pub.publish("/field", _field(stamp, 0.3 * i))
            if i >= 9:  # a field queued behind a full window would have it skipped (only the newest is judged)
                states.append(reader.recv(10.0))
                assert states[-1] is not None, f"no decision on field {i}"
        for k, item in enumerate(states):
            s = item.msg
            assert 0.0 <= s.probability <= 1.0 and s.valid and s.model == "gelsight_windows"
            assert list(s.window_stamps_ns) == stamps[k:k + 10] and s.stamp_ns == stamps[k + 9]
        # a non-finite field: the window is flagged invalid, the probability stays a number
        bad = _field(stamps[-1] + 66_000_000, 1.0)
        bad.field[3, 4, 0] = np.nan
        pub.publish("/field", bad)
        flagged = reader.recv(10.0).msg
        assert not flagged.valid and flagged.probability == 0.0
        # a grid the model was not trained for: counted as an error, the node keeps running
        pub.publish("/field", _field(stamps[-1] + 2 * 66_000_000, 1.0, grid=20))
        st = wait_status("slip_detector", lambda st: st.errors >= 1, 10.0)
        assert st.counters["invalid_windows"] >= 1
    pub.close()


def test_window_model_reads_fields_at_its_training_frame_width() -> None:
    """A window model trained on 640 px wide frames (`sim_fast`) gives a 320 px camera's field of half
    the px the probability of the 640 px one: the node rescales by the tracker's frame width."""
    from nodes.slip_detector import SlipDetectorNode
    node = SlipDetectorNode("slip_detector", {"model": "sim_fast"})
    try:
        node.setup()
        assert node.classifier.config.field_width_px == 640
        published: list[float] = []
        node.publish_state = lambda msg, probability, stamps, valid: published.append(probability)
        for i in range(10):  # no frame width yet (the tracker's reference): windows wait
            node.on_field(_field(i, 1.0))
        assert not published and node.counters["no_width"] == 1 and "/markers/reference" in node.message
        for width, scale in ((640, 1.0), (320, 0.5), (1280, 2.0)):
            node.on_window_reference(_reference(1, width))
            node.window.clear()
            for i in range(10):
                node.on_field(_field(10 + i, 0.8 * i * scale))
        assert len(published) == 3 and published[0] > 0.5
        assert published[1] == pytest.approx(published[0], abs=1e-5) == published[2]
    finally:
        node.close()


def test_a_standby_slip_detector_loads_its_window_model_before_it_takes_over() -> None:
    """A spare loaded its model and ran its first pass at takeover: /slip was silent 0.72 to 1.03 s after
    a `kill -9` of the slip detector (30 fps); 0.37 to 0.44 s with the model ready."""
    from nodes.slip_detector import SlipDetectorNode
    SlipDetectorNode.preload({"model": "sim_fast"})
    assert SlipDetectorNode.prepared is not None
    ready = SlipDetectorNode.prepared[1]
    node = SlipDetectorNode("slip_detector", {"model": "sim_fast"})
    try:
        node.setup()
        assert node.classifier is ready and SlipDetectorNode.prepared is None
    finally:
        node.close()
    SlipDetectorNode.preload({"model": "sim_fast", "threads": 1})
    assert SlipDetectorNode.prepared is not None
    ready = SlipDetectorNode.prepared[1]
    other = SlipDetectorNode("slip_detector", {"model": "sim_fast", "threads": 2})  # not what was prepared
    try:
        other.setup()
        assert other.classifier is not ready and SlipDetectorNode.prepared is None
    finally:
        other.close()
    SlipDetectorNode.preload({"model": "gelsight_online"})  # a trial model: nothing to prepare
    assert SlipDetectorNode.prepared is None


@contextlib.contextmanager
def _window_node() -> Iterator[tuple[Any, list[np.ndarray]]]:
    """A set-up `sim_fast` slip detector with its reference (640 px wide frames), and the stamps of every
    window it judges, (10,) int64 ns each, in a list; closed after the block."""
    from nodes.slip_detector import SlipDetectorNode
    node = SlipDetectorNode("slip_detector", {"model": "sim_fast"})
    try:
        node.setup()
        node.on_window_reference(_reference(0, 640))
        windows: list[np.ndarray] = []
        node.publish_state = lambda msg, probability, stamps, valid: windows.append(stamps)
        yield node, windows
    finally:
        node.close()


def test_a_field_out_of_its_windows_stream_starts_a_new_window() -> None:
    """One field stamped an hour before the others was judged with them: ten windows spanning 3600 s with
    their stamps out of order, without a word. A bag looped back in time did the same."""
    with _window_node() as (node, windows):
        hour, frame = 3600 * 10**9, 66_000_000
        start = 2 * hour
        for stamp in [start + k * frame for k in range(12)] + [start - hour]:
            node.on_field(_field(stamp, 0.5))
        assert node.state == "warn" and node.message == ("field stamped -3600.726 s from the last (window_gap_s 1 s): "
                                                         "a new window starts (window_restarts)")
        for stamp in [start + (12 + k) * frame for k in range(10)]:
            node.on_field(_field(stamp, 0.5))
        assert len(windows) == 3 + 1 and node.counters["window_restarts"] == 2  # back an hour, then forward again
        assert all(np.all(np.diff(w) > 0) and w[-1] - w[0] < 10 * frame for w in windows)
        assert node.state == "ok"  # cleared by the next window judged


def test_a_field_stamped_as_the_last_is_dropped_and_a_restart_names_its_gap_and_the_param() -> None:
    """A field stamped the same as the last (the same frame twice: two interpolators on /field) entered the
    window: ten fields of five frames, each twice, judged as ten. It is now dropped, warned and counted
    (duplicate_fields). A field 1 us early was said to be stamped '-0.000 s' from the last, and a camera
    slower than 1 Hz (every field a new window, no decision ever) was not told of window_gap_s."""
    with _window_node() as (node, windows):
        frame = 33_000_000
        for k in range(10):
            node.on_field(_field(10**9 + k * frame, 0.5))
            node.on_field(_field(10**9 + k * frame, 0.5))
        assert len(windows) == 1 and np.all(np.diff(windows[0]) > 0) and node.counters["duplicate_fields"] == 10
        assert "stamped as the last field" in node.message and "(duplicate_fields)" in node.message
        node.on_field(_field(10**9 + 9 * frame - 1000, 0.5))
        assert node.message == ("field stamped -1e-06 s from the last (window_gap_s 1 s): a new window starts "
                                "(window_restarts)")
        node.on_field(_field(10**9 + 9 * frame - 1000 + 10**10, 0.5))
        assert node.message.startswith("field stamped +10 s from the last (window_gap_s 1 s)")


def test_trial_model_refuses_grey_images_by_name() -> None:
    from msgs import Image
    from nodes.slip_detector import SlipDetectorNode
    node = SlipDetectorNode("slip_detector", {"model": "gelsight_trial"})
    try:
        node.setup()
        node.on_reference(MarkerArray(stamp_ns=5, ref_px=np.zeros((40, 2), np.float32)))
        node.on_image(Image(stamp_ns=5, encoding="mono8", data=np.zeros((240, 320), np.uint8)))
        with pytest.raises(ValueError, match="colour camera images .* mono8"):
            node.on_grasp_field(_field(5, 0.0))
    finally:
        node.close()


@pytest.mark.parametrize("grid", [1, 10])
def test_trial_model_refuses_a_field_grid_it_was_not_trained_for(grid: int) -> None:
    """A trial model judged fields of any grid: an interpolator of grid 10 gave it a curl 3.2x the one it
    was trained on, silently, and a 1x1 field raised numpy's message on gradients. As the window model
    does, it names the grids and the interpolator's grid param."""
    from msgs import Image
    from nodes.slip_detector import SlipDetectorNode
    node = SlipDetectorNode("slip_detector", {"model": "gelsight_online"})
    try:
        node.setup()
        node.on_reference(_reference(5, 320))
        node.on_image(Image(stamp_ns=5, encoding="bgr8", data=np.zeros((240, 320, 3), np.uint8)))
        with pytest.raises(ValueError, match=rf"field grid \({grid}, {grid}\) does not match the model's 30x30: "
                                             "set the interpolator's grid param"):
            node.on_grasp_field(_field(5, 0.0, grid=grid))
    finally:
        node.close()


def test_a_camera_faster_than_the_trial_model_is_judged_at_the_model_rate() -> None:
    """Fields at 50 fps for a 25 fps model: every other one is judged; the others repeat the grasp's
    P(slip) so far, with the stamp of the frame it was judged at."""
    from msgs import Image, MarkerArray
    from nodes.slip_detector import SlipDetectorNode
    node = SlipDetectorNode("slip_detector", {"model": "gelsight_online"})
    published: list[SlipState] = []
    try:
        node.setup()
        node.slip_pub.publish = published.append
        node.on_reference(MarkerArray(stamp_ns=0, ref_px=np.zeros((40, 2), np.float32)))
        rng = np.random.default_rng(0)
        for k in range(8):
            stamp = k * 20_000_000
            node.on_image(Image(stamp_ns=stamp, encoding="bgr8", data=rng.integers(0, 255, (240, 320, 3), np.uint8)))
            node.on_grasp_field(_field(stamp, 0.5 * k))
    finally:
        node.close()
    assert len(published) == 8 and node.judge.frames == 4 and node.counters["rate_skipped"] == 4
    assert [int(m.window_stamps_ns[1]) // 10**6 for m in published] == [0, 0, 40, 40, 80, 80, 120, 120]
    assert all(published[k].probability == published[k - 1].probability for k in (1, 3, 5, 7))


def test_a_field_not_after_the_grasps_last_is_left_out_by_a_trial_model() -> None:
    """A field stamped at or before the grasp's last one (the same frame twice, a stream replayed within the
    grasp) was judged as the grasp's next frame, and its interval <= 0 made the frame picker take the camera
    for a faster one: of 12 frames at 25 fps with one sent twice and one 1 us before it, 13 were judged, one
    out of order, and a later one was left unjudged (rate_skipped 1), silently. It is now left out, warned
    and counted (out_of_order_fields), and the grasp goes on judging every frame."""
    from msgs import Image
    from nodes.slip_detector import SlipDetectorNode
    node = SlipDetectorNode("slip_detector", {"model": "gelsight_online"})
    published: list[SlipState] = []
    try:
        node.setup()
        node.slip_pub.publish = published.append
        node.on_reference(_reference(0, 320))
        rng = np.random.default_rng(0)
        stamps = [k * 40_000_000 for k in range(3)] + [80_000_000, 80_000_000 - 1000] + \
            [k * 40_000_000 for k in range(3, 12)]
        for stamp in stamps:
            node.on_image(Image(stamp_ns=stamp, encoding="bgr8", data=rng.integers(0, 255, (240, 320, 3), np.uint8)))
            node.on_grasp_field(_field(stamp, 0.1))
        assert node.counters["out_of_order_fields"] == 2 and node.counters["rate_skipped"] == 0
        assert node.judge.frames == 12 and len(published) == 12 and node.counters["unmatched_fields"] == 0
        node.on_grasp_field(_field(40_000_000, 0.1))
        assert node.state == "warn" and node.message == ("a field stamped -0.4 s from the grasp's last left out "
                                                         "(out_of_order_fields)")
    finally:
        node.close()


@pytest.mark.parametrize("reference_ns, before_grasp", [(40_000_000, 2), (-2_000_000_000, 0)],
                         ids=["reference in the recording", "reference before the recording"])
def test_a_grasp_played_again_is_judged_again_by_a_trial_model(reference_ns: int, before_grasp: int) -> None:
    """`fv bag play --loop` of a recording whose frames carry no frame_index (the simulator's, a live camera's)
    plays its frames again with their stamps, and the tracker keeps its reference: every field of the second
    pass was left out as out of order, and /slip fell silent after the first. The grasp's first field again
    starts the grasp anew, and the second pass is judged as the first: also where the recording began after
    the tracker took its reference, which the replay's tracker resumes and publishes as it was taken, stamped
    before the recording's first frame (the reference frame's own field never comes)."""
    from msgs import Image
    from nodes.slip_detector import SlipDetectorNode
    node = SlipDetectorNode("slip_detector", {"model": "gelsight_online"})
    published: list[SlipState] = []
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 255, (240, 320, 3), np.uint8) for _ in range(12)]
    try:
        node.setup()
        node.slip_pub.publish = published.append
        node.on_reference(_reference(reference_ns, 320))
        for _ in range(2):
            for k, image in enumerate(images):  # frame 0 comes before a reference within the recording
                node.on_image(Image(stamp_ns=k * 40_000_000, encoding="bgr8", data=image))
                node.on_grasp_field(_field(k * 40_000_000, 0.2 * k))
        assert node.counters["out_of_order_fields"] == 0 and node.counters["before_grasp"] == before_grasp
        judged = 12 - before_grasp // 2
        assert node.counters["grasps"] == 2 and len(published) == 2 * judged
    finally:
        node.close()
    first, second = published[:judged], published[judged:]
    assert [m.probability for m in first] == [m.probability for m in second]
    assert [m.window_stamps_ns.tolist() for m in first] == [m.window_stamps_ns.tolist() for m in second]


def test_a_slow_camera_is_warned_of_for_the_rest_of_its_grasp() -> None:
    """The slow-gaps warning was cleared by the next field (33 ms later), so the status, read every
    0.2 s, almost never showed it; it now stands until a grasp without slow gaps."""
    from msgs import Image, MarkerArray
    from nodes.slip_detector import SlipDetectorNode
    node = SlipDetectorNode("slip_detector", {"model": "gelsight_online"})
    rng = np.random.default_rng(0)

    def frames(stamps_ms: list[int]) -> None:
        for stamp in (t * 1_000_000 for t in stamps_ms):
            node.on_image(Image(stamp_ns=stamp, encoding="bgr8", data=rng.integers(0, 255, (240, 320, 3), np.uint8)))
            node.on_grasp_field(_field(stamp, 0.1))

    def grasp(start_ms: int) -> None:
        node.on_reference(MarkerArray(stamp_ns=start_ms * 1_000_000, ref_px=np.zeros((40, 2), np.float32),
                                      width=320, height=240))
    try:
        node.setup()
        node.slip_pub.publish = lambda _msg: None
        grasp(0)
        frames([0, 40, 80, 280, 320, 360])  # 200 ms without a frame for a 25 fps model, then the model's rate
        assert node.state == "warn" and "slow_gaps" in node.message and node.counters["slow_gaps"] == 1
        grasp(10_000)
        frames([10_000, 10_040, 10_080])  # the next grasp, at the model's rate
        assert node.state == "ok" and node.counters["slow_gaps"] == 1
    finally:
        node.close()


def _offline_running_p_slip(video: Path, name: str, start: int) -> list[float]:
    """What `fv eval` computes of `video` with model `name` from reference frame `start`: the
    running P(slip) of the grasp after each judged frame."""
    from fv_algos.contact_motion import contact_series
    from fv_algos.grasp_judge import GraspJudge
    from fv_algos.real_trials import read_frames, video_fields
    from fv_algos.trial_net import field_rows
    fields = video_fields(video, reference_frame=start)
    series = contact_series(read_frames(video), reference_frame=start)
    judge = GraspJudge.from_file(model_path(name))
    return [judge.push(s, r) for s, r in zip(series, field_rows(fields.fields, fields.valid_share, fields.width_px))]


def _launched_running_p_slip(spawn, n: int, *launch_args: str) -> list[SlipState]:
    """The first `n` SlipStates of `fv launch launch/video.yaml ARGS...` at EVERY_FRAME_FPS, without standby
    spares (their imports at start, beside the nodes', could make a loaded 2-core machine drop a frame). A run
    whose pipeline dropped a frame gives fewer, and every later P(slip) of the grasp differs: it is launched
    again, LAUNCH_RUNS runs at most. Beside the `fv eval` tests under `pytest -n 2`, 6 of 7 runs dropped frames
    (8 and 1 of 52 where counted)."""
    for _ in range(LAUNCH_RUNS):
        states: list[SlipState] = []
        with TopicReader(["/slip"]) as reader:
            launch = spawn("launch", str(REPO / "launch" / "video.yaml"), *launch_args, f"fps:={EVERY_FRAME_FPS}",
                           "standby:=false")
            while len(states) < n and (item := reader.recv(60.0 if not states else 10.0)) is not None:
                states.append(item.msg)
        stop_process(launch, timeout_s=30.0)
        if len(states) == n:
            return states
    raise AssertionError(f"{len(states)} of {n} decisions, in each of {LAUNCH_RUNS} runs too few")


def test_video_launch_with_the_trial_model_judges_the_grasp_as_offline(bus_env, spawn, isd_data: Path) -> None:
    """launch/video.yaml replays a real grasp whole: one decision per frame from the model's reference
    frame on (the launch file's default), each the default trial model's (gelsight_online) P(slip)
    of the grasp so far, as `fv eval` computes it from the same video."""
    from fv_algos.trial_net import load_trial_model
    from nodes.launch_file import load_launch
    video = isd_data / "train" / "marker_pen" / "exp_num_2" / "camera_0.avi"  # a slip, 53 frames
    nodes = {n.kind: n for n in load_launch(REPO / "launch" / "video.yaml", {"video": str(video)})}
    name = nodes["slip_detector"].params["model"]
    assert name == "gelsight_online"
    start = load_trial_model(model_path(name)).reference_frame
    trained_from = load_trial_model(model_path("gelsight_trial")).reference_frame
    assert nodes["tracker"].params["reference_frame"] == start == trained_from
    expected = _offline_running_p_slip(video, name, start)
    got = _launched_running_p_slip(spawn, len(expected), f"video:={video}")
    assert len({int(m.window_stamps_ns[0]) for m in got}) == 1 and got[0].window_stamps_ns[0] == got[0].stamp_ns
    np.testing.assert_allclose([m.probability for m in got], expected, atol=1e-4)
    assert got[-1].slip and got[-1].model == name


def test_raw_gelsight_mini_frames_cropped_in_the_camera_are_judged_as_the_recorded_ones(
        bus_env, spawn, isd_data: Path, tmp_path: Path) -> None:
    """A GelSight Mini's frames before its software cuts 1/7 off each border (:func:`write_raw_mini`).
    `crop:=[0.142857]` in the camera gives the recording's P(slip) frame by frame."""
    video = isd_data / "train" / "marker_pen" / "exp_num_2" / "camera_0.avi"
    raw = tmp_path / "raw_mini.avi"
    write_raw_mini(video, raw)
    expected = _offline_running_p_slip(video, "gelsight_online", 1)
    got = _launched_running_p_slip(spawn, len(expected), f"video:={raw}", "crop:=[0.142857]", "size:=[320, 240]")
    np.testing.assert_allclose([m.probability for m in got], expected, atol=1e-4)


def test_both_fingers_voted_on_slip_give_the_trial_score_of_fv_eval(bus_env, spawn, isd_data: Path) -> None:
    """launch/video_pair.yaml replays both cameras of a grasp through two finger pipelines and slip_fusion:
    each finger's /left/slip, /right/slip is that camera's running P(slip), and /slip at the end is the
    trial network on both cameras, what `fv eval --trials` reports of the trial (the bag of peanuts 8: P 0.97 and
    1.00 at the end, their vote 0.988; the mean of the two P would be 0.980)."""
    import torch
    from fv_algos.camera_vote import camera_vote
    from fv_algos.contact_motion import contact_series
    from fv_algos.real_trials import read_frames, video_fields
    from fv_algos.trial_net import camera_descriptors, load_trial_model
    trial = isd_data / "train" / "bag_of_peanuts" / "exp_num_8"
    videos = [trial / "camera_0.avi", trial / "camera_2.avi"]
    model = load_trial_model(model_path("gelsight_online"))
    alone = [_offline_running_p_slip(v, "gelsight_online", 1) for v in videos]
    inputs = [camera_descriptors(contact_series(read_frames(v), reference_frame=1), video_fields(v, reference_frame=1))
              for v in videos]
    with torch.no_grad():
        trial_score = torch.sigmoid(model.net(inputs)).item()
    assert camera_vote([a[-1] for a in alone]) == pytest.approx(trial_score, abs=1e-6)
    n = sum(len(a) for a in alone)
    last: dict[str, SlipState] = {}
    counts = dict.fromkeys(["/left/slip", "/right/slip", "/slip"], 0)
    with TopicReader(list(counts)) as reader:  # (at 25 fps, 2 of 224 states never came with two busy loops)
        spawn("launch", str(REPO / "launch" / "video_pair.yaml"), f"left:={videos[0]}", f"right:={videos[1]}",
              "standby:=false", f"fps:={EVERY_FRAME_FPS}")  # standby as _launched_running_p_slip
        for k in range(2 * n):
            item = reader.recv(90.0 if k == 0 else 10.0)
            assert item is not None, f"{k} of {2 * n} states: {counts} (of {len(alone[0])}, {len(alone[1])}, {n})"
            last[item.topic] = item.msg
            counts[item.topic] += 1
    assert last["/left/slip"].probability == pytest.approx(alone[0][-1], abs=1e-4)
    assert last["/right/slip"].probability == pytest.approx(alone[1][-1], abs=1e-4)
    assert last["/slip"].probability == pytest.approx(trial_score, abs=1e-4) and last["/slip"].slip


def _slip_states(reader: TopicReader, count: int, frames: dict[int, int], first_timeout_s: float = 10.0) -> list:
    """The next ``count`` /slip items of ``reader`` (None for one that did not come within 10 s, the first within
    ``first_timeout_s``); the /camera/image messages between them fill ``frames`` (stamp_ns -> frame_index)."""
    states: list = []
    while len(states) < count:
        item = reader.recv(first_timeout_s if not states else 10.0)
        if item is not None and item.topic == "/camera/image":
            frames[item.msg.stamp_ns] = item.msg.frame_index
        else:
            states.append(item)
    return states


def test_tracker_reset_starts_a_new_grasp(bus_env, spawn, isd_data: Path) -> None:
    """A message on /tracker/reset starts a new grasp at the tracker's next frame. The looped video's next
    pass (53 frames, 2.1 s) starts one too, at its frame 1 (reference_frame): the 40 states after the reset
    reach it when fields in flight at the reset are left out (stamped before the new grasp; as many as the
    interpolator lags behind the tracker). So the grasps are told apart by their reference frame's number,
    and each later start is checked to begin at its reference frame, after the grasp before it."""
    video = isd_data / "train" / "marker_pen" / "exp_num_2" / "camera_0.avi"
    frames: dict[int, int] = {}
    with TopicReader(["/slip", "/camera/image"]) as reader:
        spawn("launch", str(REPO / "launch" / "video.yaml"), f"video:={video}", "loop:=true")
        first = _slip_states(reader, 10, frames, first_timeout_s=60.0)
        assert all(s is not None for s in first)
        start = int(first[0].msg.window_stamps_ns[0])
        pub = PublisherSocket("gripper")
        assert pub.wait_connected(5.0)
        pub.publish("/tracker/reset", SlipState())  # any message: the gripper has just closed
        later = _slip_states(reader, 40, frames)
        pub.close()
    assert all(s is not None for s in later)
    starts = [int(s.msg.window_stamps_ns[0]) for s in later]
    new = [k for k, s in enumerate(starts) if s != start]
    assert new, "no new grasp after /tracker/reset"
    assert frames[starts[new[0]]] > 1, "the first new grasp is the next pass's, not the reset's"
    grasps = [k for k in range(new[0], len(starts)) if k == new[0] or starts[k] != starts[k - 1]]
    for k in grasps:  # each new grasp starts at its reference frame, after the grasp before it
        assert later[k].msg.stamp_ns == starts[k] > (start if k == new[0] else starts[k - 1]), (k, starts)


def _write_stale_start_clip(path: Path, frames: int) -> None:
    """A colour clip (FFV1, 25 fps) of a skin whose frame 0 is stale (the dots 6 px off, as in a camera's
    start-up frame), at rest in frames 1 to 4, then sheared 0.6 px further each frame."""
    import cv2
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 25.0, (320, 240))
    for k in range(frames):
        shift = 6.0 if k == 0 else 0.6 * max(0, k - 4)
        writer.write(cv2.cvtColor(dots_image(shift), cv2.COLOR_GRAY2BGR))
    writer.release()


def test_each_pass_of_a_looped_video_is_judged_as_the_first(bus_env, spawn, tmp_path: Path) -> None:
    """`video.yaml loop:=true` judged every pass as one grasp: the tracker kept the first pass's reference
    and the trial model's grasp ran on across the loop (from the second pass on, P(slip) of a grasp that
    jumped back in time). Each pass is now a new grasp from frame reference_frame of the pass, judged as
    the first: the same states, the same P(slip), stamps and seq running on."""
    frames = 20
    video = tmp_path / "stale_start.avi"
    _write_stale_start_clip(video, frames)
    per_pass = frames - 1  # frame 0 is not tracked (reference_frame 1)
    with TopicReader(["/slip"]) as reader:  # at half the clip's rate: a loaded machine drops no frame
        spawn("launch", str(REPO / "launch" / "video.yaml"), f"video:={video}", "loop:=true",
              f"fps:={EVERY_FRAME_FPS}", "standby:=false")
        states = [reader.recv(60.0 if k == 0 else 10.0) for k in range(2 * per_pass + 1)]
    assert all(s is not None for s in states), f"{sum(s is not None for s in states)} of {2 * per_pass + 1} states"
    states = [s.msg for s in states]
    starts = [int(s.window_stamps_ns[0]) for s in states]
    assert [starts.count(start) for start in dict.fromkeys(starts)] == [per_pass, per_pass, 1], \
        "each pass is a grasp of its own"
    first, second = states[:per_pass], states[per_pass:2 * per_pass]
    assert first[0].stamp_ns == starts[0] and second[0].stamp_ns == starts[per_pass]  # each from its reference
    np.testing.assert_allclose([s.probability for s in second], [s.probability for s in first], atol=1e-6)
    assert all(a.stamp_ns < b.stamp_ns and a.seq + 1 == b.seq for a, b in zip(states, states[1:]))


def test_a_grasp_keeps_its_last_fields_when_the_next_reference_overtakes_them() -> None:
    """The tracker sends a new reference straight to the slip detector and a frame's field through the
    interpolator: after a stall it took a grasp's last frame and the next grasp's reference at once, the
    reference came first, and that last field was left out (before_grasp). It is judged in its grasp now, as
    where it came first; the next grasp starts at its first field, and its reference message sent again (the
    same stamp) starts no other."""
    from msgs import Image
    from nodes.slip_detector import SlipDetectorNode
    rng = np.random.default_rng(3)
    images = {k * 40_000_000: rng.integers(0, 255, (240, 320, 3), np.uint8) for k in range(1, 16)}
    states: dict[str, list[SlipState]] = {}
    for order in ("field first", "reference first"):
        node = SlipDetectorNode("slip_detector", {"model": "gelsight_online"})
        published: list[SlipState] = states.setdefault(order, [])
        try:
            node.setup()
            node.slip_pub.publish = published.append

            def frame(stamp: int) -> None:
                node.on_image(Image(stamp_ns=stamp, encoding="bgr8", data=images[stamp]))
                node.on_grasp_field(_field(stamp, stamp / 4e8))

            node.on_reference(_reference(40_000_000, 320))
            for stamp in list(images)[:8]:
                frame(stamp)
            if order == "reference first":
                node.on_reference(_reference(400_000_000, 320))
                frame(360_000_000)
            else:
                frame(360_000_000)
                node.on_reference(_reference(400_000_000, 320))
            for stamp in list(images)[9:12]:
                frame(stamp)
            node.on_reference(_reference(400_000_000, 320))
            for stamp in list(images)[12:]:
                frame(stamp)
            assert node.counters["before_grasp"] == node.counters["out_of_order_fields"] == 0, order
            assert node.counters["grasps"] == 2, order
        finally:
            node.close()
    field_first, reference_first = states["field first"], states["reference first"]
    assert len(reference_first) == len(field_first) == 15
    assert [s.window_stamps_ns.tolist() for s in reference_first] == [s.window_stamps_ns.tolist() for s in field_first]
    assert [s.probability for s in reference_first] == [s.probability for s in field_first]
    assert reference_first[8].window_stamps_ns.tolist() == [40_000_000, 360_000_000]
    assert [s.window_stamps_ns[0] for s in reference_first[9:]] == [400_000_000] * 6


def test_references_that_come_before_their_first_fields_take_over_in_turn() -> None:
    """Two resets within the interpolator's lag: both references come before the first field of either grasp.
    Each grasp starts at its own first field (the second reference had made the first grasp's fields be judged
    in the grasp before it); a reference stamped before the grasp under way (a recording played again) starts
    its grasp at once."""
    from msgs import Image
    from nodes.slip_detector import SlipDetectorNode
    rng = np.random.default_rng(4)
    node = SlipDetectorNode("slip_detector", {"model": "gelsight_online"})
    published: list[SlipState] = []
    try:
        node.setup()
        node.slip_pub.publish = published.append

        def frame(stamp: int) -> None:
            node.on_image(Image(stamp_ns=stamp, encoding="bgr8", data=rng.integers(0, 255, (240, 320, 3), np.uint8)))
            node.on_grasp_field(_field(stamp, stamp / 4e8))

        node.on_reference(_reference(40_000_000, 320))
        for k in range(1, 6):
            frame(k * 40_000_000)
        node.on_reference(_reference(320_000_000, 320))  # sent second, stamped later: queued in stamp order
        node.on_reference(_reference(240_000_000, 320))
        for k in range(6, 10):
            frame(k * 40_000_000)
        assert [s.window_stamps_ns[0] for s in published[5:]] == [240_000_000] * 2 + [320_000_000] * 2
        node.on_reference(_reference(40_000_000, 320))  # the recording again from its start
        frame(40_000_000)
        assert published[-1].window_stamps_ns.tolist() == [40_000_000, 40_000_000]
        assert node.counters["grasps"] == 4 and node.counters["before_grasp"] == 0
    finally:
        node.close()


def test_a_reference_without_markers_is_ignored() -> None:
    """`fv topic pub /markers/reference MarkerArray '{width: 1}'` (no markers) set a window model's frame
    width: P(slip) read the fields 640-fold; a trial model started a grasp at it."""
    from nodes.slip_detector import SlipDetectorNode
    window = SlipDetectorNode("slip_detector", {"model": "sim_fast"})
    trial = SlipDetectorNode("slip_detector", {"model": "gelsight_online"})
    try:
        window.setup()
        window.on_window_reference(_reference(1, 640))
        window.on_window_reference(_reference(2, 1, markers=0))
        assert window.frame_width_px == 640 and window.counters["empty_references"] == 1
        assert window.state == "warn" and "without markers" in window.message
        trial.setup()
        trial.on_reference(_reference(5, 320))
        trial.on_reference(_reference(9, 320, markers=0))
        assert trial.grasp_start_ns == 5 and trial.counters["grasps"] == 1
    finally:
        window.close()
        trial.close()


def test_a_warning_clears_when_good_windows_come_and_is_logged_once_per_kind(
        caplog: pytest.LogCaptureFixture) -> None:
    """After one window with non-finite values the warning stayed for the node's life; one log line per
    count of non-finite values (51 lines for 40 fields) flooded the log."""
    from nodes.slip_detector import SlipDetectorNode
    node = SlipDetectorNode("slip_detector", {"model": "sim_fast"})
    try:
        node.setup()
        node.publish_state = lambda *args: None
        node.on_window_reference(_reference(1, 640))
        for k in range(1, 15):
            bad = _field(k, 0.1)
            bad.field.reshape(-1)[:k] = np.nan
            node.on_field(bad)
        assert node.state == "warn" and node.message.startswith("window rejected")
        assert sum("window rejected" in r.getMessage() for r in caplog.records) == 1
        for k in range(15, 25):
            node.on_field(_field(k, 0.1))
        assert node.state == "ok" and node.message == ""
    finally:
        node.close()


@pytest.mark.parametrize("params, message", [
    ({"device": "gpu"}, "device 'gpu' is not cpu, cuda"),
    ({"device": "cuda:x"}, "device 'cuda:x'"),
    ({"input_timeout_s": -1.0}, "input_timeout_s -1.0 must be > 0"),
])
def test_bad_params_are_refused_before_start(params: dict, message: str) -> None:
    """`fv launch --check` passed them; the launched node then respawned for good."""
    from nodes.slip_detector import SlipDetectorParams
    with pytest.raises(ValueError, match=message):
        SlipDetectorParams(**params)
    assert SlipDetectorParams(device="cpu").device == "cpu"


def test_a_device_this_torch_cannot_use_is_refused_before_start() -> None:
    """`fv launch device:=cuda` on a CPU-only torch respawned a slip detector that could never start."""
    import torch

    from nodes.slip_detector import SlipDetectorParams
    if torch.cuda.is_available():
        assert SlipDetectorParams(device="cuda").device == "cuda"
        bad = f"cuda:{torch.cuda.device_count()}"
    else:
        bad = "cuda"
    with pytest.raises(ValueError, match=f"device '{bad}' is not usable here"):
        SlipDetectorParams(device=bad)
    if not torch.backends.mps.is_available():
        with pytest.raises(ValueError, match="device 'mps' is not usable here"):
            SlipDetectorParams(device="mps")
