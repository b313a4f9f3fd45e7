"""`fv topic ...` and `fv node list` against running nodes: outputs parse and agree
with what the nodes do."""
from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
import time
from typing import Callable, Iterator

import pytest

import msgs
from msgs import NodeStatus, SlipState
from nodes.bus import PublisherSocket, TopicReader
from nodes.topic_tools import build_message
from tests.nodes.conftest import REPO, Bus, run_fv, wait_for, wait_status


_STARTED: list[subprocess.Popen] = []  # `_start`'s processes, killed as their test ends (`_end_started`)


def _start(*args: str) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", "nodes.cli", *args], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    _STARTED.append(proc)
    return proc


@pytest.fixture(autouse=True)
def _end_started() -> Iterator[None]:
    """Every `fv` process a test started with `_start` ends with the test, passed or failed: one that a failed
    assertion left (an `fv topic pub` that a Ctrl-C did not stop) ran on after the suite."""
    yield
    while _STARTED:
        proc = _STARTED.pop()
        proc.kill()
        proc.communicate()


def _finish(proc: subprocess.Popen, timeout_s: float = 15.0) -> str:
    try:
        out, err = proc.communicate(timeout=timeout_s)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    return out


def test_introspection_outputs_parse(bus: Bus, spawn) -> None:
    spawn("node", "talker", "-p", "rate_hz=20")
    spawn("node", "listener")
    wait_status("listener", lambda st: st.counters.get("received", 0) > 0, timeout_s=8.0)
    procs = {
        "echo": _start("topic", "echo", "/chatter", "--count", "3", "--json", "--timeout", "5"),
        "hz": _start("topic", "hz", "/chatter", "--duration", "2", "--json"),
        "bw": _start("topic", "bw", "/chatter", "--duration", "1", "--json"),
        "delay": _start("topic", "delay", "/chatter", "--duration", "1", "--json"),
        "list": _start("topic", "list", "--json"),
        "info": _start("topic", "info", "/chatter", "--json"),
        "nodes": _start("node", "list", "--json"),
    }
    out = {name: _finish(proc) for name, proc in procs.items()}

    echoed = [json.loads(line) for line in out["echo"].splitlines()]
    assert len(echoed) == 3 and {e["type"] for e in echoed} == {"SlipState"}
    assert all(0.0 <= e["probability"] <= 1.0 and e["node"] == "talker" for e in echoed)
    assert echoed[0]["window_stamps_ns"] == {"dtype": "<i8", "shape": [0], "data": []}

    hz = json.loads(out["hz"])
    assert hz["topic"] == "/chatter" and 20 * 0.8 <= hz["rate_hz"] <= 20 * 1.2 and hz["window"] >= 20
    bw = json.loads(out["bw"])
    assert bw["mean_bytes"] > 50 and bw["bytes_per_s"] > 20 * 50 * 0.5
    delay = json.loads(out["delay"])
    assert 0 <= delay["transport_ms"] <= delay["delay_ms"] < 1000

    topics = {t["topic"]: t for t in json.loads(out["list"])}
    assert topics["/chatter"]["publishers"] == ["talker"] and topics["/chatter"]["subscribers"] == ["listener"]
    assert topics["/chatter"]["types"] == ["SlipState"] and "/status" in topics
    info = json.loads(out["info"])
    assert info == topics["/chatter"]
    nodes = {n["name"]: n for n in json.loads(out["nodes"])}
    assert set(nodes) == {"talker", "listener"} and nodes["listener"]["counters"]["received"] > 0


def test_pub_reaches_a_subscriber(bus: Bus) -> None:
    with TopicReader(["/cmd"]) as reader:
        proc = _start("topic", "pub", "/cmd", "SlipState", "{probability: 0.9, slip: true}", "--count", "3",
                      "--rate", "20")
        got = [reader.recv(timeout_s=5.0) for _ in range(3)]
        _finish(proc)
    assert all(g is not None and g.msg.slip and g.msg.probability == 0.9 for g in got)
    assert [g.msg.seq for g in got] == [0, 1, 2]


def test_latched_pub_reaches_a_later_echo_while_it_runs(bus: Bus) -> None:
    """A latched message goes with its publisher, as in ROS: `fv topic pub --latched` stays after its
    last message until Ctrl-C, and an echo started after that gets nothing. (The forwarder held it for
    good: an echo or a recorder joining after a session got that session's messages as live ones.)"""
    pub = _start("topic", "pub", "/info", "CameraInfo", "{width: 640, height: 480, K: [[1, 0, 0], [0, 1, 0], "
                 "[0, 0, 1]]}", "--once", "--latched")
    try:
        assert pub.stdout.readline().startswith("publishing #1")
        assert "kept for later subscribers until Ctrl-C" in pub.stdout.readline()
        for k in range(2):
            result = run_fv("topic", "echo", "/info", "--once", "--json", "--timeout", "3")
            assert result.returncode == 0, result.stderr
            info = json.loads(result.stdout)
            assert info["width"] == 640 and info["K"]["data"] == [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
            if k == 0:  # another publisher leaves: the forwarder asks which latched messages have theirs
                passer = PublisherSocket("passer")
                assert passer.wait_connected(2.0)
                passer.close()
                time.sleep(1.5)
    finally:
        pub.send_signal(signal.SIGINT)
        assert pub.wait(10) == 130
    time.sleep(1.5)
    result = run_fv("topic", "echo", "/info", "--once", "--timeout", "1")
    assert result.returncode == 1 and "no message on /info" in result.stderr


def test_echo_times_out_and_info_knows_no_topic(bus: Bus) -> None:
    result = run_fv("topic", "echo", "/nothing", "--timeout", "0.3")
    assert result.returncode == 1 and "no message on /nothing" in result.stderr
    result = run_fv("topic", "info", "/nothing", "--wait", "0.2")
    assert result.returncode == 1 and "/nothing" in result.stderr


def test_measures_of_too_few_messages_are_null_and_no_bus_is_an_error(bus_env: Bus) -> None:
    """`fv topic hz --json` on a silent topic printed NaN (not JSON); `fv topic list` and `fv node list`
    printed [] with status 0 when nothing served the bus, as if it served no node."""
    for verb in ("list",):
        for group in ("topic", "node"):
            result = run_fv(group, verb, "--json")
            assert result.returncode == 2 and "no forwarder answers on ipc://" in result.stderr, result.stderr
    for tool in (["echo", "/slip", "--count", "1"], *([v, "/slip", "--duration", "0.3"] for v in ("hz", "bw", "delay"))):
        result = run_fv("topic", *tool, timeout_s=20)  # echo waited for good; hz / bw / delay reported 0 Hz, status 0
        assert result.returncode == 2 and "no forwarder answers on ipc://" in result.stderr, (tool, result.stderr)
    bus_env.start_forwarder()
    result = run_fv("topic", "hz", "/silent", "--duration", "0.5", "--json")
    report = json.loads(result.stdout)  # strict JSON: no NaN
    assert result.returncode == 0 and report["min_s"] is None and report["rate_hz"] == 0.0 and report["window"] == 0
    for tool in ("hz", "bw", "delay"):  # as text: "min: nans max: nans std dev: nans"
        text = run_fv("topic", tool, "/silent", "--duration", "0.3").stdout
        assert "nan" not in text and "min: n/a max: n/a" in text, text


@pytest.mark.parametrize("type_name, text, match", [
    ("SlipState", "{probabilty: 0.9}", r"^SlipState\.probabilty: no such field; SlipState has \['frame_id', 'model', "
                                       r"'probability', 'slip', 'stamp_ns', 'threshold', 'valid', 'window_stamps_ns'\]$"),
    ("SlipState", "{probability: 2.0}", "probability"),
    ("SlipState", "{slip: 1}", "slip"),
    ("SlipState", "{seq: 4}", "seq"),
    ("Image", "{data: [[1, 2], [3]]}", "data"),
    ("Slip", "{}", "unknown message type"),
    ("SlipState", "[1, 2]", "mapping"),
    ("SlipState", "{stamp_ns: 1180591620717411303424}", r"stamp_ns: 1180591620717411303424 is not in \[0, 2\*\*63\)"),
    ("SlipState", "{stamp_ns: -1}", "stamp_ns"),
    ("SlipState", "{threshold: -1}", "threshold"),
    ("MarkerArray", "{width: 0}", "width/height: 0x0"),
    ("SlipState", "{probability: x}", r"^SlipState: field 'probability' = 'x' is not of type float$"),  # said "param"
])
def test_pub_fields_errors_name_the_field(type_name: str, text: str, match: str) -> None:
    with pytest.raises((ValueError, KeyError), match=match):
        build_message(type_name, text)


@pytest.mark.parametrize("wait", ["-1", "nan"])
def test_pub_refuses_a_wait_for_subscribers_that_is_no_time(wait: str) -> None:
    """`--wait-matching -1` and `nan` were taken (a wait of no time, or none at all), said nothing."""
    result = run_fv("topic", "pub", "/x", "SlipState", "{}", "--once", f"--wait-matching={wait}")
    assert result.returncode == 2 and f"--wait-matching: {wait} is not a finite number >= 0" in result.stderr


def test_pub_builds_arrays_in_the_field_dtype() -> None:
    msg = build_message("SlipState", "{window_stamps_ns: [1, 2, 3], model: m}")
    assert isinstance(msg, SlipState) and msg.window_stamps_ns.dtype.kind == "i" and msg.model == "m"


def test_hz_counts_a_played_bag_whose_messages_keep_their_recorded_pub_ns(bus: Bus) -> None:
    """A bag played keeps every message's recorded pub_ns: `fv topic hz` took them all for latched
    replays older than its start and printed 0 Hz."""
    pub = PublisherSocket("bag_play", bus.address)
    assert pub.wait_connected(2.0)
    stop = threading.Event()

    def play() -> None:  # 50 Hz of messages recorded an hour ago
        seq = 0
        while not stop.is_set():
            msg = SlipState(stamp_ns=time.time_ns() - 3_600_000_000_000)
            msg.seq, msg.node, msg.pub_ns = seq, "slip_detector", msg.stamp_ns + 1000
            pub.publish_raw("/slip", "slip_detector", False, msgs.encode(msg))
            seq += 1
            time.sleep(0.02)

    thread = threading.Thread(target=play)
    thread.start()
    try:
        hz = json.loads(_finish(_start("topic", "hz", "/slip", "--duration", "2", "--json")))
    finally:
        stop.set()
        thread.join()
        pub.close()
    assert 50 * 0.7 <= hz["rate_hz"] <= 50 * 1.2, hz


@pytest.mark.parametrize("args, says", [
    (("topic", "hz", "/slip", "--window", "0"), "--window/-w: '0' is not a whole number >= 2"),  # said 0.0 Hz
    (("topic", "bw", "/slip", "-w", "1"), "'1' is not a whole number >= 2"),
    (("topic", "echo", "/slip", "--count", "-1"), "--count/-n: -1 is not >= 1"),  # exited 0 silently
    (("topic", "pub", "/tq", "SlipState", "{stamp_ns: 1180591620717411303424}"), "stamp_ns"),  # msgpack traceback
    (("topic", "echo", ""), "topic '': must start with '/'"),  # an unset variable: echoed every topic
    (("topic", "info", "slip"), "topic 'slip': must start with '/'"),  # "no running node publishes 'slip'"
])
def test_bad_topic_arguments_are_usage_errors(args: tuple, says: str) -> None:
    result = run_fv(*args)
    assert result.returncode == 2 and says in result.stderr and "Traceback" not in result.stderr, result.stderr


def test_a_malformed_latched_status_is_skipped_and_named(bus: Bus) -> None:
    """`fv topic pub /status NodeStatus '{publishes: [x], ...}' --latched` broke `fv topic list` and
    `fv topic info` for everyone on the bus ("not enough values to unpack")."""
    from nodes.node import Node

    good = PublisherSocket("good_node")
    bad = PublisherSocket("bad_node")
    assert good.wait_connected(2.0) and bad.wait_connected(2.0)
    bad.publish("/status", NodeStatus(publishes=["x"], subscribes=[["/a", "B", "C"]]), latched=True)
    stop = threading.Event()

    def alive() -> None:  # as a node's status thread: a status older than 3 s is a node gone
        while True:
            good.publish("/status", NodeStatus(stamp_ns=time.time_ns(), publishes=[["/g", "SlipState"]]),
                         latched=True)
            if stop.wait(Node.STATUS_PERIOD_S):
                return

    thread = threading.Thread(target=alive)
    thread.start()
    try:
        for args, shows in ((("topic", "list"), "/g"), (("topic", "info", "/g"), "good_node"),
                            (("node", "list"), "good_node")):
            result = run_fv(*args, "--wait", "0.5")
            assert result.returncode == 0 and shows in result.stdout, result.stderr
            assert "skipped a bad status" in result.stderr and "'bad_node'" in result.stderr, result.stderr
    finally:
        stop.set()
        thread.join()
        good.close()
        bad.close()


def _silent(line: str) -> bool:
    """A line of `fv topic hz` that says no message came in its second."""
    return line == "no new messages\n" or '"new_messages": 0,' in line


def _hz_lines_around_a_burst(pub: PublisherSocket, done: Callable[[list[str]], bool], *args: str) -> list[str]:
    """The lines `fv topic hz /burst *args` prints while 40 messages come in 2 s, to the first for which
    `done(lines)`, or 12 lines."""
    proc = _start("topic", "hz", "/burst", *args)
    try:
        wait_for(lambda: pub.has_subscribers("/burst") or proc.poll() is not None, 10.0, "hz subscribing",
                 period_s=0.05)
        assert proc.poll() is None, "hz never subscribed"
        for _ in range(40):
            pub.publish("/burst", SlipState())
            time.sleep(0.05)
        lines: list[str] = []
        while len(lines) < 12 and not done(lines):
            lines.append(proc.stdout.readline())
        return lines
    finally:
        proc.kill()
        proc.wait(5)


def _all_then_silent(lines: list[str]) -> bool:
    """JSON lines of `fv topic hz`: the burst's 40 messages counted, then a second without any (a burst
    held up a second, on a loaded machine, has a silent second inside it)."""
    return sum(json.loads(line)["new_messages"] for line in lines) == 40 and _silent(lines[-1])


def _silent_after_a_report(lines: list[str]) -> bool:
    """Text lines of `fv topic hz`: "no new messages" after a report of some."""
    return len(lines) > 1 and _silent(lines[-1]) and not _silent(lines[-2])


def test_each_second_s_report_says_when_no_new_message_came(bus: Bus) -> None:
    """`fv topic hz /slip` went on printing the last rate ("average rate: 15.070") every second after the
    pipeline had stopped, and printed text with `--json`: now each second is a JSON line with its
    `new_messages`, and as text a silent second says "no new messages"."""
    pub = PublisherSocket("burst")
    assert pub.wait_connected(2.0)
    try:
        seconds = [json.loads(line) for line in _hz_lines_around_a_burst(pub, _all_then_silent, "--json")]
        text = _hz_lines_around_a_burst(pub, _silent_after_a_report)
    finally:
        pub.close()
    counts = [s["new_messages"] for s in seconds]
    assert sum(counts) == 40 and counts[-1] == 0, counts
    assert seconds[-1]["rate_hz"] > 0 and seconds[-1]["topic"] == "/burst"
    assert any(line.startswith("average rate") for line in text) and text[-1] == "no new messages\n", text


def test_echo_names_the_malformed_messages_it_skips(bus: Bus) -> None:
    """`fv topic echo /x` printed nothing while a publisher sent /x messages every subscriber dropped as
    malformed, then "no message on /x": the one tool to look at a topic hid what was wrong with it."""
    pub = PublisherSocket("sender")
    assert pub.wait_connected(2.0)
    proc = _start("topic", "echo", "/x", "--timeout", "10", "--count", "1")
    try:
        wait_for(lambda: pub.has_subscribers("/x") or proc.poll() is not None, 10.0,  # the echo's subscription
                 "the echo subscribing", period_s=0.05)  # has reached this publisher
        assert proc.poll() is None, "the echo never subscribed"
        bad = msgs.encode(SlipState())
        bad[0] = bad[0].replace(b"probability", b"probabilitx")
        pub.publish_raw("/x", "bad_node", False, bad)
        pub.publish("/x", SlipState(probability=0.25))
        out, err = proc.communicate(timeout=15)
    finally:
        proc.kill()
        pub.close()
    assert "probability: 0.25" in out, (out, err)
    assert "fv topic echo: skipped a malformed message: bad message on topic '/x', type 'SlipState', field " \
           "'probability': missing (from node 'bad_node')" in err, err
