"""The node runtime across processes: slow subscribers do not slow publishers, malformed
messages are counted and never crash a node, params come from defaults, launch files
and --param."""
from __future__ import annotations

import gc
import random
import threading
import time

import msgpack
import numpy as np
import pytest
import zmq

import msgs
from msgs import DisplacementField, Image, MarkerArray, SlipState
from nodes.bus import PublisherSocket, TopicReader, envelope
from nodes.forwarder import FWD_HWM
from nodes.node import Node
from tests.nodes.conftest import Bus, run_fv, spinning, wait_for, wait_status

N_MALFORMED = 3_000
# Malformed messages sent before waiting for the node to count them: fewer than the forwarder's queue to a
# subscriber holds alone, so however long a loaded machine stalls the forwarder's sending or the node, none is
# dropped in transit and every one must be counted. Rounds of 3/4 of that queue and the node's together (300 of
# FWD_HWM + SUB_HWM) lost 72 of the last round in a CI run: such a round fits only while the node's side drains.
MALFORMED_ROUND = FWD_HWM * 3 // 4


def _rate_hz(reader: TopicReader, duration_s: float) -> float:
    """Publish rate from the pub_ns stamps of the messages read for `duration_s`."""
    stamps = []
    end = time.monotonic() + duration_s
    while time.monotonic() < end:
        item = reader.recv(timeout_s=max(0.0, end - time.monotonic()))
        if item is not None:
            stamps.append(item.msg.pub_ns)
    assert len(stamps) > 2, "the talker published nothing"
    return (len(stamps) - 1) / ((stamps[-1] - stamps[0]) / 1e9)


def test_slow_subscriber_does_not_slow_the_publisher(bus: Bus, spawn) -> None:
    spawn("node", "listener", "--name", "slow", "-p", "sleep_s=1.0", "-p", "depth=5")
    wait_status("slow")
    with TopicReader(["/chatter"]) as reader:
        spawn("node", "talker", "-p", "rate_hz=20")
        assert reader.recv(timeout_s=5.0) is not None
        rate = _rate_hz(reader, 2.5)
    assert rate >= 0.9 * 20, f"talker fell to {rate:.1f} Hz with a slow subscriber"
    st = wait_status("slow", lambda s: s.counters.get("received", 0) >= 1 and s.drops > 0, timeout_s=4.0)
    assert st.counters["received"] <= 4, "the slow listener sleeps 1 s per message"


def _malformed_messages(rng: random.Random, count: int) -> list[list[bytes]]:
    """`count` messages for /fuzz that each must be rejected: random bytes, truncated
    headers, missing / short / extra array frames, unknown fields, bad versions."""
    rs = np.random.default_rng(rng.randrange(2**32))
    samples = [
        SlipState(probability=0.3, window_stamps_ns=np.arange(10)),
        Image(data=rs.integers(0, 256, (8, 8), dtype=np.uint8)),
        MarkerArray(ref_px=np.ones((4, 2), np.float32), cur_px=np.ones((4, 2), np.float32),
                    valid=np.ones(4, bool), frames_since_seen=np.zeros(4, np.int32), width=8, height=8),
        DisplacementField(field=np.ones((3, 3, 3), np.float32), grid_x_px=np.arange(3.0), grid_y_px=np.arange(3.0)),
    ]
    out = []
    for seq in range(count):
        msg = rng.choice(samples)
        msg.seq, msg.node = seq, "fuzzer"
        frames = [bytes(f) for f in msgs.encode(msg)]
        case = seq % 6
        if case == 0:  # random bytes, random number of frames
            frames = [rs.bytes(rng.randrange(0, 120)) for _ in range(rng.randrange(1, 4))]
        elif case == 1:  # header cut short
            frames[0] = frames[0][:rng.randrange(len(frames[0]))]
        elif case == 2:  # an array frame missing, or an extra one
            frames = frames[:-1] if rng.random() < 0.5 else frames + [b"\0" * 8]
        elif case == 3:  # an array frame cut short
            i = rng.randrange(1, len(frames))
            frames[i] = frames[i][:rng.randrange(len(frames[i]))]
        else:  # a header field changed to nonsense
            header = msgpack.unpackb(frames[0])
            key, value = rng.choice([("version", 2), ("fields", {"bogus": 1}), ("arrays", [["x", "<f4", [1]]]),
                                     ("type", "Nope"), ("seq", "7"), ("stamp_ns", 1.5), ("seq", -1),
                                     ("stamp_ns", 2**63), ("pub_ns", 2**64 - 1)])
            header[key] = value if key != "fields" else {**header["fields"], **value}
            frames[0] = msgpack.packb(header, use_bin_type=True)
        out.append([envelope("/fuzz", "fuzzer", False), *frames])
    out.append([envelope("/fuzz", "fuzzer", False), b""])  # envelope and an empty header
    out.append([envelope("/fuzz", "fuzzer", False)])       # envelope alone
    return out[-count:]


def _await_subscription(pub: zmq.Socket, first_frame: bytes, timeout_s: float = 10.0) -> None:
    """Wait until the XPUB socket ``pub`` has a subscription that a message whose first frame is ``first_frame``
    matches: a message sent before is dropped unseen (0.3 s was waited, which a loaded machine can overrun)."""
    deadline = time.monotonic() + timeout_s
    while pub.poll(max(0, int((deadline - time.monotonic()) * 1000))):
        subscription = pub.recv()
        if subscription[:1] == b"\x01" and first_frame.startswith(subscription[1:]):
            return
    raise AssertionError(f"no subscription matching {first_frame!r} reached the publisher within {timeout_s} s")


def test_malformed_messages_are_counted_and_never_crash(bus: Bus, spawn) -> None:
    node = spawn("node", "listener", "--name", "victim", "-p", "topic=/fuzz", "-p", f"depth={N_MALFORMED * 2}")
    wait_status("victim")
    raw = zmq.Context.instance().socket(zmq.XPUB)  # a publisher that also hears the subscriptions reaching it
    raw.linger = 1000
    raw.sndhwm = N_MALFORMED * 2
    raw.connect(bus.address.pub)
    _await_subscription(raw, envelope("/fuzz", "fuzzer", False))
    messages = _malformed_messages(random.Random(7), N_MALFORMED)
    for start in range(0, N_MALFORMED, MALFORMED_ROUND):
        for frames in messages[start:start + MALFORMED_ROUND]:
            raw.send_multipart(frames)
        sent = min(start + MALFORMED_ROUND, N_MALFORMED)
        wait_status("victim", lambda s: s.malformed >= sent, timeout_s=10.0)
    raw.send_multipart([envelope("/fuzz", "fuzzer", False), *msgs.encode(SlipState(seq=N_MALFORMED + 5))])
    st = wait_status("victim", lambda s: s.malformed >= N_MALFORMED and s.counters.get("received") == 1,
                     timeout_s=10.0)
    raw.close()
    assert node.poll() is None, "the node died"
    assert st.malformed == N_MALFORMED and st.drops == 0 and st.errors == 0


def test_params_defaults_launch_file_and_param_flag(bus: Bus, spawn, tmp_path) -> None:
    spawn("node", "listener", "--name", "plain")
    spawn("node", "listener", "--name", "flagged", "--params-json", '{"topic": "/from_json", "depth": 3}',
          "-p", "topic=/from_flag")
    launch_file = tmp_path / "l.yaml"
    launch_file.write_text("args: {t: /from_arg_default}\n"
                           "nodes:\n  - {kind: listener, name: launched, params: {topic: $(arg t)}}\n"
                           "  - {kind: listener, name: launched2, params: {topic: /from_file}}\n")
    spawn("launch", str(launch_file), "t:=/from_cmdline")
    expected = {"plain": "/chatter", "flagged": "/from_flag", "launched": "/from_cmdline", "launched2": "/from_file"}
    for name, topic in expected.items():
        st = wait_status(name, timeout_s=8.0)
        assert [t for t, _ in st.subscribes] == [topic], name


def test_bad_param_fails_at_start_naming_the_key(bus: Bus) -> None:
    result = run_fv("node", "talker", "-p", "rate_hz=fast")
    assert result.returncode == 2 and "rate_hz" in result.stderr and "float" in result.stderr
    result = run_fv("node", "talker", "-p", "speed=1")
    assert result.returncode == 2 and "unknown param 'speed'" in result.stderr



class Recorder(Node):
    """Records the stamps of what it handles on /a and /b; its callbacks wait for `gate`."""

    def setup(self) -> None:
        self.gate = threading.Event()
        self.handled: list[tuple[str, int]] = []  # (topic, stamp_ns) in the order handled
        self.subs = {t: self.subscribe(t, SlipState, lambda msg, t=t: self.on_msg(t, msg), depth=None)
                     for t in ("/a", "/b")}

    def on_msg(self, topic: str, msg: SlipState) -> None:
        self.gate.wait(10.0)
        self.handled.append((topic, msg.stamp_ns))


def test_messages_of_different_topics_are_handled_in_the_order_they_arrived(bus: Bus) -> None:
    """A node behind (its callback busy) handles what queued up in arrival order, whatever the topic: a
    tracker's new reference before the field of that frame (taken in turns by topic, the field could come
    first and be left out of the grasp, or judged with the grasp before)."""
    node = Recorder("recorder")
    sent = [("/a", 1), ("/b", 2), ("/b", 3), ("/a", 4), ("/b", 5), ("/a", 6), ("/a", 7), ("/b", 8)]
    with spinning(node):
        wait_status("recorder", timeout_s=5.0)
        pub = PublisherSocket("sender")
        assert pub.wait_connected(5.0)
        # stamp 0 until the subscription is through: its callback then waits
        wait_for(lambda: node.subs["/a"].received, 5.0, "an /a reaching the node", period_s=0.05,
                 between=lambda: pub.publish("/a", SlipState()))
        for topic, stamp in sent:
            pub.publish(topic, SlipState(stamp_ns=stamp))
        # one publisher's messages arrive in order: with the last /b, all are queued
        wait_for(lambda: node.subs["/b"].received == 4, 5.0, "the messages reaching the node")
        node.gate.set()
        wait_for(lambda: len(node.handled) == node.subs["/a"].received + 4, 5.0, "the node handling them")
        pub.close()
    assert [h for h in node.handled if h[1]] == sent


class Stage(Node):
    """A pipeline stage: answers on `out` the messages on `in` stamped a multiple of 3, returns without an answer
    for those one more, raises for the others; never answers what comes on `other`."""

    def setup(self) -> None:
        self.out = self.publisher("out", SlipState)
        self.inputs = self.subscribe("in", SlipState, self.on_in, depth=None, answered_by=self.out)
        self.subscribe("other", SlipState, lambda msg: None, depth=None)

    def on_in(self, msg: SlipState) -> None:
        if msg.stamp_ns % 3 == 2:
            raise ValueError("a stage that fails")
        if msg.stamp_ns % 3 == 0:
            self.out.publish(SlipState(stamp_ns=msg.stamp_ns))


def test_a_message_a_stage_leaves_unanswered_is_said_on_unanswered(bus: Bus) -> None:
    """A message whose callback publishes nothing on the subscription's `answered_by` publisher, returning or
    raising, is said on `unanswered` in the node's namespace, with its stamp and topic (a batch replay's
    player then sends the next frame at once); an answered one and one of a subscription without
    `answered_by` are not."""
    node = Stage("stage", namespace="left")
    with spinning(node), TopicReader(["/left/unanswered", "/left/out"]) as reader:
        wait_status("stage", timeout_s=5.0)
        pub = PublisherSocket("sender")
        assert pub.wait_connected(5.0)
        wait_for(lambda: pub.has_subscribers("/left/in") and pub.has_subscribers("/left/other"), 5.0,
                 "the stage subscribing")
        pub.publish("/left/other", SlipState(stamp_ns=100))
        for stamp in range(1, 7):
            pub.publish("/left/in", SlipState(stamp_ns=stamp))
        got = [reader.recv(5.0) for _ in range(6)]
        assert reader.recv(0.3) is None
        pub.close()
    assert all(item is not None for item in got), got
    assert sorted(item.msg.stamp_ns for item in got if item.topic == "/left/out") == [3, 6]
    notices = [(item.msg.stamp_ns, item.msg.topic, item.msg.node) for item in got if item.topic == "/left/unanswered"]
    assert sorted(notices) == [(s, "/left/in", "stage") for s in (1, 2, 4, 5)]


def test_nodes_never_closed_do_not_block_the_next_ones(bus: Bus) -> None:
    """A node dropped without close() keeps its control socket bound; the next node got the same inproc
    address (from the dropped one's id()) and failed to start: `Address already in use`."""
    left_open = []
    try:
        for k in range(20):
            node = Node(f"dropped{k}")
            left_open += [node._ctl_out, node._pub_sock]  # as a node never closed: they stay open
            del node
            gc.collect()
    finally:
        for sock in left_open:
            sock.close()


class LateReceiver(Node):
    """A node whose receiving thread connects only once `connect` is set."""

    def __init__(self, name: str) -> None:
        super().__init__(name)
        self.connect = threading.Event()

    def _receive_loop(self) -> None:
        self.connect.wait(30.0)
        super()._receive_loop()


def test_a_node_stops_before_its_receiver_has_connected(bus: Bus) -> None:
    """A node stopped before its receiving thread had connected its control socket waited in close() until that
    thread connected (its "stop" could not be sent), with no limit; the thread, once connected, finds the node
    stopped and ends."""
    node = LateReceiver("late")
    thread = threading.Thread(target=node.spin, kwargs={"install_signals": False}, daemon=True)
    thread.start()
    wait_for(lambda: node._receiver is not None and not node._starting, 10.0, "the node set up")
    node.stop()
    thread.join(5.0)
    stopped = not thread.is_alive()
    node.connect.set()
    assert stopped, "close() waited for the receiver"
    node._receiver.join(5.0)
    assert not node._receiver.is_alive()


def test_a_subscription_made_before_the_receiver_has_connected_does_not_wait_and_gets_its_messages(
        bus: Bus) -> None:
    """subscribe() after setup told the receiving thread on its control socket, and waited, with no limit, while
    that thread had not connected it. It returns at once; the thread, once connected, subscribes the topic."""
    node = LateReceiver("late_sub")
    got: list[SlipState] = []
    with spinning(node):
        wait_for(lambda: node._receiver is not None and not node._starting, 10.0, "the node set up")
        subscribed = threading.Event()
        threading.Thread(target=lambda: (node.subscribe("/late", SlipState, got.append), subscribed.set()),
                         daemon=True).start()
        returned = subscribed.wait(5.0)
        node.connect.set()
        assert returned, "subscribe() waited for the receiver"
        pub = PublisherSocket("sender")
        assert pub.wait_connected(5.0)
        wait_for(lambda: got, 10.0, "a message on /late reaching the callback", period_s=0.05,
                 between=lambda: pub.publish("/late", SlipState(stamp_ns=7)))
        pub.close()
    assert got[0].stamp_ns == 7


SUBSCRIBING_THREADS = 16
TOPICS_PER_THREAD = 100


def test_subscriptions_from_many_threads_at_once_all_get_their_messages(bus: Bus) -> None:
    """Each of 1,600 topics subscribed from 16 threads at once (started together) gets its message, and a
    subscription made after the node closed is dropped without an error. Two things lost some: the forwarder's
    queue of subscriptions to a publisher held 1,000 (two per topic), and dropped the rest without a word (4 of 5
    runs failed); and subscribe() told the receiving thread of a new topic on one ZeroMQ socket, not thread-safe,
    from every thread at once (one run of 800 topics aborted the process in ZeroMQ)."""
    node = Node("many_subs")
    got: dict[str, list[SlipState]] = {}
    errors: list[BaseException] = []
    start = threading.Barrier(SUBSCRIBING_THREADS)

    def subscribe_many(first: int) -> None:
        try:
            start.wait(5.0)
            for n in range(first, first + TOPICS_PER_THREAD):
                node.subscribe(f"/t{n}", SlipState, got.setdefault(f"/t{n}", []).append)
        except BaseException as exc:  # noqa: BLE001 (reported by the assertion below)
            errors.append(exc)

    with spinning(node):
        wait_for(lambda: node._receiver is not None and not node._starting, 10.0, "the node set up")
        threads = [threading.Thread(target=subscribe_many, args=(k * TOPICS_PER_THREAD,), daemon=True)
                   for k in range(SUBSCRIBING_THREADS)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(10.0)
        assert not errors, errors
        pub = PublisherSocket("sender")
        assert pub.wait_connected(5.0)

        def publish_missing() -> None:
            for topic, messages in got.items():
                if not messages:
                    pub.publish(topic, SlipState(stamp_ns=1))

        wait_for(lambda: len(got) == SUBSCRIBING_THREADS * TOPICS_PER_THREAD and all(got.values()), 20.0,
                 "a message on each topic reaching its callback", period_s=0.05, between=publish_missing)
        pub.close()
    node.subscribe("/after_close", SlipState, lambda msg: None)


@pytest.mark.parametrize("text, kind", [("[1]", "a list"), ('"x"', "a string"), ("3", "a number")])
def test_params_json_that_is_not_an_object_is_refused(bus_env: Bus, text: str, kind: str) -> None:
    """`--params-json '[1]'` gave a traceback (AttributeError: 'list' object has no attribute 'update')."""
    result = run_fv("node", "camera", "--params-json", text)
    assert result.returncode == 2
    assert result.stderr == f"fv node: error: --params-json must be a JSON object (got {kind})\n"
