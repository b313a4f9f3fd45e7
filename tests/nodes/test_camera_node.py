"""Camera node: publishes at the configured rate from each source, reports a vanished
video instead of dying, and fails clearly on a source it cannot open."""
from __future__ import annotations

import re
import shutil
import subprocess
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from nodes.bus import TopicReader
from nodes.exit_codes import TEMPFAIL
from tests.nodes.conftest import run_fv, wait_status


def _rate(topic: str, seconds: float, skip_s: float = 1.0) -> tuple[float, object]:
    """Messages per second on `topic` over `seconds` after the first message + skip_s."""
    with TopicReader([topic]) as reader:
        first = reader.recv(15.0)
        assert first is not None, f"nothing on {topic}"
        deadline = time.monotonic() + skip_s
        while time.monotonic() < deadline:
            reader.recv(0.1)
        count, t0, last = 0, time.monotonic(), first
        while time.monotonic() - t0 < seconds:
            item = reader.recv(0.2)
            if item is not None:
                count, last = count + 1, item
        return count / seconds, last.msg


def _write_video(path: Path, frames: int = 20) -> None:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (160, 120))
    for i in range(frames):
        image = np.full((120, 160, 3), 200, np.uint8)
        cv2.circle(image, (20 + 5 * i, 60), 6, (20, 20, 20), -1)
        writer.write(image)
    writer.release()


def test_video_source_rate_and_info(bus, spawn, tmp_path: Path) -> None:
    video = tmp_path / "clip.avi"
    _write_video(video)
    spawn("node", "camera", "-p", "source=video", "-p", f"path={video}", "-p", "fps=20")
    rate, msg = _rate("/camera/image", 2.0)
    assert 16.0 <= rate <= 22.0, rate
    assert msg.data.shape == (120, 160) and msg.encoding == "mono8"
    assert abs(msg.stamp_ns - time.time_ns()) < 2e9  # capture stamps are wall-clock times


def test_a_video_played_once_stops_its_camera_after_its_end(bus, spawn, tmp_path: Path) -> None:
    """A launch replaying a video (video.yaml) ran on after its end until Ctrl-C; the camera now exits
    with status 0 `exit_after_end_s` after the last frame, which ends a launch where it is required."""
    video = tmp_path / "clip.avi"
    _write_video(video, frames=10)
    with TopicReader(["/camera/image"]) as reader:
        camera = spawn("node", "camera", "-p", "source=video", "-p", f"path={video}", "-p", "fps=20",
                       "-p", "loop=false", "-p", "exit_after_end_s=0.5")
        frames = [item for item in iter(lambda: reader.recv(3.0), None)]
    assert camera.wait(5.0) == 0 and len(frames) == 10
    looping = spawn("node", "camera", "-p", "source=video", "-p", f"path={video}", "-p", "fps=20",
                    "-p", "exit_after_end_s=0.5")  # loop (the default): the video never ends
    with pytest.raises(subprocess.TimeoutExpired):
        looping.wait(2.0)


def test_a_looped_video_numbers_its_frames_from_0_at_each_pass(bus, spawn, tmp_path: Path) -> None:
    """A looped video's frames carried nothing that told a pass from the next (the tracker kept the first
    pass's reference for good): each frame now carries its number in the file, from 0 again at each pass,
    the held first frame too; seq and stamps run on across the loop. Each pass's start is also said on
    camera/pass_start, before its frame 0 and stamped as it (a tracker respawned as a pass began resumed the
    pass before's reference)."""
    video = tmp_path / "clip.avi"
    _write_video(video, frames=6)
    with TopicReader(["/camera/image", "/camera/pass_start"]) as reader:
        spawn("node", "camera", "-p", "source=video", "-p", f"path={video}", "-p", "fps=50")
        items = [reader.recv(15.0 if k == 0 else 2.0) for k in range(18)]
    assert all(item is not None for item in items)
    images = [item.msg for item in items if item.topic == "/camera/image"]
    assert [m.frame_index for m in images] == [0, 1, 2, 3, 4, 5] * 2 + [0, 1, 2]
    assert [m.seq for m in images] == list(range(15))
    assert all(a.stamp_ns < b.stamp_ns for a, b in zip(images, images[1:]))
    passes = [(k, item.msg) for k, item in enumerate(items) if item.topic == "/camera/pass_start"]
    assert [k for k, _ in passes] == [0, 7, 14]  # each right before its pass's frame 0
    assert all(m.cause == "source restart" and m.stamp_ns == items[k + 1].msg.stamp_ns for k, m in passes)


def test_a_looped_folder_numbers_its_images_by_their_place(tmp_path: Path) -> None:
    from nodes.camera_sources import FolderSource
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), np.full((4, 5), 50 * i, np.uint8))
    source = FolderSource(str(tmp_path), loop=True)
    source.open()
    assert [source.read().index for _ in range(7)] == [0, 1, 2, 0, 1, 2, 0]


def test_folder_source_bgr(bus, spawn, tmp_path: Path) -> None:
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), np.full((40, 50, 3), 50 * i, np.uint8))
    spawn("node", "camera", "-p", "source=folder", "-p", f"path={tmp_path}", "-p", "fps=15", "-p", "encoding=bgr8")
    rate, msg = _rate("/camera/image", 2.0)
    assert 12.0 <= rate <= 17.0, rate
    assert msg.data.shape == (40, 50, 3) and msg.encoding == "bgr8"


def test_folder_frames_of_any_depth_and_alpha_come_as_uint8_at_one_gain(tmp_path: Path) -> None:
    """An RGBA PNG broke `encoding: bgr8` (a 4-channel frame, dropped by every subscriber); 16-bit images
    were each scaled by their own maximum: 12-bit data with one hot pixel came out half as bright."""
    from nodes.camera_sources import FolderSource
    scene = np.full((24, 32), 3000, np.uint16)  # 12-bit data stored in 16 bits
    scene[8:12, 8:12] = 300  # a marker
    hot = scene.copy()
    hot[0, 0] = 4095
    for name, image in (("a.png", scene), ("b.png", hot)):
        cv2.imwrite(str(tmp_path / name), image)
    source = FolderSource(str(tmp_path), loop=False)
    source.open()
    first, second = source.read().image, source.read().image
    assert first.dtype == np.uint8 and first[20, 20] == second[20, 20] == round(3000 * 255 / 4095)
    cv2.imwrite(str(tmp_path / "0_dark.png"), np.full((24, 32), 40, np.uint16))  # a camera starting up
    source = FolderSource(str(tmp_path), loop=False)
    source.open()
    source.read()  # the dark frame's white level, 255, would clip every 12-bit frame after it
    assert source.read().image[20, 20] == round(3000 * 255 / 4095)
    rgba = tmp_path / "rgba"
    rgba.mkdir()
    cv2.imwrite(str(rgba / "c.png"), np.full((24, 32, 4), 90, np.uint8))
    source = FolderSource(str(rgba), loop=False)
    source.open()
    assert source.read().image.shape == (24, 32, 3)


def test_sim_source_publishes_frames_and_latched_info(bus, spawn) -> None:
    spawn("node", "camera", "-p", "fps=20")
    rate, msg = _rate("/camera/image", 2.0)
    assert rate >= 14.0, rate  # the simulator renders a frame in ~10 ms; 20 Hz leaves room on a loaded CI core
    assert msg.data.shape == (480, 640)
    with TopicReader(["/camera/info"]) as late_joiner:  # latched: arrives although published long ago
        info = late_joiner.recv(3.0)
    assert info is not None and info.msg.K.shape == (3, 3) and info.msg.width == 640


def test_frames_are_cropped_and_resized_and_the_info_follows(bus, spawn) -> None:
    """The simulated 640x480 camera with 1/10 off each border, resized to 320x240: the frames come
    that size, and /camera/info gives the matrix of those frames (its focal lengths scaled by
    320 / 512)."""
    from fv_algos.frame_crop import FrameCrop
    from nodes.sim_source import SimSource
    spawn("node", "camera", "-p", "fps=20", "-p", "crop=[0.1]", "-p", "size=[320, 240]")
    _, msg = _rate("/camera/image", 1.0)
    assert msg.data.shape == (240, 320)
    with TopicReader(["/camera/info"]) as late_joiner:
        info = late_joiner.recv(3.0).msg
    cam = SimSource("", 0, 20.0).camera
    K, width, height = FrameCrop((0.1,) * 4, (320, 240)).camera_matrix(np.asarray(cam.K), cam.width, cam.height)
    assert (info.width, info.height) == (width, height) == (320, 240)
    np.testing.assert_allclose(info.K, K)
    assert info.K[0, 0] == pytest.approx(cam.K[0, 0] * 320 / 512)


def test_undistorted_frames_come_with_their_pinhole_matrix_and_no_distortion(bus, spawn) -> None:
    from nodes.sim_source import SimSource
    spawn("node", "camera", "-p", "fps=20", "-p", "undistort=true")
    with TopicReader(["/camera/info"]) as late_joiner:
        info = late_joiner.recv(15.0).msg
    cam = SimSource("", 0, 20.0).camera
    np.testing.assert_allclose(info.K, cam.undistorted_camera_matrix())
    assert not info.D.any() and (info.width, info.height) == (cam.width, cam.height)
    assert info.model == "pinhole"  # it said fisheye: with D = 0 that is equidistant, 128 px off at a corner


def test_a_calibration_at_another_resolution_is_scaled_to_the_frames() -> None:
    """Pixels of the 640x480 calibration map to the 160x120 frames' pixel centres: (u + 0.5) / 4 - 0.5."""
    from fv_algos.fisheye import FisheyeCamera
    camera = FisheyeCamera(K=np.array([[305.0, 0.0, 326.0], [0.0, 298.0, 235.0], [0.0, 0.0, 1.0]]),
                           D=np.array([-0.03, 0.01, -0.002, 0.0]), width=640, height=480, rms_px=0.2)
    assert camera.for_size(640, 480) is camera
    small = camera.for_size(160, 120)
    assert small.size == (160, 120) and small.rms_px == pytest.approx(0.05)
    points = np.random.default_rng(0).uniform([-10.0, -8.0, 5.0], [10.0, 8.0, 20.0], (50, 3))
    np.testing.assert_allclose(small.project(points), (camera.project(points) + 0.5) / 4 - 0.5, atol=1e-9)
    with pytest.raises(ValueError, match=r"calibration for 640x480 frames does not fit the source's 160x90 frames"):
        camera.for_size(160, 90)


def test_undistorted_video_at_half_the_calibrations_resolution_comes_whole(bus, spawn, tmp_path: Path) -> None:
    """Before, a 640x480 calibration on 160x120 video gave 480x640 frames, mostly black, and
    /camera/info said 640x480."""
    from fv_algos.fisheye import FisheyeCamera
    video, calibration = tmp_path / "clip.avi", tmp_path / "calibration.json"
    _write_video(video)
    camera = FisheyeCamera.default()
    camera.save(calibration)
    spawn("node", "camera", "-p", "source=video", "-p", f"path={video}", "-p", "fps=20",
          "-p", f"calibration={calibration}", "-p", "undistort=true")
    _, msg = _rate("/camera/image", 0.5, skip_s=0.0)
    with TopicReader(["/camera/info"]) as late_joiner:
        info = late_joiner.recv(5.0).msg
    assert msg.data.shape == (120, 160)
    assert msg.data[10:-10, 10:-10].min() > 0  # the undistorted frame fills the view (no black border)
    assert (info.width, info.height) == (160, 120)
    np.testing.assert_allclose(info.K, camera.for_size(160, 120).undistorted_camera_matrix())


def test_a_calibration_of_another_aspect_ratio_is_refused_at_start(bus, tmp_path: Path) -> None:
    from fv_algos.fisheye import FisheyeCamera
    video, calibration = tmp_path / "clip.avi", tmp_path / "wide.json"
    _write_video(video)
    default = FisheyeCamera.default()
    FisheyeCamera(K=default.K, D=default.D, width=640, height=360).save(calibration)
    result = run_fv("node", "camera", "-p", "source=video", "-p", f"path={video}",
                    "-p", f"calibration={calibration}", timeout_s=20)
    assert result.returncode != 0
    assert "640x360" in result.stderr and "160x120" in result.stderr and "Traceback" not in result.stderr


def test_a_crop_that_leaves_nothing_is_refused_at_start(bus, tmp_path: Path) -> None:
    """It passed the params' check (every share < 0.5), then raised on every frame, published none and the
    launch ended with status 0."""
    video = tmp_path / "clip.avi"
    _write_video(video)
    result = run_fv("node", "camera", "-p", "source=video", "-p", f"path={video}", "-p", "crop=[0.499]",
                    timeout_s=20)
    assert result.returncode == 2
    assert "leaves nothing of a 160x120 frame" in result.stderr and "Traceback" not in result.stderr


def test_a_video_without_frames_is_refused_at_start(bus, tmp_path: Path) -> None:
    """It started, said "end of input" and ended the launch with status 0, having published nothing."""
    video = tmp_path / "empty.avi"
    cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 25, (160, 120)).release()
    result = run_fv("node", "camera", "-p", "source=video", "-p", f"path={video}", timeout_s=20)
    assert result.returncode == 2
    assert f"video {video}: no frame, and playing it needs one" in result.stderr


def test_the_end_of_a_whole_video_is_information_and_that_of_a_cut_one_a_warning(bus, tmp_path: Path) -> None:
    """Every video played to its end warned "end of input", the GelSight Mini example as a file cut short;
    a warning now says that decoding stopped before the frames the file lists."""
    whole, cut = tmp_path / "whole.avi", tmp_path / "cut.avi"
    _write_video(whole, frames=20)
    data = whole.read_bytes()
    cut.write_bytes(data[:len(data) // 2])  # its header still lists 20 frames
    ends = {}
    for video in (whole, cut):
        result = run_fv("node", "camera", "-p", "source=video", "-p", f"path={video}", "-p", "loop=false",
                        "-p", "fps=100", "-p", "exit_after_end_s=0", timeout_s=20)
        assert result.returncode == 0, result.stderr
        ends[video] = [line for line in result.stderr.splitlines() if "end of input" in line]
    assert ends[whole] == [f"[camera] INFO: video {whole}: end of input after 20 frames"]
    assert len(ends[cut]) == 1 and ends[cut][0].startswith(f"[camera] WARNING: video {cut}: end of input after ")
    played = int(ends[cut][0].split("after ")[1].split()[0])
    assert 0 < played < 20 and ends[cut][0].endswith(f"frames, {20 - played} fewer than the file lists "
                                                      "(cut short or damaged?)")


def test_a_video_is_cropped_frame_by_frame(bus, spawn, tmp_path: Path) -> None:
    from fv_algos.frame_crop import FrameCrop
    video = tmp_path / "clip.avi"
    _write_video(video, frames=5)
    spawn("node", "camera", "-p", "source=video", "-p", f"path={video}", "-p", "fps=25", "-p", "encoding=bgr8",
          "-p", "crop=[0.25, 0.25, 0.125, 0.125]")
    with TopicReader(["/camera/image"]) as reader:
        got = [reader.recv(15.0 if k == 0 else 5.0) for k in range(12)]
    cap = cv2.VideoCapture(str(video))
    decoded = [cap.read()[1] for _ in range(5)]
    assert all(g is not None for g in got)
    for g in got:  # the video loops: frame seq % 5
        frame = decoded[g.msg.seq % 5]
        assert g.msg.data.shape == (60, 120, 3)
        np.testing.assert_array_equal(g.msg.data, FrameCrop((0.25, 0.25, 0.125, 0.125)).apply(frame))
        np.testing.assert_array_equal(g.msg.data, frame[30:90, 20:140])


def test_video_that_disappears_is_reported_not_fatal(bus, spawn, tmp_path: Path) -> None:
    video = tmp_path / "clip.avi"
    _write_video(video, frames=10)
    proc = spawn("node", "camera", "-p", "source=video", "-p", f"path={video}", "-p", "fps=25",
                 "-p", "reopen_backoff_s=0.2")
    wait_status("camera", lambda st: st.counters.get("frames", 0) > 0, 10.0)
    hidden = tmp_path / "moved.avi"
    shutil.move(video, hidden)  # unplugged: the loop's reopen fails
    st = wait_status("camera", lambda st: st.state == "warn", 8.0)
    assert "clip.avi" in st.message and st.counters["lost"] >= 1
    assert proc.poll() is None
    shutil.move(hidden, video)  # plugged back
    st = wait_status("camera", lambda st: st.state == "ok" and st.counters.get("reopened", 0) >= 1, 10.0)
    assert proc.poll() is None


def test_missing_source_fails_at_start_with_clear_error(bus, tmp_path: Path) -> None:
    result = run_fv("node", "camera", "-p", "source=video", "-p", f"path={tmp_path / 'none.avi'}", timeout_s=20)
    assert result.returncode != 0
    assert "none.avi" in result.stderr and "no such file" in result.stderr
    assert "Traceback" not in result.stderr


@pytest.mark.parametrize("path, said", [
    ("No Such Tactile Camera 0000", "v4l2 'No Such Tactile Camera 0000': no camera of that name (plugged in?)"),
    ("/dev/video_fv_absent", "v4l2 /dev/video_fv_absent: no /dev/video_fv_absent (plugged in?)"),
    ("97", "v4l2 97: no /dev/video97 (plugged in?)"),
])
def test_a_camera_not_plugged_in_exits_not_ready(bus, path: str, said: str) -> None:
    """A V4L2 camera not there yet exits TEMPFAIL (75), which a launch starts again until it is plugged
    in: it exited 2, as a configuration error does, so a launch could not tell the two apart. A /dev path
    or index is checked before OpenCV opens it (its warnings carry the time: each try's differed)."""
    result = run_fv("node", "camera", "-p", "source=v4l2", "-p", f"path={path}", timeout_s=20)
    assert result.returncode == TEMPFAIL, result.stderr
    assert f"fv node: not ready: {said}" in result.stderr
    assert "Traceback" not in result.stderr and "WARN" not in result.stderr


def test_unknown_source_param_is_rejected(bus) -> None:
    result = run_fv("node", "camera", "-p", "source=webcam", timeout_s=20)
    assert result.returncode == 2 and "source 'webcam'" in result.stderr


def test_start_after_holds_the_first_frame_until_the_named_nodes_report(bus, spawn, tmp_path: Path) -> None:
    """A status of the named node from before the camera started (latched on the forwarder, left by an
    earlier launch) does not count: the camera waits for one published since."""
    from msgs import NodeStatus
    from nodes.bus import PublisherSocket
    video = tmp_path / "clip.avi"
    _write_video(video)
    pub = PublisherSocket("late_node")
    assert pub.wait_connected(5.0)
    pub.publish("/status", NodeStatus(), latched=True)  # the earlier launch's late_node
    with TopicReader(["/camera/image"]) as reader:
        spawn("node", "camera", "-p", "source=video", "-p", f"path={video}", "-p", "fps=25", "-p", "loop=false",
              "-p", "start_after=[late_node]")
        wait_status("camera", timeout_s=20.0)
        assert reader.recv(1.0) is None  # held back: late_node has not reported since
        opened_ns = time.time_ns()
        pub.publish("/status", NodeStatus(), latched=True)
        frames = [reader.recv(5.0) for _ in range(20)]
        pub.close()
    assert all(f is not None for f in frames)
    assert [f.msg.seq for f in frames] == list(range(20))  # the whole video, from its first frame
    # the first frame, read at start to check the video, is stamped when played: stamped at its read, it
    # came seconds before the second and a slip detector took the gap for a new grasp
    assert frames[0].msg.stamp_ns >= opened_ns
    assert max(np.diff([f.msg.stamp_ns for f in frames])) < 0.5e9


def test_start_after_gives_up_after_the_timeout_with_a_warning(bus, spawn, tmp_path: Path) -> None:
    video = tmp_path / "clip.avi"
    _write_video(video)
    with TopicReader(["/camera/image"]) as reader:
        spawn("node", "camera", "-p", "source=video", "-p", f"path={video}", "-p", "fps=25",
              "-p", "start_after=[absent_node]", "-p", "start_timeout_s=1.5")
        assert reader.recv(15.0) is not None
    st = wait_status("camera", lambda st: "absent_node" in st.message, 10.0)
    assert "started without a status" in st.message


def test_a_scene_that_fails_while_playing_stops_the_camera_saying_why(bus, tmp_path: Path) -> None:
    """A scene whose object left the skin at frame 4: the camera warned once, "reopening in 0.5 s", and replayed
    frames 0 to 3 for good, its status 'ok' again at each reopen. Its params play the scene's first
    `scene_check_frames` frames' mechanics and refuse it; a later frame the play meets stops the camera, its
    status saying so first."""
    import yaml

    from msgs import NodeStatus
    from nodes.camera import CameraNode
    from nodes.exit_codes import NodeFailed
    scene = tmp_path / "off.yaml"
    scene.write_text(yaml.safe_dump({"object": {"shape": "sphere"}, "fps": 30, "initial": {"normal_N": 1.0},
                                     "steps": [{"action": "slide", "duration_s": 1.0, "velocity_mm_s": [100, 0]}]}))
    error = r"sim .*off.yaml: frame 4 \(t = 0.133 s\): the object's centre \(13.33, 0.00\) mm has left the skin"
    with TopicReader(["/camera/image", "/status"]) as reader:
        with pytest.raises(ValueError, match=error.replace("sim .*off", "off")):
            CameraNode("camera", {"scene": str(scene)})
        node = CameraNode("camera", {"scene": str(scene), "fps": 60.0, "scene_check_frames": 2})
        with pytest.raises(NodeFailed, match=f"^{error}"):
            node.spin(install_signals=False)
        received = []
        while (item := reader.recv(1.0)) is not None:
            received.append(item.msg)
    statuses = [m for m in received if isinstance(m, NodeStatus) and m.node == "camera"]
    assert statuses[-1].state == "error" and re.match(f"stopped: {error}", statuses[-1].message), statuses[-1]
    assert sum(not isinstance(m, NodeStatus) for m in received) <= 4  # frames 0 to 3, once


def test_a_camera_reads_its_scene_file_once(bus, monkeypatch: pytest.MonkeyPatch) -> None:
    """Its params read the scene (and checked it), then its source read the file again to play it."""
    from nodes import sim_source
    from nodes.camera import CameraNode
    scene = str(Path(__file__).parents[2] / "launch" / "scenes" / "press_shear_slide.yaml")
    read: list[str] = []
    load_scene = sim_source.load_scene
    monkeypatch.setattr(sim_source, "load_scene", lambda path: read.append(path) or load_scene(path))
    node = CameraNode("camera", {"scene": scene, "scene_check_frames": 1})
    try:
        node.setup()
        assert read == [scene]
        assert node.source.sensor.scene is node.params.sim_scene
    finally:
        node.close()


def test_a_scene_that_cannot_be_played_ends_fv_node_camera_at_its_start(bus, tmp_path: Path) -> None:
    import yaml
    scene = tmp_path / "off.yaml"
    scene.write_text(yaml.safe_dump({"object": {"shape": "sphere"}, "fps": 30, "initial": {"normal_N": 1e6},
                                     "steps": [{"action": "hold", "duration_s": 1.0}]}))
    result = run_fv("node", "camera", "-p", f"scene={scene}", timeout_s=30)
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr
    assert "off.yaml: frame 0 (t = 0.000 s): the normal load of 1e+06 N pushes 256 of the 256 markers" in result.stderr


@pytest.mark.parametrize("fps", [1e-12, 1e-300])
def test_a_camera_slower_than_a_frame_a_century_runs_until_stopped(bus, fps: float) -> None:
    """At fps 1e-12 (a period past threading.TIMEOUT_MAX, 292 years) the node's executor raised OverflowError
    ('timestamp out of range for platform time_t') as it began to wait, and the camera died with a traceback."""
    import threading

    from nodes.camera import CameraNode
    node = CameraNode("camera", {"fps": fps})
    errors: list[BaseException] = []

    def spin() -> None:
        try:
            node.spin(install_signals=False)
        except BaseException as exc:
            errors.append(exc)

    thread = threading.Thread(target=spin, daemon=True)
    thread.start()
    try:
        wait_status("camera", timeout_s=10.0)
    finally:
        node.stop()
        thread.join(5.0)
    assert not thread.is_alive() and errors == []


def test_a_camera_skips_the_scene_check_its_launch_made_and_makes_it_for_another_scene(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The check ran in the launcher and again in each start of the camera: 0.5 s (a sphere) to 2.4 s (a twisting
    key) for 600 frames. A camera given the checks its launch made (`nodes.launch_checks`) skips a scene of the
    same content; a scene edited since, or one checked for fewer frames, is checked."""
    import yaml

    from nodes import launch_checks, sim_source
    from nodes.camera import CameraParams
    checked = []
    check_scene = sim_source.check_scene
    monkeypatch.setattr(sim_source, "check_scene", lambda scene, frames: checked.append(frames) or check_scene(scene, frames=frames))
    monkeypatch.setattr(launch_checks, "_noted", set())  # the launcher's process
    monkeypatch.delenv(launch_checks.CHECKED_ENV, raising=False)
    scene = tmp_path / "s.yaml"
    desc = {"object": {"shape": "sphere"}, "fps": 30, "initial": {"normal_N": 1.0},
            "steps": [{"action": "slide", "duration_s": 1.0, "velocity_mm_s": [10, 0]}]}
    scene.write_text(yaml.safe_dump(desc))
    CameraParams(scene=str(scene), scene_check_frames=20)
    assert checked == [20]
    given = launch_checks.env()
    monkeypatch.setattr(launch_checks, "_noted", set())  # the camera's process, the launcher's checks given
    monkeypatch.setenv(launch_checks.CHECKED_ENV, given[launch_checks.CHECKED_ENV])
    CameraParams(scene=str(scene), scene_check_frames=20)
    assert checked == [20]
    CameraParams(scene=str(scene), scene_check_frames=30)
    assert checked == [20, 30]
    scene.write_text(yaml.safe_dump({**desc, "steps": [{"action": "slide", "duration_s": 1.0, "velocity_mm_s": [100, 0]}]}))
    with pytest.raises(ValueError, match=r"frame 4 \(t = 0.133 s\): the object's centre .* has left the skin"):
        CameraParams(scene=str(scene), scene_check_frames=20)


def test_a_prerendered_scene_holds_only_the_images_it_publishes(caplog: pytest.LogCaptureFixture) -> None:
    """It held every frame's ground truth too (pressure, traction and displacement fields): 550 kB a frame, 16.5
    MB per second of scene at 30 fps, where its image is 307 kB. The rendering is logged: within the default
    prerender_max_mb it is 10 to 20 s before the camera's first frame, which said nothing."""
    import tracemalloc

    from fv_algos.sim.sensor import check_scene
    from nodes.sim_source import SimSource, prerender_bytes
    source = SimSource(str(Path(__file__).parents[2] / "launch" / "scenes" / "twist_key.yaml"), 0, 30.0, prerender=True)
    caplog.set_level("INFO", logger="fv.camera")
    check_scene(source.sensor.scene)  # scipy's FFT caches its plans (1.4 MB) at the mechanics' first solves: made
    # here, not counted, so that the test gives the same answer alone as after other tests
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        source.open()
        held = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    images = [source.read().image for _ in range(source.sensor.scene.n_frames)]
    assert all(image.shape == (480, 640) for image in images)
    assert held < 1.05 * sum(image.nbytes for image in images), held
    assert prerender_bytes(source.sensor.scene) == sum(image.nbytes for image in images)  # what prerender_max_mb bounds
    assert f"twist_key.yaml: rendering its {len(images)} frames (16 MB) before the first is published" in caplog.text
    assert "twist_key.yaml: rendered in " in caplog.text


def test_a_scene_whose_prerendered_images_pass_prerender_max_mb_is_refused_naming_its_size(tmp_path: Path) -> None:
    """Prerender held every image of the scene, with no bound: a 600 s scene (18,030 frames) took 5.5 GB and
    353 s before its first frame, the 100,000-frame maximum would take 30.7 GB. Its params now refuse a scene
    whose images would pass prerender_max_mb (`fv launch --check` too), naming its frames, their size and the memory."""
    from nodes.camera import CameraParams
    scene = tmp_path / "long.yaml"
    scene.write_text("object: {shape: sphere}\nfps: 30\neffects: [normal]\n"
                     "steps: [{action: press, duration_s: 0.5, normal_N: 1.0}, {action: hold, duration_s: 60.5}]\n")
    error = (f"sim {scene}: prerender would hold its 1,830 frames (61 s at 30 fps) as 640x480 images of 307 kB: "
             "562 MB, over prerender_max_mb 500 (room for 1,627 frames, 54.3 s of this scene); play it without "
             "prerender, shorten it or raise prerender_max_mb")
    with pytest.raises(ValueError, match=f"^{re.escape(error)}$"):
        CameraParams(scene=str(scene), prerender=True, scene_check_frames=1)
    CameraParams(scene=str(scene), prerender=True, prerender_max_mb=600.0, scene_check_frames=1)
    CameraParams(scene=str(scene), scene_check_frames=1)  # played as it renders: no bound
    with pytest.raises(ValueError, match="prerender_max_mb 0.0 must be > 0"):
        CameraParams(scene=str(scene), prerender=True, prerender_max_mb=0.0)


def test_a_camera_slower_than_its_fps_says_so_until_it_keeps_the_rate_again() -> None:
    """A camera asked for fps 1000 published about 180 frames/s (the simulator renders a frame in 5 ms), its
    status "ok", and nothing said it could not keep the rate: a renderer, decoder or driver slower than fps
    fell behind without a word. Published frames are counted over stretches of RATE_CHECK_S (here on a
    made-up clock); a stretch below RATE_SHORT of the rate warns, and one that keeps it clears the warning."""
    from nodes.camera import RATE_CHECK_S, CameraNode
    node = CameraNode("camera", {"fps": 100.0})
    try:
        node.setup()
        now = 0.0

        def publish(period_s: float, seconds: float) -> None:
            nonlocal now
            for _ in range(round(seconds / period_s)):
                now += period_s
                node._check_rate(now)

        publish(0.0105, 2 * RATE_CHECK_S)  # 95 frames/s: a busy machine's camera, not warned
        assert node.state == "ok" and node.counters["below_rate"] == 0
        publish(0.02, 2 * RATE_CHECK_S)
        assert node.state == "warn" and node.counters["below_rate"] >= 1
        assert node.message.startswith("sim random scenarios: 50.0 frames/s over 5.0 s, below the 100 asked for (fps)")
        node._lost("sim random scenarios: no frame")  # another warning, which the rate check leaves alone
        publish(0.01, 2 * RATE_CHECK_S)
        assert node.message.startswith("sim random scenarios: no frame")
        node.clear_warning()
        publish(0.02, 2 * RATE_CHECK_S)
        publish(0.01, 2 * RATE_CHECK_S)  # back to the rate: cleared
        assert node.state == "ok" and node.message == ""
    finally:
        node.close()


def test_a_looped_folder_whose_first_image_cannot_be_read_says_each_pass_start(bus, spawn, tmp_path: Path) -> None:
    """The camera said a pass's start only at frame_index 0: a folder whose first image cannot be read numbers
    each pass from 1, and no pass start was said (a tracker respawned as a pass began resumed the pass
    before's reference), while the tracker still saw each pass start over (1 after 3)."""
    folder = tmp_path / "imgs"
    folder.mkdir()
    (folder / "000.png").write_bytes(b"not a png")
    for k in range(1, 4):
        cv2.imwrite(str(folder / f"{k:03d}.png"), np.full((24, 32), 40 * k, np.uint8))
    with TopicReader(["/camera/image", "/camera/pass_start"]) as reader:
        spawn("node", "camera", "-p", "source=folder", "-p", f"path={folder}", "-p", "fps=50")
        items = [reader.recv(15.0 if k == 0 else 2.0) for k in range(11)]
    assert all(item is not None for item in items)
    assert [item.msg.frame_index if item.topic == "/camera/image" else "start" for item in items] == [
        "start", 1, 2, 3, "start", 1, 2, 3, "start", 1, 2]
