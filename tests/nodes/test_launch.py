"""Launch files: validation before anything starts (file, line and key in every error),
args and includes, respawn by exit code (a node not ready waits, one that cannot start ends the
launch), required nodes, and a clean stop on Ctrl-C."""
from __future__ import annotations

import io
import logging
import re
import os
import signal
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import cv2
import numpy as np
import pytest

from nodes.bag.codec import RECORDING_END_META
from msgs import Image
from nodes.bag.reader import BagReader
from nodes.bus import TopicReader, node_name, resolve_topic
from nodes.camera_sources import SourceError, SourceMissing, find_v4l2_device
from nodes.exit_codes import CONFIG, OK, TEMPFAIL
from nodes.forwarder import ping
from nodes.launch_file import LaunchError, load_launch, parse_arg_overrides
from nodes.launcher import START_TRIES, Launch
from nodes.proc_stats import process_alive
from tests.nodes.conftest import REPO, Bus, children_of, kill_group, poll_until, run_fv, wait_status
from tests.nodes.test_bag import write_bag

GOOD_NODE = "  - kind: talker\n    name: t\n"


@pytest.fixture
def video_files(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """clip.avi, a.avi and b.avi in the working folder (a video camera's params need the file), bags
    (a bag player's params need the topics it plays): run1 of one camera, session of two (left and right),
    right_only of the right one, and bad.yaml, a scene with no steps."""
    monkeypatch.chdir(tmp_path)
    for name in ("clip.avi", "a.avi", "b.avi"):
        (tmp_path / name).write_bytes(b"")
    for name, topics in (("run1", ["/camera/image"]), ("session", ["/left/camera/image", "/right/camera/image"]),
                         ("right_only", ["/right/camera/image"])):
        frame = Image(stamp_ns=1, data=np.zeros((8, 8), np.uint8), encoding="mono8")
        write_bag(tmp_path / name, [(topic, False, frame, 10**9) for topic in topics], finished=True)
    (tmp_path / "bad.yaml").write_text("object: {shape: sphere}\nfps: 30\n")  # a scene file that is no scene


def _write(folder: Path, name: str, text: str) -> Path:
    path = folder / name
    path.write_text(text)
    return path


def _refusal(path: Path) -> str:
    """The message of the LaunchError that loading the launch file `path` raises."""
    with pytest.raises(LaunchError) as err:
        load_launch(path)
    return str(err.value)


@pytest.mark.parametrize("text, line, key", [
    ("nodes:\n  - kind: talkr\n", 2, "nodes[0].kind"),
    ("nodes:\n  - kind: talker\n    params:\n      rate_hz: 5\n      speed: 3\n", 5, "params.speed"),
    ("nodes:\n  - kind: talker\n    params:\n      rate_hz: fast\n", 4, "params.rate_hz"),
    ("nodes:\n  - kind: talker\n    params: {rate_hz: 0}\n", 3, "params"),
    ("nodes:\n  - kind: talker\n    params: {rate_hz: [1\n", 4, "bad YAML"),
    ("nodes:\n  - kind: talker\n\tname: x\n", 3, "bad YAML"),
    ("nodes:\n" + GOOD_NODE + "  - kind: listener\n    params:\n      topic: $(arg topic)\n", 6, "params.topic"),
    ("args:\n  robot: {description: which}\nnodes:\n" + GOOD_NODE, 2, "args.robot"),
    ("nodes:\n  - kind: talker\n    respawn: yes please\n", 3, "respawn"),
    ("nodes:\n  - kind: talker\n    respawn_delay: -1\n", 3, "respawn_delay"),
    ("nodes:\n  - kind: talker\n    colour: red\n", 3, "nodes[0].colour"),
    ("nodes:\n" + GOOD_NODE + GOOD_NODE, 4, "name"),
    ("nodes:\n  - kind: talker\n    kind: listener\n", 3, "duplicate key"),
    ("nodez: []\n", 1, "nodez"),
    ("include:\n  - file: missing.yaml\n", 2, "include[0].file"),
    ("nodes:\n  - kind: talker\n    namespace: left arm\n", 3, "nodes[0] (talker).namespace"),
    # refused as the node started, after the forwarder had (`--check` passed them)
    ("nodes:\n  - kind: talker\n    env: {\"A=B\": 1}\n", 3, "nodes[0] (talker).env: 'A=B' is not an environment"),
    ("nodes:\n  - kind: talker\n    env: {A: \"x\\0y\"}\n", 3, "nodes[0] (talker).env.A: a value holds no NUL"),
    ("nodes:\n  - kind: talker\n    remap: {/chatter: rel}\n", 3, "remap./chatter: topic 'rel': must start with '/'"),
    ("nodes:\n  - kind: talker\n    remap: {/chatter: ''}\n", 3, "remap./chatter: topic '': must start with '/'"),
])
def test_bad_launch_file_names_file_line_and_key(tmp_path: Path, text: str, line: int, key: str) -> None:
    path = _write(tmp_path, "bad.yaml", text)
    message = _refusal(path)
    assert f"{path}:{line}:" in message and key in message, message


def test_a_launch_file_that_is_not_utf8_is_named_with_its_line(tmp_path: Path) -> None:
    """It gave "'utf-8' codec can't decode byte 0xe9 in position 31", naming no file."""
    path = tmp_path / "latin.yaml"
    path.write_bytes("nodes:\n  - kind: talker\n    # caf\xe9\n".encode("latin-1"))
    with pytest.raises(LaunchError, match=rf"{path} line 3: not UTF-8 text .*byte 0xe9"):
        load_launch(path)


def test_error_in_included_file_names_that_file(tmp_path: Path) -> None:
    inner = _write(tmp_path, "inner.yaml", "args: {rate: 1.0}\nnodes:\n  - kind: talker\n    params:\n"
                                           "      rate_hz: $(arg rate)\n")
    outer = _write(tmp_path, "outer.yaml", "include:\n  - file: inner.yaml\n    args: {rate: slow}\n")
    message = _refusal(outer)
    assert f"{inner}:5:" in message and "rate_hz" in message


def test_an_included_file_s_arguments_are_said_against_the_include_entry(tmp_path: Path) -> None:
    """An included file's missing argument was said with the command line of that file as the fix
    (`fv launch sub.yaml need:=VALUE`), which the launched file then refused as not declared."""
    _write(tmp_path, "sub.yaml", "args:\n  need: {description: x}\nnodes:\n  - kind: talker\n")
    outer = _write(tmp_path, "outer.yaml", "include:\n  - file: sub.yaml\n")
    assert _refusal(outer).endswith(f"args.need: no default and not given (give it in the args of the include "
                                    f"entry at {outer}:2)")
    other = _write(tmp_path, "other.yaml", "include:\n  - {file: sub.yaml, args: {need: 1, x: 2}}\n")
    assert f"argument 'x' given by the include entry at {other}:2 but not declared" in _refusal(other)


def test_args_includes_and_overrides(tmp_path: Path) -> None:
    _write(tmp_path, "inner.yaml", "args: {rate: 1.0, ns: ''}\nnodes:\n  - kind: talker\n    name: inner_talker\n"
                                   "    namespace: $(arg ns)\n    params: {rate_hz: $(arg rate)}\n"
                                   "    remap: {/chatter: $(arg ns)/chat, $(arg ns)/rate: /rate}\n")
    outer = _write(tmp_path, "outer.yaml",
                   "args:\n  rate: 4\n  side: left\ninclude:\n  - file: inner.yaml\n"
                   "    args: {rate: $(arg rate), ns: /$(arg side)}\n"
                   "nodes:\n  - kind: listener\n    env: {OMP_NUM_THREADS: 1}\n    respawn: true\n"
                   "    max_retries: 2\n    required: true\n")
    specs = {s.name: s for s in load_launch(outer, {"rate": 7.5})}
    talker, listener = specs["left_inner_talker"], specs["listener"]
    assert talker.params == {"rate_hz": 7.5} and talker.namespace == "/left"
    assert talker.remap == {"/chatter": "/left/chat", "/left/rate": "/rate"}  # a key too (it was kept as written)
    assert listener.env == {"OMP_NUM_THREADS": "1"} and listener.respawn and listener.max_retries == 2
    assert listener.required and listener.respawn_delay_s == 1.0
    assert talker.argv()[:4] == ["node", "talker", "--name", "left_inner_talker"]
    with pytest.raises(LaunchError, match="'speed' given but not declared"):
        load_launch(outer, {"speed": 1})


@pytest.mark.usefixtures("video_files")
def test_command_line_arguments_are_text_where_the_argument_is(tmp_path: Path) -> None:
    """Read as YAML, `device:=2` (a V4L2 index) was the int 2 and refused ("param 'path' = 2 is not of type
    str"), and a video path with " #" was cut there, the rest read as a comment."""
    specs = {s.name: s for s in load_launch(REPO / "launch" / "gelsight_mini.yaml", parse_arg_overrides(["device:=2"]))}
    assert specs["camera"].params["path"] == "2"
    pair = load_launch(REPO / "launch" / "gelsight_mini_pair.yaml", parse_arg_overrides(["left:=0", "right:=1"]))
    assert sorted(s.params["path"] for s in pair if s.kind == "camera") == ["0", "1"]  # no defaults: text too
    odd = tmp_path / "grasp #2.avi"
    odd.write_bytes(b"")
    specs = {s.name: s for s in load_launch(REPO / "launch" / "video.yaml", parse_arg_overrides([f"video:={odd}"]))}
    assert specs["camera"].params["path"] == str(odd)
    typed = {s.name: s for s in load_launch(REPO / "launch" / "pipeline.yaml",
                                            parse_arg_overrides(["fps:=12.5", "threads:=2", "standby:=false"]))}
    assert typed["camera"].params["fps"] == 12.5 and typed["slip_detector"].params["threads"] == 2


def test_an_include_in_a_namespace_moves_its_nodes_topics_and_names_there(tmp_path: Path) -> None:
    """`namespace: left` on an include: each node's namespace gets /left before it (nested includes
    compose, and a node's own namespace goes after them), its name the prefix left_; names must stay unique,
    and a bad namespace names its line."""
    _write(tmp_path, "inner.yaml", "nodes:\n  - kind: talker\n  - kind: listener\n    namespace: ears\n")
    _write(tmp_path, "finger.yaml", "args: {side: left}\ninclude:\n  - file: inner.yaml\n    namespace: $(arg side)\n")
    outer = _write(tmp_path, "hand.yaml", "include:\n  - {file: finger.yaml, namespace: /hand, args: {side: left}}\n"
                                          "  - {file: finger.yaml, namespace: hand, args: {side: right}}\n"
                                          "nodes:\n  - kind: talker\n")
    specs = {s.name: s for s in load_launch(outer)}
    assert {name: s.namespace for name, s in specs.items()} == {
        "hand_left_talker": "/hand/left", "hand_left_ears_listener": "/hand/left/ears",
        "hand_right_talker": "/hand/right", "hand_right_ears_listener": "/hand/right/ears", "talker": ""}
    assert resolve_topic("chatter", specs["hand_right_ears_listener"].namespace) == "/hand/right/ears/chatter"
    # the ROS-style path `fv param` takes: the node's namespace, then the name in its own file
    assert [node_name(path) for path in ("/hand/left/talker", "hand/right/ears/listener", "/talker")] == [
        "hand_left_talker", "hand_right_ears_listener", "talker"]
    twice = _write(tmp_path, "twice.yaml", "include:\n  - {file: inner.yaml, namespace: a}\n"
                                           "  - {file: inner.yaml, namespace: a}\n")
    with pytest.raises(LaunchError, match=rf"{twice}:3: name: node name 'a_talker' \(/a/talker, entry .*inner.yaml:2\) "
                                          rf"is already used at {twice}:2"):
        load_launch(twice)
    bad = _write(tmp_path, "bad.yaml", "include:\n  - file: inner.yaml\n    namespace: left/\n")
    with pytest.raises(LaunchError, match=rf"{bad}:3: include\[0\].namespace: 'left/' is not a namespace"):
        load_launch(bad)


def test_a_node_entrys_own_namespace_is_part_of_its_name_and_path(tmp_path: Path) -> None:
    """`namespace: left` on a node entry moves its name and its ROS-style path as an include's does: two
    cameras named `camera` in left and right are left_camera (/left/camera) and right_camera (they were
    refused, both named camera); under an include's namespace arm, arm_left_camera (/arm/left/camera)."""
    finger = _write(tmp_path, "fingers.yaml", "nodes:\n  - {kind: camera, name: camera, namespace: left}\n"
                                              "  - {kind: camera, name: camera, namespace: right}\n")
    specs = load_launch(finger)
    assert [(s.name, s.path, s.namespace) for s in specs] == [
        ("left_camera", "/left/camera", "/left"), ("right_camera", "/right/camera", "/right")]
    assert specs[0].argv()[:4] == ["node", "camera", "--name", "left_camera"]
    arm = _write(tmp_path, "arm.yaml", "include:\n  - {file: fingers.yaml, namespace: arm}\n")
    specs = load_launch(arm)
    assert [(s.name, s.path, s.namespace) for s in specs] == [
        ("arm_left_camera", "/arm/left/camera", "/arm/left"), ("arm_right_camera", "/arm/right/camera", "/arm/right")]
    assert resolve_topic("camera/image", specs[0].namespace) == "/arm/left/camera/image"
    assert all(node_name(s.path) == s.name for s in specs)  # `fv param get /arm/left/camera` finds it


def test_an_absolute_namespace_stands_under_an_include_namespace(tmp_path: Path) -> None:
    """As in ROS, `/left` on a node or an include is not moved by the namespace of an include around it
    (its topics, name and path); `left` is. A file with `/left` included twice gives both copies one name."""
    _write(tmp_path, "inner.yaml", "nodes:\n  - {kind: talker, namespace: /left}\n"
                                   "  - {kind: listener, namespace: ears}\n")
    arm = _write(tmp_path, "arm.yaml", "include:\n  - {file: inner.yaml, namespace: arm}\n")
    assert [(s.name, s.path, s.namespace) for s in load_launch(arm)] == [
        ("left_talker", "/left/talker", "/left"), ("arm_ears_listener", "/arm/ears/listener", "/arm/ears")]
    _write(tmp_path, "hand.yaml", "include:\n  - {file: inner.yaml, namespace: /hand}\n")
    arm_hand = _write(tmp_path, "arm_hand.yaml", "include:\n  - {file: hand.yaml, namespace: arm}\n")
    assert [(s.name, s.path, s.namespace) for s in load_launch(arm_hand)] == [
        ("left_talker", "/left/talker", "/left"), ("hand_ears_listener", "/hand/ears/listener", "/hand/ears")]
    twice = _write(tmp_path, "twice.yaml", "include:\n  - {file: inner.yaml, namespace: a}\n"
                                           "  - {file: inner.yaml, namespace: b}\n")
    with pytest.raises(LaunchError, match=rf"{twice}:3: name: node name 'left_talker' \(/left/talker, entry .*inner.yaml:2\) "
                                          rf"is already used at {twice}:2"):
        load_launch(twice)


def test_a_name_made_twice_by_namespaces_names_both_entries(tmp_path: Path) -> None:
    """Two nodes that end with one name are refused with both places in the launch file and paths: `left_camera`
    at the root and `camera` in the namespace left, or `camera` in left in two files (the include entry, and
    the entry in the included file). One file included twice in one namespace named the entry in it twice
    ("inner.yaml:2: ... is already used at inner.yaml:2"): the two include entries tell the nodes apart."""
    clash = _write(tmp_path, "clash.yaml", "nodes:\n  - {kind: camera, name: left_camera}\n"
                                           "  - {kind: talker, name: camera, namespace: left}\n")
    assert _refusal(clash) == (f"{clash}:3: name: node name 'left_camera' (/left/camera) is already used at "
                              f"{clash}:2 (/left_camera)")
    finger = _write(tmp_path, "finger.yaml", "nodes:\n  - {kind: camera, name: camera, namespace: left}\n")
    twice = _write(tmp_path, "twice.yaml", "include:\n  - {file: finger.yaml}\n"
                                           "nodes:\n  - {kind: talker, name: camera, namespace: left}\n")
    assert _refusal(twice) == (f"{twice}:4: name: node name 'left_camera' (/left/camera) is already used at "
                              f"{twice}:2 (/left/camera, entry {finger}:2)")
    inner = _write(tmp_path, "inner.yaml", "nodes:\n  - kind: talker\n")
    both = _write(tmp_path, "both.yaml", "include:\n  - {file: inner.yaml, namespace: a}\n"
                                         "  - {file: inner.yaml, namespace: a}\n")
    assert _refusal(both) == (f"{both}:3: name: node name 'a_talker' (/a/talker, entry {inner}:2) is already used at "
                             f"{both}:2 (/a/talker, the same entry)")
    _write(tmp_path, "hand.yaml", "include:\n  - {file: inner.yaml, namespace: a}\n")
    _write(tmp_path, "other.yaml", "nodes:\n  - kind: listener\n  - {kind: talker, namespace: a}\n")
    arm = _write(tmp_path, "arm.yaml", "include:\n  - file: hand.yaml\n  - file: other.yaml\n")
    assert _refusal(arm) == (f"{arm}:3: name: node name 'a_talker' (/a/talker, entry {tmp_path / 'other.yaml'}:3) "
                            f"is already used at {arm}:2 (/a/talker, entry {inner}:2)")


def test_check_shows_each_node_name_with_its_path(tmp_path: Path) -> None:
    """`fv launch --check` lists a node in a namespace by its name and its ROS-style path."""
    path = _write(tmp_path, "pair.yaml", "nodes:\n  - {kind: talker, name: talker, namespace: left}\n"
                                         "  - {kind: listener}\n")
    result = run_fv("launch", "--check", str(path))
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines() == [
        f"left_talker (/left/talker): talker namespace=/left params={{}} ({path}:2)",
        f"listener: listener params={{}} ({path}:3)"]


def test_demo_launch_file_is_valid() -> None:
    names = [s.name for s in load_launch(REPO / "launch" / "demo.yaml", {"rate_hz": 2})]
    assert names == ["talker", "listener"]


@pytest.mark.parametrize("name", ["pipeline.yaml", "view.yaml", "video.yaml", "gelsight_mini.yaml", "replay.yaml"])
@pytest.mark.usefixtures("video_files")
def test_the_cameras_of_the_shipped_pipelines_wait_for_the_nodes_that_take_a_reference(name: str) -> None:
    """The tracker takes its reference from the first frame it gets: a camera (or a bag player) that starts
    before it hands it a deformed skin (on the simulated main job, every held frame was then called slip)."""
    args = {"video.yaml": {"video": "clip.avi"}, "replay.yaml": {"bag": "run1"}}.get(name, {})
    specs = {s.name: s for s in load_launch(REPO / "launch" / name, args)}
    source = specs["bag_play" if name == "replay.yaml" else "camera"]
    assert set(source.params["start_after"]) == {"tracker", "interpolator", "slip_detector"}


def test_start_after_names_resolve_in_the_namespace_of_their_file(tmp_path: Path) -> None:
    """`pipeline.yaml` included under a namespace: its camera waited for `tracker`, `interpolator` and
    `slip_detector`, no nodes of that launch (they are `left_tracker` ...), its whole 30 s, reporting ok. Its
    names now resolve in its namespace; a name that is no node of the launch is refused, naming the entry."""
    outer = _write(tmp_path, "outer.yaml", f"include:\n  - {{file: {REPO / 'launch' / 'pipeline.yaml'}, "
                                           "namespace: left}\n")
    camera = {s.name: s for s in load_launch(outer)}["left_camera"]
    assert camera.params["start_after"] == ["left_tracker", "left_interpolator", "left_slip_detector"]
    lone = _write(tmp_path, "lone.yaml", "nodes:\n  - {kind: camera, params: {start_after: [tracker]}}\n")
    with pytest.raises(LaunchError, match=rf"{lone}:2: camera's start_after names 'tracker', no node of this launch "
                                          r"\(its nodes: camera\)"):
        load_launch(lone)


@pytest.mark.parametrize("name, args", [("pipeline.yaml", {}), ("view.yaml", {}), ("video.yaml", {"video": "clip.avi"}),
                                        ("gelsight_mini.yaml", {}), ("replay.yaml", {"bag": "run1"}),
                                        ("video_pair.yaml", {"left": "a.avi", "right": "b.avi"}),
                                        ("gelsight_mini_pair.yaml", {"left": "2BKR", "right": "28G8"}),
                                        ("replay_pair.yaml", {"bag": "session"})])
@pytest.mark.usefixtures("video_files")
def test_every_shipped_pipeline_respawns_its_nodes_from_a_standby_spare(name: str, args: dict) -> None:
    """A tracker, interpolator or slip detector that dies on the robot is replaced at once, on a real sensor
    as on the simulated one (the real-sensor files had no respawn: /slip stopped for good)."""
    specs = [s for s in load_launch(REPO / "launch" / name, args)
             if s.kind in ("tracker", "interpolator", "slip_detector")]
    assert len(specs) == (6 if "pair" in name else 3)
    assert all(s.respawn and s.standby and s.respawn_delay_s <= 0.2 for s in specs), [s.name for s in specs]
    lean = load_launch(REPO / "launch" / name, {**args, "standby": False})  # a small robot PC: no spares
    assert not any(s.standby for s in lean) and all(s.respawn for s in lean if s.kind in ("tracker", "slip_detector"))


def test_the_live_gelsight_mini_launch_gives_the_default_model_frames_as_it_was_trained() -> None:
    """320x240 frames (1/7 off each border, as GelSight's software records them), at the model's
    rate, in colour, with the tracker's reference at the model's reference frame."""
    from nodes.camera import CameraParams
    from fv_algos.frame_crop import FrameCrop
    from nodes.shipped_models import model_path
    from fv_algos.trial_net import load_trial_model
    specs = {s.name: s for s in load_launch(REPO / "launch" / "gelsight_mini.yaml", {})}
    camera = CameraParams(**specs["camera"].params)
    model = load_trial_model(model_path(specs["slip_detector"].params["model"]))
    crop = FrameCrop.from_lists(camera.crop, camera.size)
    assert camera.source == "v4l2" and camera.path == "GelSight Mini" and camera.encoding == "bgr8"
    assert crop.window(448, 336) == (64, 48, 384, 288) and crop.size == (320, 240)
    assert camera.fps == model.fps and specs["tracker"].params["reference_frame"] == model.reference_frame


@pytest.mark.parametrize("name, args", [("video_pair.yaml", {"left": "a.avi", "right": "b.avi"}),
                                        ("gelsight_mini_pair.yaml", {"left": "2BKR", "right": "28G8"}),
                                        ("replay_pair.yaml", {"bag": "session"})])
@pytest.mark.usefixtures("video_files")
def test_both_fingers_start_together_and_their_slips_are_the_fusion_inputs(name: str, args: dict) -> None:
    specs = {s.name: s for s in load_launch(REPO / "launch" / name, args)}

    def topic(node: str, written: str) -> str:  # what the node's `written` topic name resolves to
        return resolve_topic(written, specs[node].namespace, specs[node].remap)

    waited = {n for n in specs if not n.endswith("_camera") and n not in ("slip_monitor", "bag_play")}
    assert waited == {f"{side}_{kind}" for side in ("left", "right") for kind in ("tracker", "interpolator", "slip_detector")} | {"slip_fusion"}
    for side in ("left", "right"):
        if name == "replay_pair.yaml":  # the bag plays both fingers' frames
            source, image = specs["bag_play"], f"/{side}/camera/image"
            assert image in source.params["topics"] and set(source.params["start_after"]) == waited
        else:
            source = specs[f"{side}_camera"]
            image = topic(f"{side}_camera", "camera/image")
            assert set(source.params["start_after"]) == waited and source.params["path"] == args[side]
            assert source.path == f"/{side}/camera"  # gelsight_finger.yaml names it camera, in its side's namespace
        assert image == topic(f"{side}_tracker", "camera/image") == topic(f"{side}_slip_detector", "camera/image") \
            == f"/{side}/camera/image"
        assert topic(f"{side}_tracker", "markers") == topic(f"{side}_interpolator", "markers") == f"/{side}/markers"
        assert topic(f"{side}_tracker", "markers/reference") == topic(f"{side}_slip_detector", "markers/reference") \
            == f"/{side}/markers/reference"
        assert topic(f"{side}_interpolator", "field") == topic(f"{side}_slip_detector", "field") == f"/{side}/field"
        assert topic(f"{side}_tracker", "/tracker/reset") == "/tracker/reset"  # one message starts both grasps
    assert specs["slip_fusion"].params["inputs"] == [topic(f"{side}_slip_detector", "slip") for side in ("left", "right")]


@pytest.mark.parametrize("name, args, error", [
    ("video.yaml", {"video": "nope.avi"}, "video nope.avi: no such file"),
    ("replay.yaml", {"bag": "nope"}, "bag nope: no such file or folder"),  # the launch started, then stopped
    ("replay_pair.yaml", {"bag": "clip.avi"}, "bag clip.avi: not an MCAP file"),
    ("replay_pair.yaml", {"bag": "right_only"},  # the launch played one finger, the other's pipeline idle
     r"bag right_only: has no topic '/left/camera/image' to play; its topics: \['/right/camera/image'\]"),
    ("replay_pair.yaml", {"bag": "run1"}, "bag run1: has no topic '/left/camera/image', '/right/camera/image' to play"),
    ("replay.yaml", {"bag": "session"}, "bag session: has no topic '/camera/image' to play"),
    ("replay.yaml", {"bag": "run1", "as_recorded_by": "/markers"},  # frames only: the live answers not recorded
     "bag run1: has no topic '/markers', which as_recorded_by names"),
    ("replay_pair.yaml", {"bag": "session", "as_recorded_by": ["/left/markers"]},
     r"sync_on \['/left/camera/image', '/right/camera/image'\] and as_recorded_by \['/left/markers'\]: give one"),
    ("video_pair.yaml", {"left": "a.avi", "right": "b.av"}, "video b.av: no such file"),
    ("video.yaml", {"video": "clip.avi", "model": "gelsite_online"}, "model 'gelsite_online' is neither a shipped"),
    ("video.yaml", {"video": "clip.avi", "model": "a.avi"}, "a.avi is not a model file"),  # respawned for good
    ("pipeline.yaml", {"threads": 0}, "threads 0 must be >= 1"),
    ("pipeline.yaml", {"scene": "nope.yaml"}, "sim nope.yaml: cannot be read \\(No such file"),  # it respawned for good
    ("pipeline.yaml", {"scene": "s.txt"}, "sim s.txt: a scene file must end in .yaml"),  # the file named once: it said
    ("pipeline.yaml", {"scene": "bad.yaml"}, "sim bad.yaml: scene needs key .steps."),  # "sim bad.yaml: bad.yaml: ..."
    ("pipeline.yaml", {"prerender": True}, "prerender needs a scene file"),
])
@pytest.mark.usefixtures("video_files")
def test_a_misspelt_video_or_model_is_refused_before_anything_starts(name: str, args: dict, error: str) -> None:
    """`fv launch --check` passed these; the launch then sat with no camera (the video) or respawned a
    slip detector that could never start, importing torch again every 3 s (the model)."""
    with pytest.raises(LaunchError, match=error):
        load_launch(REPO / "launch" / name, args)


def test_a_scene_that_cannot_be_played_is_refused_before_anything_starts(tmp_path: Path) -> None:
    """A scene that slides its object off the skin at frame 34: `fv launch --check` passed it; the launch's camera
    replayed frames 0 to 33 for good (with prerender:=true it was respawned for good, exit code 2)."""
    scene = _write(tmp_path, "off.yaml", "object: {shape: sphere, radius_mm: 10, mu: 0.8}\nfps: 30\n"
                   "effects: [normal, shear, slip, noise, lighting, lens]\nsteps:\n"
                   "  - {action: press, duration_s: 0.5, normal_N: 2.0}\n"
                   "  - {action: slide, duration_s: 1.0, velocity_mm_s: [20.0, 0.0]}\n  - {action: release, duration_s: 0.4}\n")
    error = "off.yaml: frame 34 (t = 1.133 s): the object's centre (12.67, 0.00) mm has left the skin"
    for args in ({"scene": str(scene)}, {"scene": str(scene), "prerender": True}):
        with pytest.raises(LaunchError, match=re.escape(error)):
            load_launch(REPO / "launch" / "pipeline.yaml", args)
    result = run_fv("launch", str(REPO / "launch" / "pipeline.yaml"), "--check", f"scene:={scene}", timeout_s=30)
    assert result.returncode == 2 and error in result.stderr, result.stderr


def test_a_prerendered_scene_too_big_for_memory_is_refused_before_anything_starts(tmp_path: Path) -> None:
    """`prerender:=true` with a 600 s scene passed `--check`; the camera then rendered for 6 minutes and held
    5.5 GB before its first frame. The launch arg prerender_max_mb (the camera's param) bounds it."""
    scene = _write(tmp_path, "long.yaml", "object: {shape: sphere}\nfps: 30\neffects: [normal]\n"
                   "steps: [{action: press, duration_s: 0.5, normal_N: 1.0}, {action: hold, duration_s: 600}]\n")
    for name in ("pipeline.yaml", "view.yaml"):
        with pytest.raises(LaunchError, match=r"prerender would hold its 18,015 frames .*: 5,534 MB, over prerender_max_mb 500"):
            load_launch(REPO / "launch" / name, {"scene": str(scene), "prerender": True})
        camera = next(s for s in load_launch(REPO / "launch" / name, {"scene": str(scene), "prerender": True,
                                                                      "prerender_max_mb": 6000}) if s.kind == "camera")
        assert camera.params["prerender_max_mb"] == 6000


@pytest.mark.parametrize("name, args", [("video.yaml", {"video": "clip.avi"}),
                                        ("video_pair.yaml", {"left": "a.avi", "right": "b.avi"}),
                                        ("gelsight_mini_pair.yaml", {"left": "2BKR", "right": "28G8"})])
@pytest.mark.usefixtures("video_files")
def test_a_camera_that_exits_for_good_ends_the_launch(name: str, args: dict) -> None:
    """A video OpenCV cannot decode: the camera exits and the launch ends (it used to wait for frames)."""
    cameras = [s for s in load_launch(REPO / "launch" / name, args) if s.kind == "camera"]
    assert cameras and all(s.required for s in cameras)


def test_check_takes_the_launch_arguments_before_or_after_it() -> None:
    demo = str(REPO / "launch" / "demo.yaml")
    for argv in (["--check", demo, "rate_hz:=3"], [demo, "--check", "rate_hz:=3"], [demo, "rate_hz:=3", "--check"]):
        result = run_fv("launch", *argv)
        assert result.returncode == 0 and "'rate_hz': 3}" in result.stdout, (argv, result.stderr)
    result = run_fv("launch", demo, "--chek", "rate_hz:=3")
    assert result.returncode == 2 and "unrecognized arguments: --chek" in result.stderr


def test_bad_file_from_the_command_line_starts_nothing(bus_env: Bus, tmp_path: Path) -> None:
    path = _write(tmp_path, "bad.yaml", "nodes:\n  - kind: talker\n    params: {rate_hz: fast}\n")
    result = run_fv("launch", str(path))
    assert result.returncode == 2 and f"{path}:3:" in result.stderr and "rate_hz" in result.stderr
    assert ping(bus_env.address) is None and not list(bus_env.folder.iterdir()), "something was started"
    assert run_fv("launch", str(REPO / "launch" / "demo.yaml"), "rate_hz:=").returncode == 2


def _launch(folder: Path, text: str) -> tuple[Launch, io.StringIO]:
    out = io.StringIO()
    launch = Launch.from_file(_write(folder, "l.yaml", text), output=out)
    return launch, out


def test_a_second_launch_of_the_same_nodes_on_one_bus_is_refused(bus: Bus, tmp_path: Path) -> None:
    """Two main jobs on one bus mixed their /slip streams (the state flipped every 0.1 s) without a word."""
    first, _ = _launch(tmp_path, "nodes:\n  - {kind: talker, params: {rate_hz: 20}}\n")
    first.start()
    try:
        wait_status("talker", timeout_s=8.0)
        (tmp_path / "b").mkdir()
        (tmp_path / "c").mkdir()
        second, _ = _launch(tmp_path / "b", "nodes:\n  - {kind: talker}\n  - {kind: listener}\n")
        with pytest.raises(RuntimeError, match=f"nodes named talker already run on {bus.address.url}"):
            second.start()
        other, _ = _launch(tmp_path / "c", "nodes:\n  - {kind: listener}\n")  # other names: welcome
        other.start()
        other.stop()
    finally:
        first.stop()


def test_fv_param_answers_for_the_launchers_own_status_name(bus: Bus, tmp_path: Path) -> None:
    """`fv node list` shows the launcher as launch_<file stem>: `fv param list` waited its whole timeout for it
    and printed "(no params answer)"; it has no params, said at once, and a request to it is refused."""
    launch, _ = _launch(tmp_path, "nodes:\n  - {kind: talker, params: {rate_hz: 20}}\n")
    launch.start()
    try:
        wait_status("talker", timeout_s=8.0)
        wait_status("launch_l", timeout_s=8.0)
        listed = run_fv("param", "list", "--timeout", "8", timeout_s=20.0)
        assert listed.returncode == 0 and "launch_l:\n  (no params)\n" in listed.stdout, listed.stdout
        assert "no params answer" not in listed.stdout and "  rate_hz: 20.0\n" in listed.stdout
        refused = run_fv("param", "set", "launch_l", "rate_hz", "5", "--timeout", "8", timeout_s=20.0)
        assert refused.returncode == 2 and "node 'launch_l' has no params" in refused.stderr, refused.stderr
    finally:
        launch.stop()


def test_a_launch_stopped_as_its_forwarder_starts_starts_nothing_more_and_says_no_error(
        bus_env: Bus, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Ctrl-C reaches the launcher and the forwarder it is starting (one process group): the launch said "forwarder
    ... exited with code 130 at start" and exited 2, and, stopped later in its start, it started every node, to stop
    each at once as its interpreter started (-15)."""
    launch, out = _launch(tmp_path, "nodes:\n  - {kind: talker}\n")

    def stopped_as_it_starts(_address: object, **_options: object) -> None:
        launch.stop()
        raise RuntimeError(f"forwarder for {bus_env.address.url} exited with code 130 at start")

    monkeypatch.setattr("nodes.forwarder.ensure_forwarder", stopped_as_it_starts)
    launch.start()
    assert launch.wait(10.0) and launch.stop() == OK
    assert "started" not in out.getvalue(), out.getvalue()


def test_a_launch_stopped_as_it_looks_for_a_forwarder_starts_none(
        bus_env: Bus, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A stop during the launch's look for a running forwarder (then a quick look, up to 0.3 s) started a forwarder
    anyway, waited for its answer, then stopped it: the launch's stop began 0.5 to 0.7 s late."""
    import nodes.forwarder
    launch, out = _launch(tmp_path, "nodes:\n  - {kind: talker}\n")
    looked = ping

    def stopped_as_it_looks(address: object, *timeout_s: float) -> dict | None:
        launch.stop()
        return looked(address, *timeout_s)

    monkeypatch.setattr(nodes.forwarder, "ping", stopped_as_it_looks)
    launch.start()
    assert launch.wait(10.0) and launch.stop() == OK
    assert "started" not in out.getvalue(), out.getvalue()


def test_killed_respawn_node_is_back_within_delay_plus_1s(bus_env: Bus, tmp_path: Path) -> None:
    delay_s = 0.3
    launch, out = _launch(tmp_path, f"nodes:\n  - kind: talker\n    params: {{rate_hz: 20}}\n"
                                    f"    respawn: true\n    respawn_delay: {delay_s}\n")
    launch.start()
    try:
        first = wait_status("talker", timeout_s=8.0).pid
        assert first == launch.pid("talker")
        signal_time = time.monotonic()
        subprocess.run(["kill", "-9", str(first)], check=True)
        while (pid := launch.pid("talker")) in (None, first) and time.monotonic() - signal_time < delay_s + 1.0:
            time.sleep(0.01)
        back_s = time.monotonic() - signal_time
        assert pid not in (None, first) and back_s <= delay_s + 1.0, f"not back after {back_s:.2f} s"
        assert wait_status("talker", lambda st: st.pid == pid, timeout_s=5.0)
    finally:
        launch.stop()
    assert "respawn 1 in 0.3 s" in out.getvalue()
    assert not process_alive(first) and not process_alive(pid)


@pytest.mark.parametrize("sig, launch_code", [("-KILL", 1), ("-TERM", 0)])
def test_required_node_death_stops_the_launch(bus_env: Bus, tmp_path: Path, sig: str, launch_code: int) -> None:
    """The launch ends with its required node, failed if that node failed: a replay whose player has
    played its bag (exit 0) ends well (it used to end with 1 whatever the node's code)."""
    launch, out = _launch(tmp_path, "nodes:\n  - kind: talker\n    required: true\n  - kind: listener\n")
    launch.start()
    try:
        wait_status("listener", timeout_s=8.0)
        wait_status("talker", timeout_s=8.0)  # spinning: SIGTERM now stops it cleanly (exit 0)
        pids = [launch.pid("talker"), launch.pid("listener"), launch._forwarder.pid]
        subprocess.run(["kill", sig, str(pids[0])], check=True)
        assert launch.wait(3.0), "the launch went on without its required node"
    finally:
        code = launch.stop()
    assert code == launch_code and "talker is required" in out.getvalue()
    assert not any(process_alive(p) for p in pids)


def _video(path: Path) -> Path:
    """A 160x120 MJPG video of 5 frames at `path`."""
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (160, 120))
    for _ in range(5):
        writer.write(np.full((120, 160, 3), 200, np.uint8))
    writer.release()
    return path


@pytest.mark.parametrize("respawn, starts, tries", [(True, START_TRIES, f"{START_TRIES} tries in a row"),
                                                    (False, 1, "no respawn")])
def test_a_node_that_cannot_start_ends_the_launch(bus_env: Bus, spawn, tmp_path: Path, respawn: bool, starts: int,
                                                  tries: str) -> None:
    """A configuration error found only at a node's start (a crop that leaves nothing of the video's frames:
    exit 2 before any NodeStatus) was respawned every respawn_delay for good, printing the same error each
    time while the other nodes waited (without respawn, the launch ran on without it). Now it is started
    START_TRIES times at most, one line names it and its error, the launcher's last status says it, and
    `fv launch` ends with 2."""
    video = _video(tmp_path / "clip.avi")
    path = _write(tmp_path, "l.yaml", f"nodes:\n  - kind: camera\n    params: {{source: video, path: {video}, "
                                      f"crop: [0.499]}}\n    respawn: {str(respawn).lower()}\n"
                                      "    respawn_delay: 0.1\n  - kind: listener\n")
    error = "crop [0.499, 0.499, 0.499, 0.499] leaves nothing of a 160x120 frame"
    statuses = []

    def keep_status() -> None:
        item = reader.recv(0.1)
        if item is not None and item.msg.node == "launch_l":
            statuses.append(item.msg)

    with TopicReader(["/status"]) as reader:
        proc = spawn("launch", str(path), stdout=subprocess.PIPE, text=True)
        poll_until(lambda: proc.poll() is not None, 60.0, period_s=0.0, between=keep_status)
    assert proc.wait(5.0) == CONFIG
    out = proc.stdout.read()
    assert out.count("[launch] started camera (camera)") == starts, out
    assert f"[launch] camera cannot start: {error} (a configuration error, {tries}); stopping the launch" in out
    assert statuses and statuses[-1].state == "error" and statuses[-1].message == f"camera cannot start: {error}"
    assert ping(bus_env.address) is None


def test_a_configuration_error_found_while_running_ends_the_launch(bus_env: Bus, spawn, tmp_path: Path) -> None:
    """A simulated scene past the frames checked at start (`scene_check_frames`) whose object leaves the skin:
    the camera stopped with exit 2 after its first NodeStatus, and the launch respawned it for good, each
    time playing the scene up to that frame. It now exits CONFIG_WHILE_RUNNING and the launch stops at once."""
    scene = _write(tmp_path, "off.yaml", "object: {shape: sphere}\nfps: 30\ninitial: {normal_N: 1.0}\n"
                                         "steps: [{action: slide, duration_s: 1.0, velocity_mm_s: [100, 0]}]\n")
    path = _write(tmp_path, "l.yaml", f"nodes:\n  - kind: camera\n    params: {{scene: {scene}, fps: 30, "
                                      "scene_check_frames: 2}\n    respawn: true\n    respawn_delay: 0.1\n")
    proc = spawn("launch", str(path), stdout=subprocess.PIPE, text=True)
    assert proc.wait(60.0) == CONFIG
    out = proc.stdout.read()
    assert out.count("[launch] started camera (camera)") == 1, out
    assert "[launch] camera cannot go on: " in out and "has left the skin, which spans +-12 mm (a configuration error, found while " \
           "running); stopping the launch" in out, out


_PRESS = "object: {shape: sphere}\nfps: 30\neffects: [normal]\nsteps: [{action: press, duration_s: 1.0, normal_N: 1.0}]\n"
_OFF_SKIN = ("object: {shape: sphere}\nfps: 30\ninitial: {normal_N: 1.0}\n"
             "steps: [{action: slide, duration_s: 1.0, velocity_mm_s: [100, 0]}]\n")


def test_a_launch_gives_its_nodes_the_scene_checks_it_made(bus_env: Bus, tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """The camera's scene check (600 frames' mechanics; 2.1 s for a twisting key) ran in the launcher as it read the
    launch file, then again in the camera at its start (2.4 s) and at every respawn (1.6 s). The launcher now
    gives its nodes the checks that passed (`nodes.launch_checks`, FV_CHECKED), which a camera whose scene has
    the same content skips."""
    from fv_algos.sim.scene import load_scene
    from nodes.sim_source import _check_key
    scene = _write(tmp_path, "press.yaml", _PRESS)
    _talker_wrapped(tmp_path, monkeypatch, 'echo "checked: $FV_CHECKED"; exec "$PY" "$@"')
    launch, out = _launch(tmp_path, f"nodes:\n  - {{kind: camera, params: {{scene: {scene}}}}}\n  - kind: talker\n")
    launch.start()
    try:
        assert _said(out, "[talker] checked: ", 15.0), out.getvalue()
    finally:
        launch.stop()
    given = re.search(r"\[talker\] checked: (.*)", out.getvalue()).group(1).split()
    assert _check_key(load_scene(scene), 600) in given, out.getvalue()


def test_a_camera_whose_scene_changed_since_its_launch_checked_it_checks_it_again(bus_env: Bus, tmp_path: Path) -> None:
    """A scene file edited between the launcher's check and the camera's start (or a respawn) is another scene:
    the camera checks it and refuses it."""
    scene = _write(tmp_path, "s.yaml", _PRESS)
    launch, out = _launch(tmp_path, f"nodes:\n  - {{kind: camera, params: {{scene: {scene}}}}}\n")
    scene.write_text(_OFF_SKIN)
    launch.start()
    try:
        assert launch.wait(60.0), out.getvalue()
    finally:
        code = launch.stop()
    assert code == CONFIG, out.getvalue()
    assert "camera cannot start: node 'camera': sim " in out.getvalue() and "frame 4 (t = 0.133 s): the object's centre (13.33, " \
        "0.00) mm has left the skin" in out.getvalue(), out.getvalue()


def _gelsight_mini_plugged_in() -> bool:
    try:
        find_v4l2_device("GelSight Mini")
    except SourceMissing:
        return False
    except SourceError:  # several
        return True
    return True


@pytest.mark.skipif(_gelsight_mini_plugged_in(), reason="a GelSight Mini is plugged in here")
def test_the_live_gelsight_mini_camera_waits_for_its_sensor_quietly(bus_env: Bus) -> None:
    """launch/gelsight_mini.yaml's camera with no sensor plugged in exits 75 (not ready) and is started
    again every second past START_TRIES, said once (the launch printed three lines a second: the same
    error, the exit, the start); the launcher's status says what it waits for."""
    camera = next(s for s in load_launch(REPO / "launch" / "gelsight_mini.yaml") if s.kind == "camera")
    out = io.StringIO()
    launch = Launch([camera], out, name="launch_mini")
    launch.start()
    try:
        status = wait_status("launch_mini", lambda st: st.counters.get("camera.respawns", 0) > START_TRIES,
                             timeout_s=30.0)
        assert not launch.wait(0.0), out.getvalue()
    finally:
        code = launch.stop()
    assert code == OK and status.state == "warn" and status.counters["waiting"] == 1
    assert re.fullmatch(r"camera waits \(\d+ s\): v4l2 'GelSight Mini': no camera of that name \(plugged in\?\)\. "
                        r"Devices: .*", status.message), status.message
    text = out.getvalue()
    assert text.count("[camera] fv node: not ready: v4l2 'GelSight Mini': no camera of that name") == 1, text
    assert text.count("[launch] started camera") == 1 and "exited with code" not in text, text
    assert text.count(f"[launch] camera is not ready (exit {TEMPFAIL}): starting it again every 1 s until it is up, "
                      "without repeating its output") == 1, text


def _talker_script(folder: Path, shell: str) -> Path:
    """A python for a launch: a script that runs the talker node (and its spare) with `shell` (sh: "$@"
    the python arguments, $PY the python) and anything else as before."""
    script = _write(folder, "python", f'#!/bin/sh\nPY={sys.executable}\ncase "$*" in *"node talker"*) {shell};; '
                                      'esac\nexec "$PY" "$@"\n')
    script.chmod(0o755)
    return script


def _talker_wrapped(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, shell: str) -> None:
    """The launch's python (sys.executable) becomes `_talker_script(tmp_path, shell)`."""
    monkeypatch.setattr(sys, "executable", str(_talker_script(tmp_path, shell)))


def _said(out: io.StringIO, text: str, timeout_s: float) -> bool:
    """Poll the launch's output until it holds `text`."""
    return poll_until(lambda: text in out.getvalue(), timeout_s, period_s=0.05)


def test_a_node_not_ready_is_up_once_what_it_waits_for_comes(bus_env: Bus, tmp_path: Path,
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """A talker that is not ready (exit 75) until a file appears (a camera plugged in): said once, then
    the launcher says when it is up, and its output is heard again."""
    plugged = tmp_path / "plugged"
    _talker_wrapped(tmp_path, monkeypatch,
                    f'[ -e {plugged} ] || {{ echo "fv node: not ready: no sensor"; exit {TEMPFAIL}; }}')
    launch, out = _launch(tmp_path, "nodes:\n  - {kind: talker, respawn: true, respawn_delay: 0.1}\n")
    launch.start()
    try:
        wait_status("launch_l", lambda st: st.counters.get("talker.respawns", 0) > START_TRIES, timeout_s=15.0)
        plugged.touch()
        pid = wait_status("talker", timeout_s=15.0).pid
        assert _said(out, f"[launch] talker is up (pid {pid}) after waiting", 5.0), out.getvalue()
    finally:
        assert launch.stop() == OK
    text = out.getvalue()
    assert text.count("[talker] fv node: not ready: no sensor") == 1 and text.count("[launch] started talker") == 1


def test_a_configuration_error_after_the_node_has_reported_is_respawned_as_before(
        bus_env: Bus, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Exit 2 ends a node's respawns only before its first NodeStatus: a talker that ran, then exits 2,
    is respawned past START_TRIES."""
    _talker_wrapped(tmp_path, monkeypatch, "exec \"$PY\" -c 'import os, sys, threading; from nodes.cli import main; "
                                           "threading.Timer(1.5, os._exit, [2]).start(); main(sys.argv[3:])' \"$@\"")
    launch, out = _launch(tmp_path, "nodes:\n  - {kind: talker, respawn: true, respawn_delay: 0.1}\n")
    launch.start()
    try:
        wait_status("launch_l", lambda st: st.counters.get("talker.respawns", 0) >= START_TRIES, timeout_s=30.0)
        assert not launch.wait(0.0), out.getvalue()
    finally:
        assert launch.stop() == OK
    assert f"talker exited with code 2; respawn {START_TRIES} in 0.1 s" in out.getvalue()


def test_ctrl_c_stops_everything_within_2s(bus_env: Bus, spawn) -> None:
    proc = spawn("launch", str(REPO / "launch" / "demo.yaml"), "rate_hz:=20", stdout=subprocess.PIPE, text=True)
    wait_status("listener", lambda st: st.counters.get("received", 0) > 0, timeout_s=8.0)
    family = children_of(proc.pid)
    assert len(family) == 3, f"expected forwarder + 2 nodes, found {family}"
    t0 = time.monotonic()
    proc.send_signal(signal.SIGINT)
    proc.wait(5.0)
    stop_s = time.monotonic() - t0
    leftover = [p for p in family if process_alive(p)]
    assert not leftover and stop_s < 2.0, f"stopped in {stop_s:.2f} s, left {leftover}"
    output = proc.stdout.read()
    assert "[listener] INFO: SlipState seq=" in output and "[listener] [listener]" not in output
    assert ping(bus_env.address) is None


def _gone(pids: list[int], timeout_s: float) -> list[int]:
    """Poll until none of `pids` is alive; the ones still alive after `timeout_s`."""
    poll_until(lambda: not any(map(process_alive, pids)), timeout_s, period_s=0.05)
    return [p for p in pids if process_alive(p)]


def _kill(pids: list[int]) -> None:
    """SIGKILL whichever of `pids` still runs (a test's leftovers)."""
    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def _cmdline(pid: int) -> list[str]:
    """The command line of process `pid` ([""] once it has gone)."""
    try:
        with open(f"/proc/{pid}/cmdline") as f:
            return f.read().split("\0")
    except FileNotFoundError:
        return [""]


def _waits_for_takeover(pid: int) -> bool:
    """True when process `pid` waits for SIGUSR1 as a standby spare does (`nodes.core_commands`): asleep in
    sigtimedwait, or between two of its waits with SIGUSR1 blocked. While sigtimedwait waits, the kernel lists the
    signals it waits for as unblocked, so the mask alone almost never showed a waiting spare."""
    with open(f"/proc/{pid}/wchan") as f:
        if "sigtimedwait" in f.read():
            return True
    with open(f"/proc/{pid}/status") as f:
        mask = next(line.split()[1] for line in f if line.startswith("SigBlk:"))
    return bool(int(mask, 16) & (1 << (signal.SIGUSR1 - 1)))


def test_sighup_stops_everything_as_sigterm_does(bus_env: Bus, spawn) -> None:
    """Closing the launch's terminal (SIGHUP) killed the launcher alone: the forwarder and nodes ran on,
    and the next launch on that bus was refused for the namesakes they left."""
    proc = spawn("launch", str(REPO / "launch" / "demo.yaml"), "rate_hz:=20")
    family: list[int] = []
    try:
        wait_status("listener", lambda st: st.counters.get("received", 0) > 0, timeout_s=15.0)
        family = children_of(proc.pid)
        assert len(family) == 3, f"expected forwarder + 2 nodes, found {family}"
        proc.send_signal(signal.SIGHUP)
        assert proc.wait(10.0) == 0
        leftover = _gone(family, 5.0)
        assert not leftover, f"left running after SIGHUP: {leftover}"
        assert ping(bus_env.address) is None
    finally:
        _kill(family)


@contextmanager
def _launcher(python: Path, path: Path) -> Iterator[subprocess.Popen]:
    """`fv launch path` in its own process (group), its nodes run with `python` (`sys.executable` or a `_talker_script`);
    killed at the end."""
    code = "import sys; sys.executable = sys.argv.pop(1); from nodes.cli import main; sys.exit(main(sys.argv[1:]))"
    proc = subprocess.Popen([sys.executable, "-c", code, str(python), "launch", str(path)], cwd=REPO,
                            start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        yield proc
    finally:
        kill_group(proc)


def _descendants(pid: int) -> list[int]:
    """The processes `pid` started, their children, and so on."""
    found, todo = [], [pid]
    while todo:
        children = children_of(todo.pop())
        found += children
        todo += children
    return found


SLEEPER = 'sleep 60 >/dev/null 2>&1 & exec "$PY" "$@"'  # the talker (and its spare) with a child of its own
# a talker that starts after delay_s, then imports for 60 s
SLOW_START = ("exec \"$PY\" -c 'import sys, time; time.sleep(float(sys.argv[1])); import nodes.registry as r; "
              "r.node_class = lambda kind, load=r.node_class: (time.sleep(60), load(kind))[1]; "
              "from nodes.cli import main; main(sys.argv[4:])' {delay_s} \"$@\"")


def test_every_process_of_a_launch_stops_when_its_launcher_is_killed(bus_env: Bus, tmp_path: Path) -> None:
    """A launcher killed with SIGKILL cannot stop what it started (each node in its own session): the nodes,
    the standby spare, their children and the forwarder get SIGTERM from the kernel and stop, cleanly: the
    recorder's bag is finished. Before, the forwarder and the nodes' children ran on for good."""
    bag = tmp_path / "bag"
    path = _write(tmp_path, "l.yaml", "nodes:\n"
                                      "  - {kind: talker, params: {rate_hz: 50}, respawn: true, standby: true}\n"
                                      "  - {kind: listener}\n"
                                      f"  - {{kind: bag_record, params: {{output: '{bag}', topics: [/chatter]}}}}\n")
    family: list[int] = []
    try:
        with _launcher(_talker_script(tmp_path, SLEEPER), path) as proc:
            wait_status("listener", lambda st: st.counters.get("received", 0) > 0, timeout_s=20.0)
            wait_status("bag_record", lambda st: st.counters.get("recorded", 0) > 0, timeout_s=10.0)
            deadline = time.monotonic() + 20.0
            while time.monotonic() < deadline:
                family = _descendants(proc.pid)
                spares = [pid for pid in family if "--standby" in _cmdline(pid)]
                if len(family) == 7 and spares and _waits_for_takeover(spares[0]):
                    break
                time.sleep(0.05)
            sleeps = [pid for pid in family if _cmdline(pid)[0] == "sleep"]
            assert len(family) == 7 and spares and len(sleeps) == 2, \
                f"expected the forwarder, 3 nodes, a spare and 2 sleeps, found {[_cmdline(p)[:4] for p in family]}"
            proc.kill()
            proc.wait(5.0)
            leftover = _gone(family, 10.0)
        assert not leftover, f"left running after the launcher was killed: {[_cmdline(p)[:4] for p in leftover]}"
        assert ping(bus_env.address) is None
        reader = BagReader(bag)
        assert reader.message_count > 0 and RECORDING_END_META in reader.metadata()
    finally:
        _kill(family)


def test_the_children_of_a_killed_node_are_stopped(bus_env: Bus, tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """A node killed outright (SIGKILL, the OOM killer) cannot end its children: the launcher ends its
    process group when it sees it exit. Before, they ran on, past the launch's end."""
    _talker_wrapped(tmp_path, monkeypatch, SLEEPER)
    launch, _ = _launch(tmp_path, "nodes:\n  - {kind: talker, respawn: true, respawn_delay: 0.1}\n")
    launch.start()
    sleeps: list[int] = []
    try:
        wait_status("talker", timeout_s=20.0)
        talker = launch.pid("talker")
        sleeps = [pid for pid in children_of(talker) if _cmdline(pid)[0] == "sleep"]
        assert sleeps, f"the talker has no sleep child: {[_cmdline(p)[:4] for p in children_of(talker)]}"
        os.kill(talker, signal.SIGKILL)
        leftover = _gone(sleeps, 5.0)
        assert not leftover, f"the killed talker's child ran on: {leftover}"
    finally:
        launch.stop()
        _kill(sleeps)


# a talker whose python loads nodes.cli (and installs its stop handlers) only once the file $1 exists
WAITS_FOR_FILE = ("exec \"$PY\" -c 'import os, sys, time\nwhile not os.path.exists(sys.argv[1]): time.sleep(0.01)\n"
                  "from nodes.cli import main; sys.exit(main(sys.argv[4:]))' {go} \"$@\"")


def test_a_node_stopped_before_it_takes_sigterm_is_sent_it_once_it_does(bus_env: Bus, tmp_path: Path,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """A node started just before a stop (a first start, a respawn, a spare), Python still loading nodes.cli, was
    ended by the launcher's SIGTERM (-15): the launcher now sends it once the node has its stop handler
    (here: once the file `go` exists), and the node stops cleanly."""
    go = tmp_path / "go"
    _talker_wrapped(tmp_path, monkeypatch, WAITS_FOR_FILE.format(go=go))
    monkeypatch.setattr("nodes.launcher.GRACE_S", 60.0)  # no kill before the handler, however loaded the host
    launch, out = _launch(tmp_path, "nodes:\n  - {kind: talker}\n")
    launch.start()
    talker = launch.children[0].proc
    stopper = threading.Thread(target=launch.stop)
    stopper.start()
    try:
        stopper.join(0.5)
        assert stopper.is_alive() and talker.poll() is None, (talker.returncode, out.getvalue())
    finally:
        go.touch()
        stopper.join(60.0)
    assert talker.returncode in (OK, 128 + signal.SIGTERM), (talker.returncode, out.getvalue())


def test_a_node_that_never_takes_sigterm_is_sent_it_before_the_grace_ends_not_killed(
        bus_env: Bus, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A node without its stop handler all through the grace time (its Python never loads nodes.cli here) is sent
    SIGTERM `TERM_WAIT_S` before the grace time ends, which ends it: sent at the end, it was killed at once and said
    as one that "did not stop"."""
    _talker_wrapped(tmp_path, monkeypatch, WAITS_FOR_FILE.format(go=tmp_path / "never"))
    launch, out = _launch(tmp_path, "nodes:\n  - {kind: talker}\n")
    launch.start()
    talker = launch.children[0].proc
    launch.stop()
    assert talker.returncode == -signal.SIGTERM, (talker.returncode, out.getvalue())
    assert "killed" not in out.getvalue() and "was ended by a signal: Terminated" in out.getvalue(), out.getvalue()


# a "talker" that a SIGTERM ends by the signal
ENDED_BY_SIGTERM = ("exec \"$PY\" -c 'import os, signal, time\nsignal.signal(signal.SIGTERM, lambda *_: "
                    "(signal.signal(signal.SIGTERM, signal.SIG_DFL), os.kill(os.getpid(), signal.SIGTERM)))\n"
                    "time.sleep(60)'")


@pytest.mark.parametrize("debug", [False, True])
def test_the_stop_says_how_each_node_ended(bus_env: Bus, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                           caplog: pytest.LogCaptureFixture, debug: bool) -> None:
    """At its stop the launcher says each node's exit code with `-v` (debug), and one ended by a signal at any
    level (as one killed after the grace time). Before, it said nothing of how they ended."""
    _talker_wrapped(tmp_path, monkeypatch, ENDED_BY_SIGTERM)
    caplog.set_level(logging.DEBUG if debug else logging.INFO, logger="launch")
    launch, out = _launch(tmp_path, "nodes:\n  - {kind: talker}\n  - {kind: listener}\n")
    launch.start()
    try:
        wait_status("listener", timeout_s=20.0)
        talker, listener = launch.pid("talker"), launch.pid("listener")
    finally:
        launch.stop()
    text = out.getvalue()
    assert f"[launch] talker pid {talker} was ended by a signal: Terminated (exit -15)" in text, text
    assert (f"[launch] listener pid {listener} exited with code 0" in text) == debug, text


@pytest.mark.parametrize("delay_s", [0, 3])
def test_nodes_still_starting_stop_when_their_launcher_is_killed(bus_env: Bus, tmp_path: Path, delay_s: int) -> None:
    """A node still importing (a slip detector's torch) when its launcher was killed stopped only once it
    spun (here never: its import takes 60 s); one whose process began its start after the launcher died
    (delay_s) is told at its start."""
    path = _write(tmp_path, "l.yaml", "nodes:\n  - {kind: talker}\n  - {kind: listener}\n")
    family: list[int] = []
    try:
        with _launcher(_talker_script(tmp_path, SLOW_START.format(delay_s=delay_s)), path) as proc:
            wait_status("listener", timeout_s=20.0)
            family = _descendants(proc.pid)
            assert any("talker" in _cmdline(pid) for pid in family), [_cmdline(p)[:4] for p in family]
            proc.kill()
            proc.wait(5.0)
            leftover = _gone(family, delay_s + 10.0)
        assert not leftover, f"left running after the launcher was killed: {[_cmdline(p)[:4] for p in leftover]}"
    finally:
        _kill(family)


@pytest.mark.parametrize("kind, params", [("camera", {"source": "sim"}), ("tracker", {}), ("interpolator", {}),
                                          ("slip_detector", {"model": "gelsight_online"}), ("slip_detector", {}),
                                          ("viewer", {"port": 0})])
def test_a_pipeline_node_in_a_namespace_uses_its_topics_there(bus_env: Bus, kind: str, params: dict) -> None:
    """What `namespace: left` on an include relies on: every topic a pipeline node publishes or
    subscribes moves under /left, but the grasp-wide /tracker/reset and the launch-wide /status."""
    from nodes.registry import node_class
    node = node_class(kind)(f"left_{kind}", params, namespace="left")
    try:
        node.setup()
        status = node.status()
    finally:
        node.close()
    topics = {topic for topic, _ in status.publishes + status.subscribes}
    assert topics - {"/tracker/reset", "/status"} and all(
        t.startswith("/left/") for t in topics - {"/tracker/reset", "/status"}), topics


def test_a_spare_that_cannot_get_ready_is_started_less_and_less_often(tmp_path: Path) -> None:
    """A standby spare whose start failed (exit 2: e.g. its model file gone since the node started) was
    started again every second for good, its error echoed each time. Spares in a row that exit before they
    are ready now wait twice as long each (1, 2, 4 ... s, at most SPARE_RETRY_MAX_S); a ready one resets it."""
    import io
    import subprocess
    import sys

    from nodes.launcher import SPARE_RETRY_MAX_S, Launch
    path = _write(tmp_path, "l.yaml", "nodes:\n  - kind: talker\n    respawn: true\n    respawn_delay: 0.1\n"
                                      "    standby: true\n")
    out = io.StringIO()
    launch = Launch.from_file(path, output=out)
    child = launch.children[0]
    failed = subprocess.Popen([sys.executable, "-c", "raise SystemExit(2)"])
    failed.wait()
    child.proc = failed  # any process: the node is there, so spares are due
    spawned: list[float] = []

    def spawn(c) -> None:
        spawned.append(now)
        c.spare, c.spare_ready, c.spare_at = failed, False, None

    launch._spawn_spare = spawn
    now, waits = 0.0, []
    child.spare = failed
    for _ in range(9):
        launch._watch_spare(child, now)  # the spare has exited: the next one is scheduled
        waits.append(child.spare_at - now)
        now = child.spare_at
        launch._watch_spare(child, now)  # due: started
    assert waits == [1.0, 2.0, 4.0, 8.0, 16.0, 32.0, SPARE_RETRY_MAX_S, SPARE_RETRY_MAX_S, SPARE_RETRY_MAX_S]
    assert len(spawned) == 9 and "exited with code 2 before it was ready (3 in a row); next spare in 4 s" in out.getvalue()
    child.spare_ready = True  # a spare that got ready, then exited (its node took it over, or it was killed)
    launch._watch_spare(child, now)
    assert child.spare_failures == 0 and child.spare_at - now == 1.0
