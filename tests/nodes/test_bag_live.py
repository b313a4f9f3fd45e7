"""Bags on a live bus: record, kill -9 and recover, play with timing, round trip,
flow-controlled fast replay, pause, the replay launch file and `fv bench bag`.

Each test has its own forwarder on a private IPC path; every process started is killed
by a finalizer.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable, Iterator

import mcap.reader
import numpy as np
import pytest
import yaml

import msgs
from msgs import CameraInfo, Image, MarkerArray, SlipState, Unanswered
from nodes.bag.reader import BagError, BagReader, read_bag
from nodes.bag.commands import parse_size
from nodes.bag.recorder import BagRecord
from nodes.bag.player import BagPlay
from nodes.bag.recover import recover, recover_in_place
from nodes.bag.writer import BagWriter
from nodes.process_stop import stop_process
from nodes.bus import PUB_HWM, PublisherSocket, TopicReader
from nodes.cli import main
from nodes.endpoints import BUS_ENV, BusAddress, bus_address
from nodes.forwarder import ensure_forwarder
from nodes.launch_file import load_launch
from nodes.node import Node
from nodes.params import ParamError
from tests.nodes.conftest import hangup_as_from_a_terminal, poll_until, wait_for, wait_status
from tests.nodes.test_bag import T0_NS, bag_chunks, frames_of, sample_messages, write_bag

REPO = Path(__file__).resolve().parents[2]
Spawn = Callable[..., subprocess.Popen]


def stop(proc: subprocess.Popen, sig: int = signal.SIGINT) -> int:
    return stop_process(proc, sig, timeout_s=20.0)


@pytest.fixture
def bus(monkeypatch: pytest.MonkeyPatch) -> Iterator[BusAddress]:
    """A private forwarder; FV_BUS points at it for this test and its subprocesses."""
    folder = tempfile.mkdtemp(prefix="fvbag", dir="/tmp")
    address = bus_address(f"ipc://{folder}/bus")
    monkeypatch.setenv(BUS_ENV, address.url)
    forwarder = ensure_forwarder(address)
    yield address
    stop(forwarder, signal.SIGTERM)
    shutil.rmtree(folder, ignore_errors=True)


@pytest.fixture
def spawn(bus: BusAddress) -> Iterator[Spawn]:
    """spawn(*fv_args, **popen_kwargs) starts `python -m nodes.cli ...` on the test's bus (stderr kept)."""
    procs: list[subprocess.Popen] = []

    def start(*args: str, **popen_kwargs: object) -> subprocess.Popen:
        streams = {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE, "preexec_fn": hangup_as_from_a_terminal,
                   **popen_kwargs}
        proc = subprocess.Popen([sys.executable, "-m", "nodes.cli", *args], cwd=REPO, stdin=subprocess.DEVNULL,
                                text=True, **streams)
        procs.append(proc)
        return proc

    yield start
    for proc in procs:
        stop(proc, signal.SIGKILL)


def wait_subscribed(pub: PublisherSocket, topics: list[str], timeout_s: float = 20.0) -> None:
    pub.wait_connected(timeout_s)
    wait_for(lambda: all(pub.has_subscribers(t) for t in topics), timeout_s, f"subscribers to {topics}",
             period_s=0.02)


def in_thread(node) -> threading.Thread:
    thread = threading.Thread(target=node.spin, kwargs={"install_signals": False}, daemon=True)
    thread.start()
    return thread


@contextlib.contextmanager
def recording(node: BagRecord, bus: BusAddress) -> Iterator[PublisherSocket]:
    """``node`` recording in a thread, with a publisher of /a it has subscribed to; both ended after."""
    thread = in_thread(node)
    pub = PublisherSocket("src", bus)
    try:
        wait_subscribed(pub, ["/a"])
        yield pub
    finally:
        pub.close()
        node.stop()
        thread.join(10)


def play_to_the_end(bus: BusAddress, params: dict, topics: list[str],
                    remap: dict[str, str] | None = None) -> tuple[BagPlay, list]:
    """A `BagPlay` of ``params`` (and ``remap``) run to its end in a thread, and what came on ``topics``
    meanwhile (the items of a `TopicReader` subscribed before it started, until 2 s without one)."""
    with TopicReader(topics, bus) as reader:
        node = BagPlay("play", params, remap=remap, address=bus)
        thread = in_thread(node)
        got = []
        while (item := reader.recv(2.0)) is not None:
            got.append(item)
        thread.join(5)
    return node, got


def test_a_player_without_flow_control_waits_end_wait_s_after_its_last_message(bus: BusAddress,
                                                                               tmp_path: Path) -> None:
    """A replay launch ends with its player: a pair replay's fusion, stopped as the player ended on its last
    frame, had not voted one finger's last state in 2 of 6 runs. The player now waits `end_wait_s` (the
    replay launch files' 1 s) after the bag's last message before it ends."""
    write_bag(tmp_path / "b", sample_messages(5, np.random.default_rng(3)))
    with TopicReader(["/slip"], bus) as reader:
        node = BagPlay("play", {"path": str(tmp_path / "b"), "fast": True, "topics": ["/slip"], "end_wait_s": 0.8,
                                "wait_for_subscribers": False}, address=bus)
        thread = in_thread(node)
        for _ in range(5):
            assert reader.recv(5.0) is not None
        last_s = time.monotonic()
        thread.join(10)
    assert time.monotonic() - last_s >= 0.7 and node.error is None


def test_kill_9_then_recover_keeps_every_completed_chunk(bus: BusAddress, spawn: Spawn, tmp_path: Path) -> None:
    flush_s = 0.2
    rec = spawn("bag", "record", "/camera/image", "/slip", "-o", str(tmp_path / "crash"), "--chunk-size", "64K",
                "--flush-period", str(flush_s))
    pub = PublisherSocket("cam", bus)
    rng = np.random.default_rng(3)
    sent: list[tuple[float, np.ndarray]] = []  # (monotonic publish time, image) by seq
    try:
        wait_subscribed(pub, ["/camera/image", "/slip"])
        kill_at = time.monotonic() + 1.5
        killed = None
        while time.monotonic() < kill_at + 0.3:
            data = rng.integers(0, 255, (120, 160), dtype=np.uint8)
            sent.append((time.monotonic(), data))
            pub.publish("/camera/image", Image(stamp_ns=len(sent), data=data))
            pub.publish("/slip", SlipState(stamp_ns=len(sent)))
            if killed is None and time.monotonic() >= kill_at:
                rec.kill()
                killed = time.monotonic()
            time.sleep(0.005)
    finally:
        pub.close()
    rec.wait(5)
    file = tmp_path / "crash" / "crash_0.mcap"
    with pytest.raises(BagError, match="recover"):
        BagReader(file)
    report = recover(file, tmp_path / "fixed.mcap")
    bag = BagReader(tmp_path / "fixed.mcap")
    images = [m for m in bag.messages(["/camera/image"])]
    seqs = [m.sequence for m in images]
    assert seqs == list(range(len(seqs)))  # a gap-free prefix of what was published
    assert [m.sequence for m in bag.messages(["/slip"])] == list(range(bag.topics()["/slip"].count))
    surely_flushed = sum(t < killed - flush_s - 0.1 for t, _ in sent)
    sent_before_kill = sum(t < killed for t, _ in sent)
    assert surely_flushed <= len(seqs) <= sent_before_kill
    assert report.messages == bag.message_count and not report.complete  # lost_b may be 0: a cut between chunks
    for m in images[::25]:
        np.testing.assert_array_equal(m.decode().data, sent[m.sequence][1])


def test_a_recorder_whose_terminal_closes_finishes_its_bag(bus: BusAddress, spawn: Spawn, tmp_path: Path) -> None:
    """SIGHUP (the terminal closed, an SSH session dropped) killed the recorder outright: its bag was
    unfinished and needed `fv bag recover`. Every node now stops on it as on Ctrl-C."""
    rec = spawn("bag", "record", "/slip", "-o", str(tmp_path / "hup"))
    pub = PublisherSocket("cam", bus)
    try:
        wait_subscribed(pub, ["/slip"])
        for k in range(20):
            pub.publish("/slip", SlipState(stamp_ns=k + 1))
        time.sleep(0.5)
    finally:
        pub.close()
    assert stop(rec, signal.SIGHUP) == 0
    assert BagReader(tmp_path / "hup" / "hup_0.mcap").topics()["/slip"].count == 20


def test_a_full_disk_ends_the_recording_with_the_command_that_keeps_it(bus: BusAddress, spawn: Spawn,
                                                                       tmp_path: Path) -> None:
    """A file size limit (what a full disk does to the recorder): one error naming the file and
    `fv bag recover`, no traceback, and the recovered bag holds what was flushed. It used to end in a
    thread's traceback with no summary and no advice."""
    import resource

    def limit_file_size() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (300_000, 300_000))

    rec = spawn("bag", "record", "/camera/image", "-o", str(tmp_path / "full"), "--chunk-size", "32K",
                "--flush-period", "0.1", "--compression", "none", preexec_fn=limit_file_size)
    pub = PublisherSocket("cam", bus)
    rng = np.random.default_rng(4)
    try:
        wait_subscribed(pub, ["/camera/image"])
        poll_until(lambda: rec.poll() is not None, 20.0, between=lambda: pub.publish(
            "/camera/image", Image(stamp_ns=time.time_ns(), data=rng.integers(0, 255, (120, 160), np.uint8))))
    finally:
        pub.close()
    assert rec.wait(10) == 1
    err = rec.stderr.read()
    file = tmp_path / "full" / "full_0.mcap"
    assert f"run `fv bag recover {file}`" in err and "Traceback" not in err, err
    report = recover(file, tmp_path / "kept.mcap")
    assert report.messages > 5 and BagReader(tmp_path / "kept.mcap").message_count == report.messages


# Timing of a played recording, as the player sent it (its publisher's calls, timed in the test's process): the
# times it was recorded again at add the forwarder's and the recorder's delays, which beside four busy loops and
# other work (load average 10 on 2 cores) put whole fifths of the recording 50 to 150 ms late, a timed player or
# not. Load delays a send (the player wakes late), never hastens it: against the player's schedule, a message's
# send time less its recorded time is a constant plus its lateness, which `lateness_ms` gives against the least late
# message. The least late message of each fifth of the recording (its floor) goes on time on a timed player, as long
# as one message a fifth (280 ms) is not held up. A player off the schedule sends early somewhere, which lifts the
# floors elsewhere: played evenly spaced, the 4 to 25 ms intervals drawn here put a floor 36 ms up, played 2 % fast
# 22 ms, as fast as possible 1,086 ms (computed from the intervals; measured: 22 and 968 ms). The median bounds a
# player that keeps to the schedule only now and then (one that looks at its clock every 100 ms: 52 ms). The player
# as it is, 5 runs beside two busy loops and other work (load average 5 to 7): highest floor 0.01 to 0.04 ms, median
# 0.05 to 1.7 ms; 6 runs beside five (load average 7 to 9): 0.01 to 0.15 ms and 0.06 to 3.5 ms. Beside two busy loops
# its times as recorded again were off by a median interval of 1.2 to 7.5 ms, which failed the 2 ms bound this test
# held on them before.
FLOOR_STRETCHES = 5
MAX_FLOOR_MS = 10.0
MAX_MEDIAN_LATE_MS = 25.0


def lateness_ms(recorded_ns: list[int], played_ns: list[int]) -> np.ndarray:
    """(N,) ms: how late each of N messages was played, against the least late one (0), from its recorded
    log time and the time it was played at (any clock)."""
    offset = np.asarray(played_ns, np.int64) - np.asarray(recorded_ns, np.int64)
    return (offset - offset.min()) / 1e6


def test_record_play_record_round_trip_with_recorded_timing(bus: BusAddress, spawn: Spawn, tmp_path: Path,
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(5)
    dt_ns = list(rng.integers(4_000_000, 25_000_000, 100))
    original = write_bag(tmp_path / "one", sample_messages(100, rng, (120, 160), dt_ns))
    rec = spawn("bag", "record", "-a", "-x", "^/status$", "-o", str(tmp_path / "two"))
    sent_ns: dict[str, list[int]] = {}
    publish_raw = PublisherSocket.publish_raw

    def timed(pub: PublisherSocket, topic: str, *args: object) -> None:
        sent_ns.setdefault(topic, []).append(time.monotonic_ns())
        publish_raw(pub, topic, *args)

    monkeypatch.setattr(PublisherSocket, "publish_raw", timed)
    node = BagPlay("play", {"path": str(original.output), "subscriber_timeout_s": 20.0}, address=bus)
    thread = in_thread(node)
    thread.join(60)
    assert not thread.is_alive() and node.error is None
    assert stop(rec) == 0
    one, two = BagReader(original.output), BagReader(tmp_path / "two")
    a, b = list(one.messages()), list(two.messages())
    key = lambda m: (m.topic, m.sequence)  # noqa: E731
    assert sorted((key(m), m.payload, m.publish_time_ns, m.node, m.latched) for m in a) == \
           sorted((key(m), m.payload, m.publish_time_ns, m.node, m.latched) for m in b)
    assert {t: i.latched for t, i in two.topics().items()}["/camera/info"]
    assert {topic: len(times) for topic, times in sent_ns.items()} == {t: i.count for t, i in one.topics().items()}
    for topic in ("/camera/image", "/slip"):
        late_ms = lateness_ms([m.log_time_ns for m in a if m.topic == topic], sent_ns[topic])
        floors = [round(float(part.min()), 2) for part in np.array_split(late_ms, FLOOR_STRETCHES)]
        assert max(floors) < MAX_FLOOR_MS, f"{topic}: the earliest message of each stretch went {floors} ms late"
        assert np.median(late_ms) < MAX_MEDIAN_LATE_MS, f"{topic}: messages went {late_ms} ms late"


def _answer_slowly(bus: BusAddress, image_topic: str, answer_topic: str, work_s: float, seen: list[int],
                   done: threading.Event) -> threading.Thread:
    """A started thread: a depth-2 subscriber of ``image_topic`` that appends each frame's seq to ``seen`` and
    answers it on ``answer_topic`` (a SlipState of the frame's stamp) after ``work_s``, until ``done``."""
    def answer() -> None:
        pub = PublisherSocket(f"slow{answer_topic.replace('/', '_')}", bus)
        with TopicReader([image_topic], bus, hwm=2) as reader:
            while not done.is_set():
                raw = reader.recv_raw(0.1)
                if raw is not None:
                    header = msgs.decode_header(raw[3][0])
                    seen.append(header["seq"])
                    time.sleep(work_s)
                    pub.publish(answer_topic, SlipState(stamp_ns=header["stamp_ns"]))
        pub.close()

    thread = threading.Thread(target=answer, daemon=True)
    thread.start()
    return thread


def test_fast_play_with_sync_never_overruns_a_slow_consumer(bus: BusAddress, spawn: Spawn, tmp_path: Path) -> None:
    n, work_s = 60, 0.01
    write_bag(tmp_path / "b", sample_messages(n, np.random.default_rng(1)))
    seen: list[int] = []
    done = threading.Event()
    consumer = _answer_slowly(bus, "/camera/image", "/slip", work_s, seen, done)
    try:
        play = spawn("bag", "play", str(tmp_path / "b"), "--fast", "--topics", "/camera/image", "--sync-topic",
                     "/slip", "--wait-timeout", "20")
        assert play.wait(60) == 0
    finally:
        done.set()
        consumer.join(5)
    log = play.stderr.read()
    assert seen == list(range(n)), log
    assert "sync timeouts 0" in log
    fps = float(log.split(" frames/s")[0].rsplit(": ", 1)[1])
    assert 10 < fps < 1 / work_s * 1.1  # paced by the consumer, not by the bag's 100 Hz


class EveryOtherFrame(Node):
    """A pipeline stage that answers the frames of even seq on `slip` after `work_s` and leaves the others
    unanswered, noting each frame's seq in `seen`; it keeps only the latest frame, as a tracker does."""

    def setup(self) -> None:
        self.seen: list[int] = []
        self.slip = self.publisher("slip", SlipState)
        self.subscribe("camera/image", Image, self.on_image, depth=1, answered_by=self.slip)

    def on_image(self, msg: Image) -> None:
        self.seen.append(msg.seq)
        time.sleep(0.01)
        if msg.seq % 2 == 0:
            self.slip.publish(SlipState(stamp_ns=msg.stamp_ns))


def test_fast_play_sends_the_next_frame_once_a_stage_leaves_one_unanswered(bus: BusAddress, spawn: Spawn,
                                                                         tmp_path: Path) -> None:
    """A synced fast play waited sync_timeout_s (2 s) for each frame the pipeline leaves unanswered (a tracker's
    frames before its reference, a window model's fields while its window fills): 9 of them, 18 s, began each
    replay of a sim session (`_replays_as_live`). A stage's `unanswered` notice (in its namespace: /left/unanswered
    for /left/slip) now lets the next frame go at once, and none is lost."""
    n = 30
    write_bag(tmp_path / "b", sample_messages(n, np.random.default_rng(4)))
    node = EveryOtherFrame("stage", namespace="left")
    thread = in_thread(node)
    try:
        wait_status("stage", timeout_s=20.0)
        play = spawn("bag", "play", str(tmp_path / "b"), "--fast", "--topics", "/camera/image", "--remap",
                     "/camera/image:=/left/camera/image", "--sync-topic", "/left/slip", "--wait-timeout", "20")
        assert play.wait(60) == 0
    finally:
        node.stop()
        thread.join(5)
    log = play.stderr.read()
    assert node.seen == list(range(n)), log
    assert "sync timeouts 0" in log, log


def test_a_play_without_frames_counts_its_messages_once(bus: BusAddress, spawn: Spawn, tmp_path: Path) -> None:
    """`fv bag play --topics /slip` (no frames to count) ended with "played 100 messages (100 messages) in ...:
    ... frames/s"."""
    original = write_bag(tmp_path / "one", sample_messages(100, np.random.default_rng(5)))
    play = spawn("bag", "play", str(original.output), "--topics", "/slip", "--rate", "10",
                 "--no-wait-for-subscribers")  # nobody subscribes: waiting for one only delays the summary
    assert play.wait(60) == 0
    summary = play.stderr.read()
    assert "played 100 messages in " in summary and " messages/s" in summary and "(100" not in summary, summary


def test_fast_play_syncs_each_finger_on_its_own_answers(bus: BusAddress, spawn: Spawn, tmp_path: Path) -> None:
    """Two cameras' frames interleaved in one bag (one pipeline per finger): each waits for its own finger's
    answer, so neither slow consumer loses a frame, the slower one (30 ms) paces the whole."""
    n, rng = 40, np.random.default_rng(2)
    sides = ("/left", "/right")
    messages = [(f"{side}/camera/image", False, Image(stamp_ns=T0_NS + i * 10_000_000 + k,
                                                      data=rng.integers(0, 255, (24, 32), dtype=np.uint8)),
                 T0_NS + i * 10_000_000 + k) for i in range(n) for k, side in enumerate(sides)]
    write_bag(tmp_path / "b", messages)
    seen: dict[str, list[int]] = {side: [] for side in sides}
    done = threading.Event()
    consumers = [_answer_slowly(bus, f"{side}/camera/image", f"{side}/slip", work_s, seen[side], done)
                 for side, work_s in zip(sides, (0.005, 0.03))]
    try:
        play = spawn("bag", "play", "--fast", "--sync-on", "/left/camera/image", "--sync-on", "/right/camera/image",
                     "--sync-topic", "/left/slip", "--sync-topic", "/right/slip", "--wait-timeout", "20",
                     str(tmp_path / "b"))
        assert play.wait(60) == 0
    finally:
        done.set()
        for consumer in consumers:
            consumer.join(5)
    log = play.stderr.read()
    assert seen == {side: list(range(n)) for side in sides}, log
    assert "sync timeouts 0" in log and "(80 on /left/camera/image, /right/camera/image)" in log
    fps = float(log.split(" frames/s")[0].rsplit(": ", 1)[1])
    assert fps < 2 / 0.03 * 1.1  # each right frame waited for its 30 ms answer


ANSWERED = [2, 3, 5, 6, 8, 9]  # of frames 0 .. 9: 0 before the tracker's reference, 1, 4 and 7 dropped live


def _live_session(folder: Path, frame_index: Callable[[int], int], notices: bool,
                  reference_ns: int | None) -> None:
    """A bag of a live run: frames 0 .. 9 on /camera/image (frame_index(i) each), /markers answering ANSWERED, the
    tracker's /markers/reference (latched) stamped at T0_NS + ``reference_ns`` when given, and with ``notices``
    the recorded `unanswered` notices: the tracker's of frame 0, another stage's of frame 4."""
    stamp = [T0_NS + i * 10_000_000 for i in range(10)]
    messages = [("/camera/image", False, Image(stamp_ns=stamp[i], data=np.zeros((4, 4), np.uint8),
                                               frame_index=frame_index(i)), stamp[i]) for i in range(10)]
    messages += [("/markers", False, MarkerArray(stamp_ns=stamp[i]), stamp[i] + 1) for i in ANSWERED]
    if reference_ns is not None:  # logged as a recorder gets a latched message: at once, or as it is taken
        messages.append(("/markers/reference", True, MarkerArray(stamp_ns=T0_NS + reference_ns),
                         T0_NS + max(reference_ns, 0)))
    if notices:
        messages += [("/unanswered", False, Unanswered(stamp_ns=stamp[0], topic="/camera/image"), stamp[0] + 1),
                     ("/unanswered", False, Unanswered(stamp_ns=stamp[4], topic="/field"), stamp[4] + 1)]
    write_bag(folder, sorted(messages, key=lambda m: m[3]))


@pytest.mark.parametrize("frame_index, notices, reference_frame, reference_ns, played", [
    (lambda i: i, False, 1, None, ANSWERED),  # a video's frames: those answered (each pass, its reference by number)
    (lambda i: -1, False, 1, None, [1, *ANSWERED]),  # a live camera's: also the reference_frame last before the first
    (lambda i: -1, False, 1, 20_000_000, [1, *ANSWERED]),  # answer, its reference frame (the reference's stamp)
    (lambda i: -1, False, 0, None, ANSWERED),
    (lambda i: -1, False, 3, None, [0, 1, *ANSWERED]),  # all there are
    (lambda i: -1, False, 1, -500_000_000, ANSWERED),  # the recording began after the live reference
    (lambda i: -1, True, 1, None, [0, *ANSWERED]),  # the notices recorded: also the frames the tracker said it left
], ids=["video", "live camera", "live camera, its reference recorded", "live camera, reference_frame 0",
        "live camera, reference_frame 3", "live camera, recorded after its reference", "notices recorded"])
def test_as_recorded_by_plays_the_frames_the_live_pipeline_took(bus: BusAddress, tmp_path: Path, frame_index,
                                                                notices: bool, reference_frame: int,
                                                                reference_ns: int | None,
                                                                played: list[int]) -> None:
    """`as_recorded_by` /markers: of a live run that dropped frames, only the frames the live pipeline took are
    played, each once the pipeline has answered the one before on /markers (none lost). Of a live camera's
    frames before the first answer (the live reference frame), every one was played: the live tracker had
    missed frame 1 (frame 2, the 2nd it saw, was its reference: reference_frame 1), and the replay's took its
    reference at frame 1. Now the reference_frame last are, and none where the recording began after the
    live tracker took its reference (recorded, stamped before the first frame): the live tracker dropped them,
    and the replay's, resuming that reference, answered them."""
    _live_session(tmp_path / "b", frame_index, notices, reference_ns)
    seen: list[int] = []
    done = threading.Event()
    consumer = _answer_slowly(bus, "/camera/image", "/markers", 0.0, seen, done)
    node = BagPlay("play", {"path": str(tmp_path / "b"), "fast": True, "as_recorded_by": "/markers",
                            "reference_frame": reference_frame}, address=bus)
    in_thread(node).join(20)
    done.set()
    consumer.join(5)
    recorded_reference = [] if reference_ns is None else ["/markers/reference"]  # for the tracker's recorded_reference
    assert node.played_topics == ["/camera/image", *recorded_reference]  # not the live answers the player awaits
    assert seen == played and node.error is None
    assert node.counters["frames_left_out"] == 10 - len(played) and node.counters["sync_timeouts"] == 0


def test_as_recorded_by_refuses_a_bag_without_the_live_answers(bus: BusAddress, tmp_path: Path) -> None:
    write_bag(tmp_path / "frames", sample_messages(3, np.random.default_rng(6)))
    with pytest.raises(ParamError, match=r"frames: has no topic '/markers', which as_recorded_by names: the live "
                                         r"pipeline's answers are needed .* `fv bag record -a`"):
        BagPlay("play", {"path": str(tmp_path / "frames"), "as_recorded_by": "/markers"}, address=bus)
    with pytest.raises(ValueError, match="one recorded topic per as_recorded_by topic"):
        BagPlay("p", {"path": "x", "as_recorded_by": ["/left/markers", "/right/markers"],
                      "sync_on": "/left/camera/image"})
    with pytest.raises(ValueError, match="reference_frame -1 must be >= 0"):
        BagPlay("p", {"path": "x", "as_recorded_by": "/markers", "reference_frame": -1})


def test_reference_frame_without_as_recorded_by_is_refused(capsys: pytest.CaptureFixture) -> None:
    """`fv bag play --reference-frame N` acts only with --as-recorded-by: alone it was ignored, silently."""
    assert main(["bag", "play", "no_such_bag", "--reference-frame", "2"]) == 2
    assert capsys.readouterr().err.strip().endswith("--reference-frame acts only with --as-recorded-by")


def test_as_recorded_by_chooses_the_camera_of_its_namespace(bus: BusAddress, tmp_path: Path) -> None:
    """A two-finger bag: `as_recorded_by` /right/markers alone chose the first Image topic, /left/camera/image,
    filtered it by the right camera's answers and played the right camera whole. Now it chooses the right
    camera's frames it answered; an answer topic whose namespace holds both cameras, or none played, is refused,
    naming them; the live answers it reads are not played, with another sync topic too (they were)."""
    messages = []
    for k, side in enumerate(("/left", "/right")):
        stamps = [T0_NS + i * 10_000_000 + 3_000_000 * k for i in range(6)]
        messages += [(f"{side}/camera/image", False, Image(stamp_ns=t, data=np.zeros((4, 4), np.uint8),
                                                           frame_index=i), t) for i, t in enumerate(stamps)]
        messages += [(f"{side}/markers", False, MarkerArray(stamp_ns=t), t + 1) for t in stamps[1::2]]
    write_bag(tmp_path / "pair", sorted(messages, key=lambda m: m[3]))
    node = BagPlay("play", {"path": str(tmp_path / "pair"), "fast": True, "as_recorded_by": "/right/markers",
                            "sync_topic": "/right/slip"}, address=bus)
    node.setup()
    try:
        assert node.sync_on == ["/right/camera/image"]
        assert node.played_topics == ["/left/camera/image", "/right/camera/image", "/left/markers"]
        assert node.live["/right/camera/image"] == {T0_NS + i * 10_000_000 + 3_000_000 for i in (1, 3, 5)}
    finally:
        node.close()
    node = BagPlay("play", {"path": str(tmp_path / "pair"), "as_recorded_by": "/right/markers",
                            "topics": ["/left/camera/image"]}, address=bus)
    with pytest.raises(ValueError, match=r"as_recorded_by /right/markers: no Image topic\(s\) played in its "
                                         r"namespace '/right/' \(played: /left/camera/image\).*give sync_on"):
        node.setup()
    node.close()
    messages += [("/markers", False, MarkerArray(stamp_ns=T0_NS), T0_NS + 1)]
    write_bag(tmp_path / "root", sorted(messages, key=lambda m: m[3]))
    node = BagPlay("play", {"path": str(tmp_path / "root"), "as_recorded_by": "/markers"}, address=bus)
    with pytest.raises(ValueError, match=r"2 Image topic\(s\) played in its namespace '/' \(/left/camera/image, "
                                         r"/right/camera/image\)"):
        node.setup()
    node.close()


def test_a_notice_releases_the_frame_of_its_own_camera(bus: BusAddress, tmp_path: Path) -> None:
    """Two fingers' cameras whose frames share stamps (synchronised cameras): the left tracker's notice that it
    left a frame unanswered released the right camera's frame of that stamp too, before the right pipeline had
    answered it."""
    stamp = T0_NS + 10_000_000
    write_bag(tmp_path / "pair", [(f"{side}/camera/image", False, Image(stamp_ns=stamp, data=np.zeros((4, 4), np.uint8)),
                                   stamp) for side in ("/left", "/right")])
    node = BagPlay("play", {"path": str(tmp_path / "pair"), "fast": True,
                            "sync_on": ["/left/camera/image", "/right/camera/image"],
                            "sync_topic": ["/left/slip", "/right/slip"]}, address=bus)
    node.setup()
    try:
        for pending in node._pending:
            pending.append(stamp)
        assert node._answered("/left/unanswered", stamp) and node.counters["unanswered"] == 1
        assert [list(p) for p in node._pending] == [[], [stamp]]
        assert node._answered("/right/unanswered", stamp) and not node._answered("/right/unanswered", stamp)
    finally:
        node.close()


def test_sync_streams_must_pair_up() -> None:
    with pytest.raises(ValueError, match="one recorded topic per sync topic"):
        BagPlay("p", {"path": "x", "sync_topic": ["/left/slip", "/right/slip"], "sync_on": "/left/camera/image"})


def test_play_offset_duration_topics_remap_and_latched_first(bus: BusAddress, tmp_path: Path) -> None:
    messages = sample_messages(50, np.random.default_rng(2))  # frames every 10 ms
    write_bag(tmp_path / "b", messages)
    node, items = play_to_the_end(bus, {"path": str(tmp_path / "b"), "fast": True, "start_offset_s": 0.2,
                                        "duration_s": 0.1, "topics": ["/camera/image", "/camera/info"]},
                                  ["/cam2", "/camera/info", "/slip"], remap={"/camera/image": "/cam2"})
    got = [(item.topic, item.msg.seq, item.latched) for item in items]
    start = messages[0][3]
    want = [i for i, (t, _, _, lt) in enumerate(m for m in messages if m[0] == "/camera/image")
            if start + 0.2e9 <= lt < start + 0.3e9]
    assert got == [("/camera/info", 0, True)] + [("/cam2", i, False) for i in want]
    assert len(want) == 10 and node.counters["played"] == 11


def test_a_play_reads_each_files_summary_once(bus: BusAddress, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                             caplog: pytest.LogCaptureFixture) -> None:
    """`fv bag play` read a bag's summaries (tens of ms a file for a recording of an hour) in the command, the
    params' check and the node's setup, and again for its metadata and each pass over its messages (28 reads of
    this bag's 3 files): now once a file, as the bag opens. A split bag whose metadata makes the player look for
    gone publishers' latched messages, played from an offset (the latched messages before it are read first)."""
    write_bag(tmp_path / "b", sample_messages(40, np.random.default_rng(2)), chunk_size_b=4_000, max_bag_size_b=20_000)
    files = sorted(map(str, BagReader(tmp_path / "b").files))
    reads: list[str] = []
    read_summary = mcap.reader.SeekingReader.get_summary

    def counted(reader: mcap.reader.SeekingReader) -> object:
        reads.append(reader._stream.name)
        return read_summary(reader)

    monkeypatch.setattr(mcap.reader.SeekingReader, "get_summary", counted)
    caplog.set_level(logging.INFO)
    assert main(["bag", "play", str(tmp_path / "b"), "--fast", "--start-offset", "0.2",
                 "--no-wait-for-subscribers"]) == 0
    assert "played 64 messages" in caplog.text  # the camera info, then 21 frames each with a field and slip state
    assert len(files) > 1 and sorted(reads) == files


def test_a_duration_under_a_nanosecond_plays_the_first_message(bus: BusAddress, tmp_path: Path) -> None:
    """The stretch [start, start + duration) was cut to whole ns: --duration 1e-12 played nothing."""
    write_bag(tmp_path / "b", sample_messages(5, np.random.default_rng(2)))  # the camera info opens the bag
    _, items = play_to_the_end(bus, {"path": str(tmp_path / "b"), "fast": True, "duration_s": 1e-12,
                                     "topics": ["/camera/image", "/camera/info"]}, ["/camera/image", "/camera/info"])
    assert [item.topic for item in items] == ["/camera/info"]


def test_a_loop_over_nothing_ends_and_numbers_that_mean_nothing_are_refused(bus: BusAddress, tmp_path: Path) -> None:
    """--loop from past the end spun a core forever, re-sending the latched messages; NaN and
    infinity hung the player (rate) or ended it in a traceback (offsets, durations)."""
    write_bag(tmp_path / "b", sample_messages(5, np.random.default_rng(3)))
    node = BagPlay("play", {"path": str(tmp_path / "b"), "fast": True, "loop": True, "start_offset_s": 100.0},
                   address=bus)
    thread = in_thread(node)
    thread.join(10)
    assert not thread.is_alive() and node.counters["loops"] == 0
    for param in ("rate", "start_offset_s", "duration_s", "sync_timeout_s"):
        for value in (float("nan"), float("inf")):
            with pytest.raises(ValueError, match=f"param '{param}' = {value} is not a finite number"):
                BagPlay("play", {"path": str(tmp_path / "b"), param: value}, address=bus)
    with pytest.raises(ValueError, match="'max_bag_duration_s' = inf is not a finite number"):
        BagRecord("rec", {"output": str(tmp_path / "r"), "topics": ["/a"], "max_bag_duration_s": float("inf")},
                  address=bus)
    assert not (tmp_path / "r").exists()
    with pytest.raises(ValueError, match=f"attach: '{tmp_path}' is a folder, not a file"):  # it said "not found"
        BagRecord("rec", {"output": str(tmp_path / "r"), "topics": ["/a"], "attach": [str(tmp_path)]}, address=bus)
    assert parse_size("1.5K") == 1536 and parse_size("0") == 0
    with pytest.raises(argparse.ArgumentTypeError, match="'0.1' is less than a byte"):
        parse_size("0.1")  # 0 bytes: "never split", without a word


def test_optional_topics_are_played_when_recorded_and_skipped_when_not(bus: BusAddress, tmp_path: Path) -> None:
    """`optional_topics` (replay.yaml's /tracker/reset) play in their recorded order among the frames
    when the bag holds them; a bag without them plays its required topics, where a required topic
    missing is an error naming it."""
    messages = sample_messages(6, np.random.default_rng(3))
    reset_at = messages[3 * 3][3] + 10  # between the third frame's slip state and the fourth frame
    with_reset = [m for m in messages if m[0] != "/slip"] + [("/tracker/reset", False, SlipState(), reset_at)]
    write_bag(tmp_path / "with", sorted(with_reset, key=lambda m: m[3]))
    write_bag(tmp_path / "without", messages)
    params = {"fast": True, "topics": ["/camera/image"], "optional_topics": ["/tracker/reset", "/not_recorded"]}
    for name, want in (("with", ["/camera/image"] * 3 + ["/tracker/reset"] + ["/camera/image"] * 3),
                       ("without", ["/camera/image"] * 6)):
        node, items = play_to_the_end(bus, {"path": str(tmp_path / name), **params},
                                      ["/camera/image", "/tracker/reset"])
        assert [item.topic for item in items] == want and node.error is None, name
    with pytest.raises(ParamError, match="without: has no topic '/tracker/reset' to play"):  # as its params are checked
        BagPlay("play", {"path": str(tmp_path / "without"), "topics": ["/tracker/reset"]}, address=bus)


def test_a_bag_holding_the_bus_plumbing_plays_it_only_when_named(bus: BusAddress, tmp_path: Path,
                                                               caplog: pytest.LogCaptureFixture) -> None:
    """`fv bag record -a` recorded the nodes' param requests and `unanswered` notices before it left them out:
    played with every topic, such a bag's `/tracker/param/set` set the replay's tracker and its notices released
    frames before the pipeline answered them. Now they are played only when named."""
    from msgs import ParamSet, Unanswered
    messages = sample_messages(4, np.random.default_rng(5))
    plumbing = [("/tracker/param/set", False, ParamSet(request_id="r", values={"gate_px": 3.0}), messages[2][3] + 5),
                ("/unanswered", False, Unanswered(stamp_ns=messages[1][2].stamp_ns, topic="/camera/image"),
                 messages[2][3] + 7)]
    write_bag(tmp_path / "old", sorted(messages + plumbing, key=lambda m: m[3]))
    caplog.set_level(logging.INFO)
    shown = ["/camera/image", "/tracker/param/set", "/unanswered"]
    topics = ["/camera/info", "/field", "/slip", *shown]  # every recorded one, so that none is waited for
    for named, want in (([], ["/camera/image"] * 4), (["/camera/image", "/unanswered"], [
            "/camera/image", "/unanswered", "/camera/image", "/camera/image", "/camera/image"])):
        node, items = play_to_the_end(bus, {"path": str(tmp_path / "old"), "fast": True, "topics": named}, topics)
        assert [item.topic for item in items if item.topic in shown] == want and node.error is None, named
    assert "not played: /tracker/param/set, /unanswered, the bus's plumbing (name a topic to play it)" in caplog.text


def test_start_paused_until_sigusr1(bus: BusAddress, spawn: Spawn, tmp_path: Path) -> None:
    write_bag(tmp_path / "b", sample_messages(20, np.random.default_rng(4)))
    with TopicReader(["/slip"], bus) as reader:
        play = spawn("bag", "play", str(tmp_path / "b"), "--topics", "/slip", "--start-paused", "--wait-timeout", "20")
        while "paused" not in play.stderr.readline():
            assert play.poll() is None
        assert reader.recv(0.8) is None
        # the player is listed as the publisher of what it plays (`fv topic list / info` saw none of it)
        status = wait_status("bag_play", lambda st: bool(st.publishes), timeout_s=5.0)
        assert status.publishes == [["/status", "NodeStatus"], ["/slip", "SlipState"]]
        play.send_signal(signal.SIGUSR1)
        got = [reader.recv(2.0) for _ in range(20)]
    assert [r.msg.seq for r in got] == list(range(20))
    assert play.wait(10) == 0
    # 20 messages 10 ms apart: the summary's time and rate leave the pause (at least 0.8 s) out
    played_s, paused_s = map(float, re.search(r"in ([\d.]+) s \(and ([\d.]+) s paused\)", play.stderr.read()).groups())
    assert played_s < 0.6 and paused_s >= 0.75


def test_a_paused_player_keeps_its_latched_messages(bus: BusAddress, spawn: Spawn, tmp_path: Path) -> None:
    """Paused, the player answered none of the forwarder's refreshes (made when another publisher leaves):
    its CameraInfo was taken for a gone publisher's, and a node started during the pause got none."""
    from nodes.forwarder import ping
    from nodes.latched_cache import REFRESH_WAIT_S

    write_bag(tmp_path / "b", sample_messages(20, np.random.default_rng(4)))
    play = spawn("bag", "play", str(tmp_path / "b"), "--start-offset", "0.05", "--start-paused",
                 "--no-wait-for-subscribers")
    while "paused" not in play.stderr.readline():
        assert play.poll() is None
    wait_for(lambda: "L/camera/info\0cam" in ping(bus)["latched"], 10.0,  # sent before the first message it pauses at
             "the latched /camera/info at the forwarder", period_s=0.05)
    other = PublisherSocket("other", bus)
    assert other.wait_connected(2.0)
    other.close()  # the forwarder asks every publisher left to send its latched messages again
    time.sleep(REFRESH_WAIT_S + 0.5)
    with TopicReader(["/camera/info"], bus) as late:
        got = late.recv(2.0)
    assert got is not None and got.msg.width == 32
    stop(play)


def test_recording_stops_at_the_stop_on_a_live_bus(bus: BusAddress, tmp_path: Path) -> None:
    """A bus that never goes quiet (a 100 Hz topic): the recording ends with the messages published
    before the stop. The drain used to wait for 0.1 s of silence and so recorded 2 s more."""
    node = BagRecord("rec", {"output": str(tmp_path / "live"), "topics": ["/a"]}, address=bus)
    thread = in_thread(node)
    pub = PublisherSocket("src", bus)
    stop_ns = None
    try:
        wait_subscribed(pub, ["/a"])
        started = time.monotonic()
        while time.monotonic() - started < 3.0:
            pub.publish("/a", SlipState(stamp_ns=time.time_ns()))
            if stop_ns is None and time.monotonic() - started > 0.5:
                stop_ns = time.time_ns()
                node.stop()
            time.sleep(0.01)
    finally:
        pub.close()
    thread.join(10)
    last_ns = max(m.publish_time_ns for m in BagReader(tmp_path / "live").messages(["/a"]))
    assert last_ns <= stop_ns, f"recorded {(last_ns - stop_ns) / 1e6:.0f} ms of messages published after the stop"


def _stall_a_flush(monkeypatch: pytest.MonkeyPatch, stall_s: float) -> tuple[threading.Event, list[tuple[int, int]]]:
    """`BagWriter.flush` held up `stall_s` once (an fsync a slow disk holds up), at its first call after the
    returned event is set; the list gets that stall's (start, end) wall times in ns."""
    arm, stalls = threading.Event(), []
    flush = BagWriter.flush

    def stalling_flush(self: BagWriter) -> None:
        if arm.is_set() and not stalls:
            start = time.time_ns()
            time.sleep(stall_s)
            stalls.append((start, time.time_ns()))
        flush(self)

    monkeypatch.setattr(BagWriter, "flush", stalling_flush)
    return arm, stalls


def _record_through_a_stall(node: BagRecord, bus: BusAddress, arm: threading.Event,
                            stalls: list[tuple[int, int]]) -> int:
    """Run the recorder `node` while `/a` is published every 10 ms from before the stall to after it, then stop
    it; the number of messages published."""
    thread = in_thread(node)
    pub = PublisherSocket("src", bus)
    try:
        wait_subscribed(pub, ["/a"])
        arm.set()
        wait_for(lambda: stalls, 20.0, "a stalled flush", between=lambda: pub.publish("/a", SlipState()))
        for _ in range(10):
            pub.publish("/a", SlipState())
            time.sleep(0.01)
        published = pub.publish("/a", SlipState()) + 1
    finally:
        pub.close()
        node.stop()
        thread.join(10)
    return published


def test_messages_received_while_a_flush_stalls_keep_their_receive_time(bus: BusAddress, tmp_path: Path,
                                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """One thread received and wrote: a message that came while the writer compressed, wrote or synced waited in
    the socket and was stamped (its log time) when the writer was done, however long before it had come
    (measured beside two busy loops: up to 540 ms late, README). Here a flush stalls 0.8 s; every message published
    in its first half was stamped after it ended, 0.4 to 0.8 s late. They now keep the time they came."""
    stall_s = 0.8
    arm, stalls = _stall_a_flush(monkeypatch, stall_s)
    node = BagRecord("rec", {"output": str(tmp_path / "stall"), "topics": ["/a"], "flush_period_s": 1.0},
                     address=bus)
    _record_through_a_stall(node, bus, arm, stalls)
    (start_ns, end_ns), = stalls
    early = [m for m in BagReader(tmp_path / "stall").messages(["/a"])
             if start_ns <= m.publish_time_ns <= start_ns + stall_s / 2 * 1e9]
    assert len(early) >= 5, f"{len(early)} messages published in the stall's first half"
    late_ms = [(m.log_time_ns - m.publish_time_ns) / 1e6 for m in early if m.log_time_ns >= end_ns]
    assert not late_ms, (f"{len(late_ms)} of {len(early)} messages published in the first half of a {stall_s} s "
                         f"flush stall were stamped after it, {min(late_ms):.0f} to {max(late_ms):.0f} ms late")
    assert node.counters["dropped"] == 0 and node.state == "ok"


def test_a_writer_more_than_queue_depth_behind_drops_and_names_what_it_dropped(
        bus: BusAddress, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """At most `queue_depth` messages wait for the writer, as in the socket's queue, which dropped the rest
    unnamed. A flush stalled 1.5 s while 100 messages a second come, 50 at most waiting: what comes beyond them
    is dropped, counted and named by topic; every message published is either in the bag or counted as
    dropped. The recorder's drops are no bus losses: none is also missing by seq, where every one was (the seqs
    were counted as the writer took the messages)."""
    arm, stalls = _stall_a_flush(monkeypatch, 1.5)
    node = BagRecord("rec", {"output": str(tmp_path / "behind"), "topics": ["/a"], "queue_depth": 50},
                     address=bus)
    published = _record_through_a_stall(node, bus, arm, stalls)
    bag = BagReader(tmp_path / "behind")
    dropped = json.loads(bag.metadata()["fv_recording_end"]["dropped"])
    assert dropped.keys() == {"/a"} and dropped["/a"] > 0 and node.counters["dropped"] == dropped["/a"]
    assert bag.topics()["/a"].count + dropped["/a"] == published
    assert node.counters["gaps"] == 0 and _summary_counts(node.summary_line())["/a"]["missing"] == 0, \
        node.summary_line()
    assert bag.metadata()["fv_recording_end"]["gaps"] == "0"
    assert node.state == "warn" and "dropped" in node.message and "/a" in node.message, node.message
    assert f"{dropped['/a']} dropped)" in node.summary_line() and node.summary_line().endswith(
        f"dropped {dropped['/a']}")


def _record_published(node: BagRecord, bus: BusAddress, topics: tuple[str, ...], count: int,
                      latched: tuple[str, CameraInfo] | None = None) -> None:
    """Run the recorder `node` while `SlipState(stamp_ns=i)` is published on every one of `topics` for i < `count`,
    10 ms apart (after the `latched` (topic, message), if any), then stop it."""
    thread = in_thread(node)
    pub = PublisherSocket("src", bus)
    try:
        wait_subscribed(pub, [topics[0]])
        if latched is not None:
            pub.publish(*latched, latched=True)
        for i in range(count):
            for topic in topics:
                pub.publish(topic, SlipState(stamp_ns=i))
            time.sleep(0.01)
    finally:
        pub.close()
    node.stop()
    thread.join(10)


@pytest.mark.parametrize("selection", [{"all_topics": True}, {"regex": "^/(a|x|y|left|right|unanswered)"}])
def test_record_all_or_regex_leaves_out_plumbing_topics_unless_named(bus: BusAddress, tmp_path: Path,
                                                                     selection: dict) -> None:
    """`-a` recorded every node's latched `/N/param/state` (the player's too: a recording of a replay held
    more than was played) and the pipeline's `unanswered` notices (played with the bag, they released a
    `sync_topic` replay's frames early); either is recorded by `-a` or `-e` only when named."""
    params = {"output": str(tmp_path / "all"), **selection, "topics": ["/y/param/state", "/right/unanswered"],
              "exclude_regex": "^/status$"}
    _record_published(BagRecord("rec", params, address=bus), bus,
                      ("/a", "/x/param/state", "/x/param/set", "/y/param/state", "/unanswered", "/left/unanswered",
                       "/right/unanswered"), 5)
    assert {t: i.count for t, i in BagReader(tmp_path / "all").topics().items()} == {
        "/a": 5, "/y/param/state": 5, "/right/unanswered": 5}


def test_record_node_selection_split_attachments(bus: BusAddress, tmp_path: Path) -> None:
    launch = tmp_path / "session.yaml"
    launch.write_text("nodes: []\n")
    node = BagRecord("rec", {"output": str(tmp_path / "sel"), "regex": "^/(a|cam)", "exclude_regex": "skip",
                             "max_bag_duration_s": 0.3, "attach": [str(launch)], "compression": "lz4"}, address=bus)
    info = CameraInfo(width=160, height=120, K=np.eye(3) * 100.0, D=np.zeros(4))
    _record_published(node, bus, ("/a", "/a/skip", "/b"), 80, latched=("/camera/info", info))
    bag = BagReader(tmp_path / "sel")
    assert {t: i.count for t, i in bag.topics().items()} == {"/camera/info": 1, "/a": 80}
    assert len(bag.files) >= 3 and [m.sequence for m in bag.messages(["/a"])] == list(range(80))
    names = {a.name for a in bag.attachments()}
    assert names == {"session.yaml", "calibration/camera_info.yaml"}
    calib = yaml.safe_load(next(a.data for a in bag.attachments() if a.name.startswith("calibration")))
    assert calib["K"][0][0] == 100.0 and calib["width"] == 160
    meta = bag.metadata()
    assert {"host", "start_time", "software", "command_line", "bus", "topics"} <= set(meta["fv_recording"])
    totals = json.loads(meta["fv_recording_end"]["per_topic"])["/a"]
    assert totals["count"] == 80 and totals["gaps"] == 0 and 0 < totals["first_ns"] < totals["last_ns"]
    assert "missing by seq 0" in node.summary_line() and "/a 80" in node.summary_line()


def test_a_recording_started_after_a_session_holds_none_of_its_latched_messages(bus: BusAddress,
                                                                             tmp_path: Path) -> None:
    """A recorder started on a forwarder left running (`fv forwarder`) after a session, before the next,
    recorded the latched messages the gone session left there: its camera's CameraInfo, attached to the
    bag as the calibration (two `calibration/camera_info.yaml`, the earlier camera's 640x480 first), and
    its nodes' statuses. A latched message now goes with its publisher: the bag holds the next camera's
    alone."""
    from msgs import NodeStatus
    from nodes.latched_cache import REFRESH_WAIT_S

    earlier = PublisherSocket("camera", bus)
    assert earlier.wait_connected(2.0)
    earlier.publish("/camera/info", CameraInfo(width=640, height=480, K=np.eye(3) * 300.0), latched=True)
    earlier.publish("/status", NodeStatus(stamp_ns=time.time_ns()), latched=True)
    time.sleep(0.2)
    earlier.close()
    time.sleep(REFRESH_WAIT_S + 0.5)
    node = BagRecord("rec", {"output": str(tmp_path / "next"), "all_topics": True}, address=bus)
    thread = in_thread(node)
    camera = PublisherSocket("camera", bus)  # the next session's
    try:
        wait_subscribed(camera, ["/camera/image"])
        camera.publish("/camera/info", CameraInfo(width=320, height=240, K=np.eye(3) * 150.0), latched=True)
        camera.publish("/camera/image", Image(stamp_ns=time.time_ns(), data=np.zeros((240, 320), np.uint8)))
        time.sleep(0.5)
    finally:
        node.stop()
        thread.join(10)
        camera.close()
    bag = BagReader(tmp_path / "next")
    assert [m.decode().width for m in bag.messages(["/camera/info"])] == [320]
    assert {m.node for m in bag.messages(["/status"])} == {"rec"}
    calibrations = [yaml.safe_load(a.data) for a in bag.attachments() if a.name.startswith("calibration/")]
    assert [(c["width"], c["K"][0][0]) for c in calibrations] == [(320, 150.0)]


def _session_bag(folder: Path, recorded_by: dict[str, str], replaced_tracker: bool) -> BagWriter:
    """A recording begun before a session's camera: at its start the tracker reference and camera info a
    forwarder still held (seq 0 of "tracker" and "camera"), then the session's camera info (its camera
    started again: seq 0), its first 10 frames from seq 0 and, with `replaced_tracker`, a new tracker's
    reference (seq 0) taken from frame 1. `recorded_by`: its `fv_recording` metadata."""
    def reference(stamp_ns: int) -> MarkerArray:
        px = np.zeros((3, 2), np.float32)
        return MarkerArray(stamp_ns=stamp_ns, ref_px=px, cur_px=px, valid=np.ones(3, bool),
                           frames_since_seen=np.zeros(3, np.int32), width=32, height=24)

    writer = BagWriter(folder, metadata={"fv_recording": recorded_by}, fsync=False)
    writer.write("/markers/reference", "tracker", True, frames_of(reference(EARLIER_NS), 0, "tracker", EARLIER_NS),
                 T0_NS)
    for k, t in enumerate((T0_NS + 1000, T0_NS + 10**9)):
        info = CameraInfo(stamp_ns=t, width=32 * (k + 1), height=24, K=np.eye(3), D=np.zeros(4))
        writer.write("/camera/info", "camera", True, frames_of(info, 0, "camera", t - 100), t)
    for k in range(10):
        t = T0_NS + 2 * 10**9 + k * 10**8
        writer.write("/camera/image", "camera", False,
                     frames_of(Image(stamp_ns=t - 500, data=np.zeros((24, 32), np.uint8)), k, "camera", t - 100), t)
        if k == 1 and replaced_tracker:
            writer.write("/markers/reference", "tracker", True, frames_of(reference(t - 500), 0, "tracker", t + 10**6),
                         t + 10**7)
    writer.close()
    return writer


EARLIER_NS = T0_NS - 20 * 10**9  # an earlier session's tracker reference: its stamp and publish time


@pytest.mark.parametrize("recorded_by, replaced_tracker, not_played", [
    ({"host": "test"}, True, {("/markers/reference", EARLIER_NS), ("/camera/info", T0_NS + 1000)}),
    ({"host": "test"}, False, {("/camera/info", T0_NS + 1000)}),
    ({"host": "test", "latched": "of running publishers"}, True, set()),
])
def test_a_recording_of_gone_publishers_latched_messages_leaves_them_out(
        bus: BusAddress, tmp_path: Path, recorded_by: dict[str, str], replaced_tracker: bool,
        not_played: set) -> None:
    """A bag recorded before recorders got only running publishers' latched messages, begun before a
    session on a forwarder left running: it holds an earlier session's tracker reference, which the replay
    tracked the whole bag against (19 of 56 decisions of a real grasp differed from the live ones). Where its
    publisher started again in the bag (the session's tracker took its own), it is not played. A reference
    whose tracker ran on (a camera respawned as the recording began) is played; so is every message of a
    recording made since (its metadata says so)."""
    bag = BagReader(_session_bag(tmp_path / "b", recorded_by, replaced_tracker).output)
    with TopicReader(["/markers/reference", "/camera/info"], bus) as reader:
        thread = in_thread(BagPlay("play", {"path": str(bag.path), "fast": True, "wait_for_subscribers": False},
                                   address=bus))
        played = {(item.topic, item.msg.stamp_ns) for item in iter(lambda: reader.recv(2.0), None)}
        thread.join(5)
    recorded = {(m.topic, m.decode().stamp_ns) for m in bag.messages(["/markers/reference", "/camera/info"])}
    assert recorded - played == not_played


def test_replay_launch_plays_the_camera_topics(bus: BusAddress, spawn: Spawn, tmp_path: Path) -> None:
    """The bag part of launch/replay.yaml alone, waiting for no pipeline node (test_session_replay.py
    replays whole sessions through it)."""
    messages = sample_messages(30, np.random.default_rng(6))
    write_bag(tmp_path / "b", messages)
    kinds = {s.kind for s in load_launch(REPO / "launch" / "replay.yaml", {"bag": str(tmp_path / "b")})}
    assert {"bag_play", "tracker", "interpolator", "slip_detector"} <= kinds  # the pipeline from camera_pipeline.yaml
    doc = yaml.safe_load((REPO / "launch" / "replay.yaml").read_text())
    assert doc["nodes"][0]["kind"] == "bag_play"
    assert set(doc["nodes"][0]["params"].pop("start_after")) == {"tracker", "interpolator", "slip_detector"}
    only_bag = tmp_path / "replay_bag.yaml"
    only_bag.write_text(yaml.safe_dump({"args": doc["args"], "nodes": doc["nodes"][:1]}))
    with TopicReader(["/camera/image", "/camera/info"], bus) as reader:
        launch = spawn("launch", str(only_bag), f"bag:={tmp_path / 'b'}", "fast:=true")
        got = [reader.recv(10.0) for _ in range(31)]
    assert [f.msg.seq for f in got if f.topic == "/camera/image"] == list(range(30))
    assert [(f.latched, f.msg.width) for f in got if f.topic == "/camera/info"] == [(True, 32)]
    assert launch.wait(30) == 0  # bag_play is required: the launch ends with it, well when it played its bag
    assert "bag_play exited with code 0" in launch.stdout.read() + launch.stderr.read()
    # a bag damaged past its start fails the player as it plays, and the launch (both exited 0, as if played)
    write_bag(tmp_path / "d", messages, chunk_size_b=4_000)
    file = BagReader(tmp_path / "d").files[0]
    data = bytearray(file.read_bytes())
    chunk = bag_chunks(file)[-1]
    data[chunk.chunk_start_offset + chunk.chunk_length - 40] ^= 0xFF
    file.write_bytes(bytes(data))
    launch = spawn("launch", str(only_bag), f"bag:={tmp_path / 'd'}", "fast:=true")
    assert launch.wait(30) == 1
    out = launch.stdout.read() + launch.stderr.read()
    assert "damaged data" in out and "bag_play exited with code 1" in out


def test_bench_bag_reports_completeness_and_cpu(bus: BusAddress, spawn: Spawn) -> None:
    bench = spawn("bench", "bag", "--duration", "2", "--json")
    out, err = bench.communicate(timeout=90)
    assert bench.returncode == 0, err
    result = json.loads(out)
    assert result["complete"] and result["published"]["/camera/image"] == 120
    assert result["recorded"] == result["published"] and set(result["missing"].values()) == {0}
    assert 0 < result["recorder_cpu_percent"] < 200 and result["fast_play"]["received"] == 120
    assert result["publish_s"] >= 1.9  # the payload rate is over the publishing time, which can exceed --duration
    assert result["payload_MBps"] == pytest.approx(result["payload_b"] / 1e6 / result["publish_s"])


QUIET = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
SCENE = REPO / "launch" / "scenes" / "press_shear_slide.yaml"


def _replays_as_live(bag: Path, spawn: Spawn) -> None:
    """Replay `bag` through launch/replay.yaml as a batch to the bag's last live /slip state: a replayed state
    of the same window of fields as live (`window_stamps_ns`) has the live decision and P(slip) within 0.02;
    the frames the pipeline leaves unanswered (the window model's first 9) cost no sync timeout. A live node
    behind on a loaded host judges its latest field and drops those before: its window then differs from
    the replay's, which judges every frame."""
    recorded = {m.stamp_ns: m for m in (msg for _, msg, _ in read_bag(bag, topics=["/slip"]))}
    last = max(recorded)
    replayed: dict[int, SlipState] = {}
    output = bag.parent / f"{bag.name}_replay.log"
    with TopicReader(["/slip"]) as reader, open(output, "w") as log:
        launch = spawn("launch", str(REPO / "launch" / "replay.yaml"), f"bag:={bag}", "fast:=true",
                       "sync_topic:=/slip", "standby:=false", stdout=log, stderr=subprocess.STDOUT)
        while last not in replayed:
            item = reader.recv(90.0 if not replayed else 10.0)
            assert item is not None, f"the replay stopped after {len(replayed)} states"
            replayed[item.msg.stamp_ns] = item.msg
    assert launch.wait(30) == 0  # the bag played: the launch ends
    assert "sync timeouts 0" in output.read_text(), output.read_text()
    common = sorted(set(recorded) & set(replayed))
    same = [stamp for stamp in common
            if np.array_equal(replayed[stamp].window_stamps_ns, recorded[stamp].window_stamps_ns)]
    assert len(same) >= 20, f"{len(same)} of {len(common)} replayed states judged the live window"
    for stamp in same:
        assert replayed[stamp].slip == recorded[stamp].slip
        assert replayed[stamp].probability == pytest.approx(recorded[stamp].probability, abs=0.02)


def test_a_recording_started_mid_session_replays_against_the_live_reference(bus: BusAddress, spawn: Spawn,
                                                                           tmp_path: Path) -> None:
    """A recording started while the skin was pressed holds the tracker's reference (latched) but not its
    frame. replay.yaml took the bag's first frame, a pressed skin, as the reference, and 103 of 106 states
    differed from the live ones (slip for the whole shear); it now plays the recorded reference to the
    tracker, which tracks the bag against it as live. Resumed on a frame of the slide, the tracker took the
    shear as the markers' velocity and put 4 of 256 a pitch off for 12 frames, 2 invalid for 13 (P 0.24 against 0.17
    live at one state, in 3 of 9 runs three at once)."""
    bag = tmp_path / "mid"
    with TopicReader(["/slip"], bus) as reader:
        live = spawn("launch", str(REPO / "launch" / "pipeline.yaml"), "fps:=15", f"scene:={SCENE}",
                     "standby:=false", **QUIET)
        for k in range(25):  # 1.7 s of the scene: pressed, shearing
            assert reader.recv(90.0 if k == 0 else 10.0) is not None, f"{k} live states"
        recorder = spawn("bag", "record", "-a", "-x", "^/status$", "--compression", "none", "-o", str(bag), **QUIET)
        wait_status("bag_record", timeout_s=20.0)
        up_ns, recorded = time.time_ns(), 0
        while recorded < 45:  # states published while the recorder started, queued here, are not in the bag
            item = reader.recv(10.0)
            assert item is not None, f"{recorded} live states since the recorder is up"
            recorded += item.msg.pub_ns > up_ns
    assert stop(recorder) == 0
    stop(live)
    _replays_as_live(bag, spawn)


def test_a_recording_begun_as_the_camera_respawns_replays_against_the_live_reference(bus: BusAddress,
                                                                                    spawn: Spawn,
                                                                                    tmp_path: Path) -> None:
    """The camera killed (kill -9) mid-grasp, the recording begun before its respawn: the bag's first frame
    is the new camera's first, seq 0, and its recorded reference the one the live tracker went on with
    (here taken at a /tracker/reset while the skin was pressed). The replay took its own reference at the
    bag's frame 1 (meant for a recorder that got an earlier session's reference): 113 of 179 decisions
    differed from the live ones. It now tracks against the recorded reference."""
    from nodes.client import reset_grasp

    bag = tmp_path / "respawn"
    with TopicReader(["/slip"], bus) as reader:
        live = spawn("launch", str(REPO / "launch" / "pipeline.yaml"), "fps:=15", f"scene:={SCENE}",
                     "standby:=false", **QUIET)
        for k in range(18):  # 1.2 s of the scene: pressed
            assert reader.recv(90.0 if k == 0 else 10.0) is not None, f"{k} live states"
    reset_grasp()  # the live tracker's reference: the pressed skin
    camera = wait_status("camera", lambda st: st.counters["frames"] > 20).pid
    time.sleep(0.3)
    os.kill(camera, signal.SIGSTOP)  # no frame until the respawned camera's
    recorder = spawn("bag", "record", "-a", "-x", "^/status$", "--compression", "none", "-o", str(bag), **QUIET)
    wait_status("bag_record", timeout_s=20.0)
    killed_ns = time.time_ns()
    os.kill(camera, signal.SIGKILL)
    with TopicReader(["/slip"], bus) as reader:
        after = 0
        while after < 60:
            item = reader.recv(60.0 if not after else 10.0)
            assert item is not None, f"{after} live states after the respawn"
            after += item.msg.stamp_ns > killed_ns
    assert stop(recorder) == 0
    stop(live)
    assert next(BagReader(bag).messages(["/camera/image"])).sequence == 0
    _replays_as_live(bag, spawn)


def test_a_node_process_sends_what_it_published_before_it_exits(bus: BusAddress, spawn: Spawn, tmp_path: Path) -> None:
    """A node process leaves without Python's teardown (os._exit, for the slip detector's slow one); it
    first lets ZeroMQ send what it still queues. A bag player that stops right after its last frame
    lost frames of a fast burst when the process left with ZeroMQ's I/O thread mid-flush (48 to 57 of 300). The
    burst stays under the publisher's queue of PUB_HWM messages, which drops beyond it by design when the
    forwarder falls behind (278 of 300 arrived in one suite run beside other tests)."""
    rng = np.random.default_rng(9)
    frames = PUB_HWM * 3 // 4
    original = write_bag(tmp_path / "burst", sample_messages(frames, rng, (480, 640), [1_000_000] * frames))
    images = sum(1 for m in BagReader(original.output).messages() if m.topic == "/camera/image")
    with TopicReader(["/camera/image"], bus, hwm=1000) as reader:
        play = spawn("node", "bag_play", "-p", f"path={original.output}", "-p", "fast=true")
        assert play.wait(60) == 0, play.stderr.read()
        got = sum(1 for _ in iter(lambda: reader.recv(2.0), None))
    assert got == images


@pytest.mark.parametrize("failing", ["open", "finish", "mcap"])
def test_a_split_that_fails_ends_in_an_error_naming_the_file_and_a_summary(
        bus: BusAddress, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture,
        failing: str) -> None:
    """A recording split by size whose next file cannot be opened (permissions), or whose file cannot be finished
    as it is closed (its summary and index: a full disk): the node's error names it (with `fv bag recover` for the
    unfinished file), what was recorded is kept, and the recording ends with its summary. Both ended in the writer
    thread's AssertionError ('writer is closed', a traceback) and no summary, and the unfinished file went unnamed;
    it went unnamed still when the MCAP writer's own error (not an OSError) stopped the finishing."""
    import errno

    import mcap.writer

    import nodes.bag.writer as writer_module
    opened, open_mcap, finish = [], writer_module.open_mcap, mcap.writer.Writer.finish

    def second_open_fails(path: Path, *args: object) -> object:
        opened.append(path)
        if len(opened) > 1:
            raise PermissionError(13, "Permission denied", str(path))
        return open_mcap(path, *args)

    def first_finish_fails(self: mcap.writer.Writer) -> None:
        if not getattr(first_finish_fails, "failed", False):
            first_finish_fails.failed = True
            raise OSError(errno.ENOSPC, "No space left on device") if failing == "finish" else ValueError("bad chunk")
        finish(self)

    monkeypatch.setattr(writer_module, "open_mcap", second_open_fails)
    if failing != "open":
        monkeypatch.setattr(mcap.writer.Writer, "finish", first_finish_fails)
    died: list = []
    monkeypatch.setattr(threading, "excepthook", died.append)
    node = BagRecord("rec", {"output": str(tmp_path / "split"), "topics": ["/a"], "max_bag_size_b": 4000,
                             "compression": "none"}, address=bus)
    thread = in_thread(node)
    pub = PublisherSocket("src", bus)
    try:
        wait_subscribed(pub, ["/a"])
        poll_until(lambda: not thread.is_alive(), 20.0, between=lambda: pub.publish("/a", SlipState()))
    finally:
        pub.close()
        node.stop()
        thread.join(10)
    assert not died, died[0].exc_value
    assert node.state == "error" and node.summary_line().startswith(f"recorded {node.counters['recorded']} messages")
    if failing == "open":
        assert "Permission denied" in node.message, node.message
        assert len(opened) == 2 and BagReader(opened[0]).topics()["/a"].count == node.counters["recorded"] > 0
    else:
        error = "OSError: [Errno 28]" if failing == "finish" else "ValueError: bad chunk"
        assert node.message.startswith(f"could not finish {opened[0]} (recording failed: {error}"), node.message
        assert f"run `fv bag recover {opened[0]}`" in caplog.text
        assert recover(opened[0], tmp_path / "kept.mcap").messages == node.counters["recorded"] > 0


def _summary_counts(line: str) -> dict[str, dict[str, int]]:
    """Per topic of a recorder's summary line, {"recorded": n, "missing": n, "dropped": n, "lost": n} (0 when not
    named): "/a 2 (18 dropped, 10 lost), /b 3" gives {"/a": {"recorded": 2, "dropped": 18, "lost": 10, ...}...}."""
    topics = line.split(": ", 1)[1].rsplit("; missing by seq", 1)[0]
    counts = {}
    for topic, recorded, losses in re.findall(r"(/\S+) (\d+)(?: \(([^)]*)\))?", topics):
        words = dict(reversed(word.split(" ")) for word in losses.split(", ") if word)
        counts[topic] = {"recorded": int(recorded), **{w: int(words.get(w, 0)) for w in ("missing", "dropped", "lost")}}
    return counts


@pytest.mark.parametrize("failing", ["write", "split"])
def test_a_writer_that_fails_counts_by_topic_every_message_it_did_not_store(
        bus: BusAddress, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture,
        failing: str) -> None:
    """The writer fails (a full disk as it writes a message, a split whose new file cannot be opened) while
    messages wait for it, 20 at most: every message published before is in the bag, dropped or lost, counted
    by topic in the summary, the node's error and the status's counters (and the `fv_recording_end` record where
    the file could still be closed), none missing by seq. Those waiting, the one it failed on and those received
    after were counted nowhere."""
    import errno

    import mcap.writer

    import nodes.bag.writer as writer_module
    blocked, release, rounds = threading.Event(), threading.Event(), 30

    def fail_once_released() -> None:
        blocked.set()
        release.wait(30)
        raise (OSError(errno.ENOSPC, "No space left on device") if failing == "write"
               else PermissionError(13, "Permission denied"))

    if failing == "write":
        add_message, added = mcap.writer.Writer.add_message, []

        def third_add_fails(self: mcap.writer.Writer, *args: object, **kwargs: object) -> None:
            added.append(1)
            if len(added) == 3:
                fail_once_released()
            add_message(self, *args, **kwargs)

        monkeypatch.setattr(mcap.writer.Writer, "add_message", third_add_fails)
    else:
        open_mcap, opened = writer_module.open_mcap, []

        def second_open_fails(path: Path, *args: object) -> object:
            opened.append(path)
            if len(opened) > 1:
                fail_once_released()
            return open_mcap(path, *args)

        monkeypatch.setattr(writer_module, "open_mcap", second_open_fails)
    caplog.set_level(logging.INFO)
    died: list = []
    monkeypatch.setattr(threading, "excepthook", died.append)
    split = {"chunk_size_b": 500, "max_bag_size_b": 1500} if failing == "split" else {}
    node = BagRecord("rec", {"output": str(tmp_path / "failed"), "topics": ["/a", "/b"], "queue_depth": 20,
                             "compression": "none", **split}, address=bus)
    thread = in_thread(node)
    pub = PublisherSocket("src", bus)
    try:
        wait_subscribed(pub, ["/a", "/b"])
        for i in range(rounds):  # 40 messages/s: a receive thread stalled 0.5 s (busy cores) overflows no socket
            pub.publish("/a", SlipState(stamp_ns=i))
            pub.publish("/b", SlipState(stamp_ns=i))
            time.sleep(0.05)
        wait_for(blocked.is_set, 20.0, "the writer at its failure")
    finally:
        release.set()
        pub.close()
        thread.join(10)
    assert not died, died[0].exc_value
    counts = _summary_counts(node.summary_line())
    assert {t: sum(c[w] for w in ("recorded", "dropped", "lost")) for t, c in counts.items()} == \
        {"/a": rounds, "/b": rounds}, node.summary_line()
    lost = {t: c["lost"] for t, c in counts.items() if c["lost"]}
    assert sum(lost.values()) > 20 and node.counters["lost"] == sum(lost.values()), node.summary_line()
    assert node.counters["gaps"] == 0 and all(c["missing"] == 0 for c in counts.values()), node.summary_line()
    by_topic = ", ".join(f"{t} {n}" for t, n in sorted(lost.items()))
    assert node.state == "error" and node.message.endswith(
        f"; {sum(lost.values())} messages received were not stored ({by_topic})"), node.message
    assert node.message in caplog.text and node.summary_line() in caplog.text
    recorded = {t: info.count for t, info in BagReader(tmp_path / "failed").topics().items()}
    assert recorded == {t: c["recorded"] for t, c in counts.items() if c["recorded"]}
    if failing == "write":
        assert json.loads(BagReader(tmp_path / "failed").metadata()["fv_recording_end"]["lost"]) == lost


@pytest.mark.parametrize("failing", ["add_metadata", "finish"])
def test_a_bag_that_cannot_be_closed_is_named_with_recover_and_summed_up(
        bus: BusAddress, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture,
        failing: str) -> None:
    """An error other than an OSError as the recording ends (its end record, or the MCAP writer's summary and
    index): the node's error names the file, with `fv bag recover`, the file is closed as it stands, and the
    summary line is logged. Only an OSError was caught there: any other ended in the writer thread's traceback,
    the file unnamed (and left open) and no summary."""
    import mcap.writer

    def fails(*args: object) -> None:
        raise ValueError("bad record")

    owner = BagWriter if failing == "add_metadata" else mcap.writer.Writer
    monkeypatch.setattr(owner, failing, fails)
    caplog.set_level(logging.INFO)
    died: list = []
    monkeypatch.setattr(threading, "excepthook", died.append)
    node = BagRecord("rec", {"output": str(tmp_path / "end"), "topics": ["/a"], "flush_period_s": 0.1},
                     address=bus)
    _record_published(node, bus, ("/a",), 20)
    file = tmp_path / "end" / "end_0.mcap"
    assert not died, died[0].exc_value
    assert node.state == "error" and node.message == f"could not finish {file}: ValueError: bad record", \
        node.message
    assert f"run `fv bag recover {file}`" in caplog.text and node.summary_line() in caplog.text
    assert not node.writer.is_open and node.counters["recorded"] == 20
    monkeypatch.undo()  # the MCAP writer that `recover` uses too
    assert 0 < recover(file, tmp_path / "kept.mcap").messages <= 20


def test_a_recording_in_progress_is_said_so_and_not_recovered(bus: BusAddress, tmp_path: Path) -> None:
    """`fv bag info` of a recording in progress called it unfinished or damaged, advising `fv bag recover`, which
    took the file away: the recorder wrote on into its `.broken` copy, and the bag kept the few messages before."""
    node = BagRecord("rec", {"output": str(tmp_path / "live"), "topics": ["/a"], "flush_period_s": 0.2}, address=bus)
    file = tmp_path / "live" / "live_0.mcap"
    with recording(node, bus) as pub:
        pub.publish("/a", SlipState(stamp_ns=1))
        wait_for(lambda: node.counters.get("recorded") == 1, 10.0, "a message flushed")
        with pytest.raises(BagError, match="still being written \\(a recording in progress\\)"):
            BagReader(tmp_path / "live")
        with pytest.raises(ValueError, match="is still being written"):
            recover_in_place(file)
        assert sorted(p.name for p in file.parent.iterdir()) == ["live_0.mcap"]
    assert BagReader(tmp_path / "live").message_count == 1


def test_a_bag_folder_removed_while_recording_ends_the_recording_naming_the_file(
        bus: BusAddress, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """`rm -rf` of the bag folder as it records: the recorder wrote on into the removed file without a word, and its
    closing summary ended in a thread's FileNotFoundError (no summary line, exit 0). Now the next flush ends it
    with an error naming the file, every message it held counted lost, and no `fv bag recover` advice."""
    node = BagRecord("rec", {"output": str(tmp_path / "gone"), "topics": ["/a"], "flush_period_s": 0.2}, address=bus)
    with caplog.at_level("INFO"), recording(node, bus) as pub:
        for i in range(20):
            pub.publish("/a", SlipState(stamp_ns=i))
        wait_for(lambda: node.counters.get("recorded") == 20, 10.0, "20 messages flushed")
        shutil.rmtree(tmp_path / "gone")
        pub.publish("/a", SlipState(stamp_ns=20))
        wait_for(lambda: bool(node.error), 10.0, "the removal said")
    file = tmp_path / "gone" / "gone_0.mcap"
    assert node.state == "error" and f"removed while being written (its messages went with it): '{file}'" in node.message
    assert "21 messages received were not stored (/a 21)" in node.message, node.message
    assert {k: node.counters.get(k) for k in ("recorded", "lost")} == {"recorded": 0, "lost": 21}
    assert "fv bag recover" not in caplog.text and node.summary_line() in caplog.text


def test_a_disk_full_at_a_flush_counts_the_chunk_in_progress_lost_not_recorded(
        bus: BusAddress, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The disk fills as a flush writes the chunk in progress: the messages of that chunk never reached the
    file, yet they stayed counted as recorded (summary, counters) and not as lost."""
    import errno

    import nodes.bag.writer as writer_module
    open_mcap, full = writer_module.open_mcap, threading.Event()

    class FillingStream:
        def __init__(self, stream: object) -> None:
            self._s = stream

        def write(self, data: bytes) -> int:
            if full.is_set():
                raise OSError(errno.ENOSPC, "No space left on device")
            return self._s.write(data)

        def __getattr__(self, name: str) -> object:
            return getattr(self._s, name)

    def filling_open(path: Path, compression: str, chunk_size_b: int = writer_module.DEFAULT_CHUNK_B) -> object:
        stream = open(path, "xb")
        wrapped = FillingStream(stream)
        writer = writer_module.Writer(wrapped, chunk_size=chunk_size_b,
                                      compression=writer_module.COMPRESSIONS[compression])
        writer.start(profile=writer_module.PROFILE)
        return wrapped, writer

    monkeypatch.setattr(writer_module, "open_mcap", filling_open)
    node = BagRecord("rec", {"output": str(tmp_path / "full"), "topics": ["/a"], "flush_period_s": 0.5,
                             "compression": "none"}, address=bus)
    with recording(node, bus) as pub:
        for i in range(20):
            pub.publish("/a", SlipState(stamp_ns=i))
            time.sleep(0.01)
        wait_for(lambda: node.writer.stats.get("/a") is not None and node.writer.stats["/a"].count == 20, 10.0,
                 "20 messages in the chunk in progress")
        full.set()  # the disk is full before the next flush writes the chunk
        wait_for(lambda: bool(node.error), 10.0, "the writer's failure")
    file = tmp_path / "full" / "full_0.mcap"
    stored = recover(file, tmp_path / "kept.mcap").messages
    counts = {k: node.counters.get(k) for k in ("recorded", "lost", "dropped")}
    assert stored == 0 and counts == {"recorded": 0, "lost": 20, "dropped": 0}, (counts, node.summary_line())
    assert "20 messages received were not stored (/a 20)" in node.message, node.message
    assert "/a 0 (20 lost)" in node.summary_line(), node.summary_line()
