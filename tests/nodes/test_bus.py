"""The bus: cross-process delivery, exact topic matching, latching, CURVE on TCP, and the
robot-code client (including the README snippet, verbatim)."""
from __future__ import annotations

import copy
import os
import pickle
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
import msgpack
import pytest
import zmq

import msgs
from msgs import CameraInfo, MarkerArray, NodeStatus, SlipState
from nodes.bus import PublisherSocket, SeqTracker, TopicReader, envelope, parse_envelope
from nodes.endpoints import BUS_ENV, CURVE_ENV, bus_address, make_keys, secure_server
from nodes.forwarder import (Forwarder, ForwarderRunning, ForwarderStart, ensure_forwarder, lock_path, ping,
                             silent_forwarder)
from nodes.params import ParamError
from tests.nodes.conftest import REPO, Bus, poll_until, run_fv, wait_for


def _publish_until(stop: threading.Event, sock: PublisherSocket, items: list[tuple[str, object]],
                   period_s: float = 0.02) -> threading.Thread:
    """Publish `items` ((topic, message)) round-robin from a thread until `stop`."""
    def loop() -> None:
        while not stop.is_set():
            for topic, msg in items:
                sock.publish(topic, msg)
            time.sleep(period_s)
    thread = threading.Thread(target=loop, daemon=True)
    thread.start()
    return thread


def test_envelope_round_trip_and_rejects_garbage() -> None:
    assert parse_envelope(envelope("/slip", "det", True)) == ("/slip", "det", True)
    assert parse_envelope(envelope("/slip", "", False)) == ("/slip", "", False)
    for bad in (b"", b"X/slip\0n", b"-/slip", b"L"):
        with pytest.raises(ValueError):
            parse_envelope(bad)


def test_cross_process_publish_subscribe(bus: Bus, spawn) -> None:
    with TopicReader(["/chatter"]) as reader:
        spawn("node", "talker", "-p", "rate_hz=50")
        got = [reader.recv(timeout_s=5.0) for _ in range(5)]
    assert all(g is not None for g in got), "talker messages did not arrive"
    assert {g.msg.node for g in got} == {"talker"} and {g.topic for g in got} == {"/chatter"}
    seqs = [g.msg.seq for g in got]
    assert seqs == sorted(seqs) and len(set(seqs)) == 5
    assert all(isinstance(g.msg, SlipState) for g in got)


def test_exact_topic_matching(bus: Bus) -> None:
    pub = PublisherSocket("pub", bus.address)
    assert pub.wait_connected(2.0)
    stop = threading.Event()
    with TopicReader(["/slip"]) as reader:
        thread = _publish_until(stop, pub, [("/slip_debug", SlipState(probability=0.1)),
                                            ("/slip", SlipState(probability=0.9)), ("/sli", SlipState())])
        try:
            got = [reader.recv(timeout_s=2.0) for _ in range(20)]
        finally:
            stop.set()
            thread.join()
            pub.close()
    assert all(g is not None for g in got)
    assert {g.topic for g in got} == {"/slip"} and {g.msg.probability for g in got} == {0.9}


def test_latched_message_reaches_late_joiner_once(bus: Bus) -> None:
    pub = PublisherSocket("camera", bus.address)
    assert pub.wait_connected(2.0)
    pub.publish("/camera_info", CameraInfo(width=640, height=480), latched=True)
    pub.publish("/image_note", SlipState())  # volatile: a late joiner never sees it
    time.sleep(0.2)
    try:
        with TopicReader(["/camera_info", "/image_note"]) as first:
            item = first.recv(timeout_s=2.0)
            assert item is not None and item.latched and item.msg.width == 640
            with TopicReader(["/camera_info"]) as second:  # its join replays the latched message to both
                assert second.recv(timeout_s=2.0).msg.width == 640
                assert first.recv(timeout_s=0.3) is None, "a replay seen before must be dropped"
    finally:
        pub.close()


LATCHED_SCRIPT = """
import sys, time
from nodes.client import advertise
from msgs import SlipState
with advertise("/grip/state", latched=True) as pub:
    pub.publish(SlipState(probability=float(sys.argv[1])))
    print("published", flush=True)
    sys.stdin.read()  # until the test closes it
"""


def test_two_scripts_latched_messages_on_one_topic_both_reach_a_late_subscriber(bus: Bus) -> None:
    """Robot code advertised under one default name, "robot": two scripts' latched messages on one topic were
    one publisher's to the bus, and a subscriber started later got only the last one's."""
    from nodes.client import subscribe

    scripts = [subprocess.Popen([sys.executable, "-c", LATCHED_SCRIPT, p], cwd=REPO, stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, text=True) for p in ("0.1", "0.9")]
    try:
        for script in scripts:
            assert script.stdout.readline().strip() == "published"
        with subscribe("/grip/state", timeout_s=5.0) as states:
            got = sorted((next(iter(states)), next(iter(states))), key=lambda m: m.probability)
        assert [m.probability for m in got] == [0.1, 0.9]
        assert {m.node for m in got} == {f"robot_{script.pid}" for script in scripts}
    finally:
        for script in scripts:
            script.stdin.close()
            script.wait(10)


def test_a_gone_publisher_s_latched_message_reaches_only_those_who_ask(bus: Bus) -> None:
    """A latched message goes with its publisher, as in ROS: on a forwarder left running, a reader
    joining after a session got that session's camera info as a live one (a bag recorded before the
    next session took it for its calibration). A subscription that asks for gone publishers' messages
    (a respawned tracker's, for its predecessor's reference) still gets it, flagged; an idle latched
    publisher keeps its message by answering the forwarder's refreshes."""
    from nodes.client import advertise
    from nodes.latched_cache import REFRESH_WAIT_S
    from nodes.node import Node

    old = PublisherSocket("old_camera", bus.address)
    assert old.wait_connected(2.0)
    old.publish("/camera/info", CameraInfo(width=640, height=480), latched=True)
    with advertise("/camera/info", name="camera", latched=True) as live:
        live.publish(CameraInfo(width=320, height=240))
        old.close()
        time.sleep(REFRESH_WAIT_S + 0.5)
        with TopicReader(["/camera/info"]) as late:
            got = [(item.msg.node, item.msg.width) for item in iter(lambda: late.recv(0.5), None)]
        assert got == [("camera", 320)]
        assert ping()["gone"] == ["L/camera/info\0old_camera"]
        asking = Node("resumer", address=bus.address)
        heard: list[tuple[str, int]] = []
        asking.subscribe("/camera/info", CameraInfo, lambda msg: heard.append((msg.node, msg.width)), gone=True)
        thread = threading.Thread(target=asking.spin, kwargs={"install_signals": False}, daemon=True)
        thread.start()
        try:
            poll_until(lambda: len(heard) >= 2, 5.0, period_s=0.05)
        finally:
            asking.stop()
            thread.join(5.0)
        assert sorted(heard) == [("camera", 320), ("old_camera", 640)]
    time.sleep(REFRESH_WAIT_S + 0.5)
    with TopicReader(["/camera/info"]) as after:
        assert after.recv(0.5) is None, "a closed publisher's latched message is gone"


def test_what_a_publisher_sent_before_it_left_is_gone_with_it(bus_env: Bus) -> None:
    """The forwarder read one message per turn, and the closed connection's event started the refresh
    while the rest of what that publisher had sent was still queued: read afterwards, it counted as
    answers, live until another publisher left (12 to 16 of 20 on a busy forwarder, in 2 runs of 6)."""
    from nodes.latched_cache import REFRESH_WAIT_S

    def serve(seconds: float) -> None:
        stop = threading.Event()
        thread = threading.Thread(target=forwarder.run, args=(stop,), daemon=True)
        thread.start()
        time.sleep(seconds)
        stop.set()
        thread.join(2.0)

    forwarder = Forwarder(bus_env.address)
    try:
        pub = PublisherSocket("burster", bus_env.address)
        serve(0.3)  # the forwarder takes the connection
        assert pub.wait_connected(2.0)
        for k in range(20):
            pub.publish(f"/t{k}", SlipState(), latched=True)
        pub.close()
        time.sleep(0.5)  # all of it queued, and the closed connection's event too, before the forwarder reads on
        serve(REFRESH_WAIT_S + 0.5)
        assert (len(forwarder.latched.live), len(forwarder.latched.gone)) == (0, 20)
    finally:
        forwarder.close()


def test_a_closed_forwarder_leaves_no_socket_files(bus_env: Bus) -> None:
    """A forwarder stopped cleanly left its IPC socket files: the next launch on the bus waited 0.3 s for an answer
    from them (`ensure_forwarder`'s quick look) before starting its own. Now a look there answers at once."""
    forwarder = Forwarder(bus_env.address)
    forwarder.close()
    left = [p.name for p in bus_env.folder.iterdir() if p.is_socket()]
    assert not left, left


def test_a_killed_forwarder_s_socket_files_are_told_from_a_serving_one_at_once(bus_env: Bus, spawn) -> None:
    """A forwarder killed with SIGKILL leaves its IPC socket files, and each ping waited its whole timeout for an
    answer that could not come (`fv topic list` 2.5 s after a crash). A connect to them is refused: a ping says
    None at once. A serving forwarder takes such a look as a peer that leaves (it says nothing and answers the
    next ping), and the next forwarder's bind replaces the files."""
    address = bus_env.address
    forwarder = spawn("forwarder", stderr=subprocess.PIPE, text=True)
    wait_for(lambda: ping(address, 0.2) is not None or forwarder.poll() is not None, 10.0, "the forwarder's start",
             period_s=0.0)
    assert forwarder.poll() is None, "the forwarder did not start"
    for _ in range(20):  # the look a ping takes first
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as look:
            look.connect(str(address.ipc_files[-1]))
    assert ping(address, 2.0)["pid"] == forwarder.pid
    forwarder.kill()
    forwarder.wait(5.0)
    assert forwarder.stderr.read().splitlines() == [f"[fv.forwarder] INFO: forwarder on {address.url}"]
    assert all(path.is_socket() for path in address.ipc_files), "a killed forwarder leaves its socket files"
    start = time.monotonic()
    assert ping(address, 5.0) is None
    assert time.monotonic() - start < 1.0, "a ping waited for an answer from a killed forwarder's socket file"
    restarted = ensure_forwarder(address)
    try:
        assert ping(address, 2.0)["pid"] == restarted.pid
    finally:
        restarted.terminate()
        restarted.wait(5.0)


def test_a_started_forwarder_that_never_answers_is_looked_at_then_stopped_and_reaped(
        bus_env: Bus, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """`ForwarderStart.answered` looks once without waiting for the answer (the launcher supervises its nodes
    between its looks): False while the process may still answer; past `timeout_s`, RuntimeError, the process
    stopped and reaped."""
    python = tmp_path / "python"  # a forwarder whose Python never starts
    python.write_text("#!/bin/sh\nexec sleep 60\n")
    python.chmod(0o755)
    monkeypatch.setattr(sys, "executable", str(python))
    start = ForwarderStart(bus_env.address, timeout_s=1.0)
    assert start.answered() is False and start.proc.returncode is None
    with pytest.raises(RuntimeError, match=f"forwarder for {bus_env.address.url} did not answer within 1.0 s"):
        poll_until(start.answered, 30.0)
    assert start.proc.returncode == -signal.SIGTERM, "the forwarder was left running or unreaped"


def test_a_forwarder_that_took_the_bus_as_another_started_is_not_taken_for_it(bus: Bus) -> None:
    """A forwarder started while another takes the bus (two launches at once) exits at its start, the bus's lock
    held; the other's answer was taken for its own (`answered` True, the launch supervising a process that had
    exited). The answer's pid tells them apart: ForwarderRunning naming the serving forwarder, which
    `ensure_forwarder` takes as the bus's (None), the one started stopped."""
    start = ForwarderStart(bus.address)
    with pytest.raises(ForwarderRunning, match=f"another forwarder \\(pid {os.getpid()}\\) serves {bus.address.url}"):
        poll_until(start.answered, 30.0)
    assert start.proc.returncode is not None, "the forwarder started was left running or unreaped"


def test_a_bus_held_by_a_stopped_forwarder_is_said_with_its_pid(bus_env: Bus, spawn) -> None:
    """A forwarder stopped in its terminal (Ctrl-Z) holds the bus and answers nothing: every launch started a
    forwarder of its own, which exited at its start, and said only "exited with code 2 at start"; the topic tools
    and a robot's SilenceError said that no forwarder runs, and a node started then told to start one. The lock file
    holds the pid of its forwarder, which all four name, saying what to do (a pickled SilenceError too)."""
    from nodes.client import SilenceError, wait_for_message

    held = spawn("forwarder")
    wait_for(lambda: ping(bus_env.address, 0.2) is not None, 10.0, "the forwarder's start")
    held.send_signal(signal.SIGSTOP)
    why = (f"forwarder pid {held.pid} holds the bus but is stopped (as by Ctrl-Z in its terminal): continue it "
           f"(kill -CONT {held.pid}) or end it, or use another FV_BUS")
    try:
        with pytest.raises(RuntimeError) as refused:
            ensure_forwarder(bus_env.address)
        listed = run_fv("topic", "list")
        with pytest.raises(SilenceError) as silence:
            wait_for_message("/slip", timeout_s=0.1, address=bus_env.address)
        silent = str(silence.value)
        node = spawn("node", "talker", stderr=subprocess.PIPE, text=True)
        warned = node.stderr.readline()  # after the node's CONNECT_WAIT_S
        node.kill()
    finally:
        held.send_signal(signal.SIGCONT)
    assert warned == f"[talker] WARNING: no forwarder answers on {bus_env.address.url}; {why} (waiting for it)\n"
    assert silent == f"no message on /slip within 0.1 s (no forwarder answers on {bus_env.address.url}: {why})"
    assert str(pickle.loads(pickle.dumps(silence.value))) == silent
    assert str(refused.value) == f"forwarder for {bus_env.address.url} exited with code 2 at start: {why}"
    assert listed.returncode != 0
    assert listed.stderr == f"fv topic: error: no forwarder answers on {bus_env.address.url}: {why}\n"
    assert ping(bus_env.address, 2.0)["pid"] == held.pid


def test_a_bus_lock_naming_a_live_forwarder_or_none_is_told_apart(bus_env: Bus) -> None:
    """`silent_forwarder` names the process the bus's lock file names only while it is a live forwarder: not once
    it is gone (a forwarder killed by SIGKILL leaves its pid there), nor another process given its pid since."""
    hung = subprocess.Popen(["fv forwarder", "60"], executable=shutil.which("sleep"))  # named as one, from its exec
    other = subprocess.Popen(["sleep", "60"])
    try:
        lock_path(bus_env.address).write_text(f"{hung.pid}\n")
        assert silent_forwarder(bus_env.address) == (f"forwarder pid {hung.pid} holds the bus but does not answer "
                                                     "(hung?): end it, or use another FV_BUS")
        lock_path(bus_env.address).write_text(f"{other.pid}\n")
        assert silent_forwarder(bus_env.address) == ""
        hung.kill()
        hung.wait(5.0)
        lock_path(bus_env.address).write_text(f"{hung.pid}\n")
        assert silent_forwarder(bus_env.address) == ""
    finally:
        for proc in (hung, other):
            proc.kill()
            proc.wait(5.0)


def test_a_launch_waits_for_a_slow_answer_from_a_serving_forwarder(bus: Bus, monkeypatch: pytest.MonkeyPatch) -> None:
    """`ensure_forwarder` looked 0.3 s for an answer, lest it wait for one from a killed forwarder's socket file
    (now told at once): a serving forwarder slow to answer on a loaded host was missed, and the second forwarder
    it started could not take the bus's lock ("exited with code 2 at start"). It waits as a ping does."""
    info = bus.forwarder.info

    def slow_info() -> dict:
        time.sleep(0.8)
        return info()

    monkeypatch.setattr(bus.forwarder, "info", slow_info)
    assert ensure_forwarder(bus.address) is None


def test_a_latched_message_published_before_any_forwarder_is_delivered(bus_env: Bus) -> None:
    """Only a reconnect re-sent latched messages: one published before the first forwarder answered (a
    camera's CameraInfo, when the camera started first) was dropped and never delivered."""
    pub = PublisherSocket("camera", bus_env.address)
    try:
        assert not pub.wait_connected(0.2)
        pub.publish("/camera/info", CameraInfo(width=640, height=480), latched=True)
        bus_env.start_forwarder()
        assert pub.wait_connected(5.0) and pub.reconnects == 0
        with TopicReader(["/camera/info"], bus_env.address) as reader:
            item = reader.recv(timeout_s=5.0)
            assert item is not None and item.latched and item.msg.width == 640
            assert reader.recv(timeout_s=0.3) is None, "delivered twice"
    finally:
        pub.close()


def _free_port_base() -> int:
    """A port p with p, p+1, p+2 free on 127.0.0.1."""
    for _ in range(50):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            base = s.getsockname()[1]
        if base > 65000:
            continue
        try:
            for p in (base + 1, base + 2):
                with socket.socket() as s:
                    s.bind(("127.0.0.1", p))
            return base
        except OSError:
            continue
    raise RuntimeError("no three consecutive free ports")


def test_secret_keys_are_the_owners_alone_and_never_replaced(tmp_path) -> None:
    """The CURVE secret keys were written world-readable (0644), and a second `fv keys` replaced every
    key without a word, locking out the hosts that hold the old client keys."""
    files = {p.name: p for p in make_keys(tmp_path / "keys")}
    modes = {name: path.stat().st_mode & 0o777 for name, path in files.items()}
    assert modes["server.key_secret"] == modes["client.key_secret"] == 0o600
    assert modes["server.key"] == modes["client.key"] == 0o644
    before = files["client.key_secret"].read_bytes()
    with pytest.raises(ValueError, match="holds keys already"):
        make_keys(tmp_path / "keys")
    assert files["client.key_secret"].read_bytes() == before


def test_tcp_needs_curve_keys(bus_env: Bus, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    keys = bus_env.folder / "keys"
    make_keys(keys)
    stranger = bus_env.folder / "stranger"  # right server key, client key not authorised
    make_keys(stranger)
    (stranger / "server.key").write_bytes((keys / "server.key").read_bytes())
    tcp = f"tcp://127.0.0.1:{_free_port_base()}"
    bus_env.start_forwarder(tcp_url=tcp, keys=keys)
    tcp_address = bus_address(tcp)
    pub = PublisherSocket("camera", bus_env.address)  # local publisher over IPC
    assert pub.wait_connected(2.0)

    plain = zmq.Context.instance().socket(zmq.SUB)  # no CURVE at all
    plain.linger = 0
    plain.setsockopt(zmq.SUBSCRIBE, b"")
    plain.connect(tcp_address.sub)
    monkeypatch.setenv(CURVE_ENV, str(stranger))
    unauthorised = TopicReader(["/slip"], tcp_address)
    monkeypatch.setenv(CURVE_ENV, str(keys))
    authorised = TopicReader(["/slip"], tcp_address)
    stop = threading.Event()
    thread = _publish_until(stop, pub, [("/slip", SlipState(probability=0.5))])
    try:
        got = authorised.recv(timeout_s=5.0)
        assert got is not None and got.msg.probability == 0.5, "the client with the keys received nothing"
        assert unauthorised.recv(timeout_s=0.5) is None
        assert not plain.poll(200), "a client without CURVE keys received data"
        refused = [r.getMessage() for r in caplog.records if "refuses the CURVE handshake" in r.getMessage()]
        assert refused == [f"the forwarder at {tcp} refuses the CURVE handshake (FV_CURVE_DIR {stranger}): it does "
                           "not know this host's client key: copy that client.key into its authorized/ folder; "
                           "nothing passes until it is fixed"]  # it received nothing and said nothing
    finally:
        stop.set()
        thread.join()
        for sock in (authorised, unauthorised, plain, pub):
            sock.close()


def test_a_tool_refused_by_the_forwarder_says_why(bus_env: Bus, monkeypatch: pytest.MonkeyPatch) -> None:
    """`fv topic list` with a client key the forwarder does not know said only that no launch runs."""
    keys, stranger = bus_env.folder / "keys", bus_env.folder / "stranger"
    make_keys(keys)
    make_keys(stranger)
    (stranger / "server.key").write_bytes((keys / "server.key").read_bytes())
    tcp = f"tcp://127.0.0.1:{_free_port_base()}"
    bus_env.start_forwarder(tcp_url=tcp, keys=keys)
    monkeypatch.setenv(BUS_ENV, tcp)
    monkeypatch.setenv(CURVE_ENV, str(stranger))
    result = run_fv("topic", "list", timeout_s=20)
    assert result.returncode == 2
    assert f"the forwarder at {tcp} refuses the CURVE handshake (FV_CURVE_DIR {stranger})" in result.stderr
    monkeypatch.setenv(CURVE_ENV, str(keys))
    assert "refuses" not in run_fv("topic", "list", timeout_s=20).stderr
    # the fix the message gives, done while the forwarder runs: it was taken only after a restart
    (keys / "authorized" / "stranger.key").write_bytes((stranger / "client.key").read_bytes())
    time.sleep(1.5)
    monkeypatch.setenv(CURVE_ENV, str(stranger))
    assert "refuses" not in run_fv("topic", "list", timeout_s=20).stderr


def test_a_tcp_port_in_use_is_one_line(bus_env: Bus) -> None:
    """`fv forwarder --tcp` on a port another program held ended in a ZMQError traceback."""
    keys = bus_env.folder / "keys"
    make_keys(keys)
    holder = zmq.Context.instance().socket(zmq.REP)
    holder.linger = 0
    port = holder.bind_to_random_port("tcp://127.0.0.1")
    try:
        with pytest.raises(ValueError, match=f"cannot listen on tcp://127.0.0.1:{port}: Address already in use"):
            Forwarder(address=bus_address(f"ipc://{bus_env.folder}/other"), tcp_url=f"tcp://127.0.0.1:{port}",
                      keys=keys)
    finally:
        holder.close()


def test_sockets_on_a_tcp_bus_leave_no_file_descriptors_behind(bus_env: Bus, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every socket on a TCP bus has a monitor that watches its CURVE handshake. Closed once the handshake
    succeeded, the monitor left 4 file descriptors behind per socket: 100 pings took about 400 in a process
    of their own, and one that had pinged a TCP forwarder 300 times could open no more sockets ("Too many
    open files"). The monitors' endpoints were named after the socket's file descriptor, which the next
    socket reused: "Address already in use" (half the runs of this test in the pytest process)."""
    keys = bus_env.folder / "keys"
    make_keys(keys)
    tcp = f"tcp://127.0.0.1:{_free_port_base()}"
    bus_env.start_forwarder(tcp_url=tcp, keys=keys)
    monkeypatch.setenv(CURVE_ENV, str(keys))
    address = bus_address(tcp)
    assert ping(address, 5.0) is not None  # in this process
    pinger = ("import os; from nodes.endpoints import bus_address; from nodes.forwarder import ping\n"
              f"address = bus_address({tcp!r}); assert ping(address, 5.0) is not None\n"
              "before = len(os.listdir('/proc/self/fd'))\n"
              "assert all(ping(address, 5.0) is not None for _ in range(100))\n"
              "print(len(os.listdir('/proc/self/fd')) - before)")
    result = subprocess.run([sys.executable, "-c", pinger], capture_output=True, text=True, timeout=60,
                            cwd=REPO, env=dict(os.environ, **{CURVE_ENV: str(keys)}))
    assert result.returncode == 0, result.stderr
    assert int(result.stdout) < 20, "file descriptors left behind by 100 pings"


def test_a_context_on_a_tcp_bus_is_destroyed_without_aborting(bus_env: Bus) -> None:
    """A node on a TCP bus stopped with Ctrl-C destroyed its ZeroMQ context while the threads watching
    its sockets' CURVE handshakes read their monitor sockets: libzmq aborted the process ("Assertion
    failed: pfd.revents & POLLIN", rc -6; 2 of 12 runs of 20 sockets here, 7 of 8 node stops for a
    reviewer). The watchers now stop first, each closing its own monitor."""
    keys = bus_env.folder / "keys"
    make_keys(keys)
    tcp = f"tcp://127.0.0.1:{_free_port_base()}"
    bus_env.start_forwarder(tcp_url=tcp, keys=keys)
    rounds = ("import time, zmq\n"
              "from nodes.bus import connect_client, stop_handshake_watchers\n"
              "from nodes.endpoints import bus_address\n"
              f"address = bus_address({tcp!r})\n"
              "for k in range(8):\n"
              "    ctx = zmq.Context()\n"
              "    socks = [ctx.socket(zmq.SUB) for _ in range(20)]\n"
              "    for sock in socks:\n"
              "        connect_client(sock, address, address.sub)\n"
              "    time.sleep(0.3)\n"
              "    for sock in socks:\n"
              "        sock.close(linger=500)\n"
              "    stop_handshake_watchers()\n"
              "    ctx.destroy(linger=500)\n"
              "    print(k, flush=True)\n")
    result = subprocess.run([sys.executable, "-c", rounds], capture_output=True, text=True, timeout=120,
                            cwd=REPO, env=dict(os.environ, **{CURVE_ENV: str(keys)}))
    assert result.returncode == 0 and result.stdout.split() == [str(k) for k in range(8)], result.stderr


@pytest.mark.parametrize("transport", ["ipc", "tcp"])
def test_a_ping_waits_for_a_slow_answer(bus_env: Bus, monkeypatch: pytest.MonkeyPatch, transport: str) -> None:
    """On a loaded host 0.3 s missed a forwarder that was serving ("no forwarder answers ... no launch runs on
    this bus"): over TCP, where the CURVE handshake comes before the answer, 2 runs of `fv topic hz` in 16; over
    IPC, `fv topic echo` 1 run in 16 of test_topic_tools' latched echo under 3 busy loops. A ping, and a tool's
    check that a forwarder serves the bus, wait for an answer 0.8 s late."""
    from nodes.topic_tools import require_forwarder

    address, keys = bus_env.address, None
    if transport == "tcp":
        keys = bus_env.folder / "keys"
        make_keys(keys)
        monkeypatch.setenv(CURVE_ENV, str(keys))
        address = bus_address(f"tcp://127.0.0.1:{_free_port_base()}")
        monkeypatch.setenv(BUS_ENV, address.url)
    slow = zmq.Context.instance().socket(zmq.REP)  # a forwarder's control socket that answers in 0.8 s
    slow.linger = 0
    if keys is not None:
        secure_server(slow, keys)
    slow.bind(address.ctl)

    def answer() -> None:
        for _ in range(2):  # ping(), then require_forwarder()
            if slow.poll(10_000):
                slow.recv()
                time.sleep(0.8)
                slow.send(msgpack.packb({"pid": 1}))

    thread = threading.Thread(target=answer)
    thread.start()
    try:
        assert ping(address) == {"pid": 1}
        require_forwarder()
    finally:
        thread.join()
        slow.close()


def test_tcp_forwarder_refuses_to_start_without_keys(bus_env: Bus) -> None:
    with pytest.raises(ValueError, match="CURVE"):
        bus_env.start_forwarder(tcp_url=f"tcp://127.0.0.1:{_free_port_base()}")


def test_client_readme_snippet(bus: Bus) -> None:
    pub = PublisherSocket("slip_detector", bus.address)
    assert pub.wait_connected(2.0)
    stop = threading.Event()
    thread = _publish_until(stop, pub, [("/slip", SlipState(slip=False)), ("/slip", SlipState(slip=True))])

    class Gripper:
        squeezes = 0

        def squeeze(self) -> None:
            self.squeezes += 1

    gripper = Gripper()
    seen: list[bool] = []
    try:
        # --- README snippet, verbatim ---
        from nodes.client import subscribe

        with subscribe("/slip", timeout_s=1.0) as states:
            for state in states:          # SlipState messages, in order
                if state.slip:
                    gripper.squeeze()
                # --- end of snippet ---
                seen.append(state.slip)
                if len(seen) == 20:
                    break
    finally:
        stop.set()
        thread.join()
        pub.close()
    assert gripper.squeezes == sum(seen) == 10


def test_client_timeout_callback_and_type_check(bus: Bus) -> None:
    from nodes.client import listen, subscribe, wait_for_message

    with subscribe("/slip", timeout_s=0.2) as states, pytest.raises(TimeoutError, match="/slip"):
        next(iter(states))
    pub = PublisherSocket("det", bus.address)
    assert pub.wait_connected(2.0)
    got: list[SlipState] = []
    with listen("/slip", got.append, SlipState):
        stop = threading.Event()
        thread = _publish_until(stop, pub, [("/slip", SlipState(slip=True))])
        poll_until(lambda: len(got) >= 3, 3.0, period_s=0.02)
        assert wait_for_message("/slip", SlipState, timeout_s=2.0).slip
        with subscribe("/slip", CameraInfo) as wrong:  # dropped and counted: it raised TypeError
            assert wrong.recv(0.5) is None and wrong.wrong_type >= 1
        stop.set()
        thread.join()
    pub.close()
    assert len(got) >= 3 and all(s.slip for s in got)


def test_client_reset_grasp_reaches_the_trackers_and_needs_a_bus(bus: Bus, bus_env: Bus) -> None:
    """Robot code's first message is not lost: a bare PublisherSocket's, sent before the forwarder
    took it, was dropped without a word (the README told users to publish on /tracker/reset)."""
    from nodes.client import advertise, reset_grasp

    with TopicReader(["/tracker/reset", "/my/topic"]) as reader:
        with advertise("/my/topic") as pub:  # until the reader's subscriptions have reached the forwarder
            for _ in range(40):
                pub.publish(SlipState(probability=0.25))
                if (got := reader.recv(0.05)) is not None:
                    break
            assert got is not None and got.msg.probability == 0.25
        for k in range(5):  # a fresh connection each time, the message sent at once
            reset_grasp()
            got = reader.recv(2.0)
            assert got is not None and got.topic == "/tracker/reset", f"reset {k} lost"
    bus.stop_forwarder()
    with pytest.raises(TimeoutError, match="no forwarder took /tracker/reset on ipc://"):
        reset_grasp(connect_timeout_s=0.3)


def test_client_publish_refuses_what_subscribers_would_drop(bus: Bus) -> None:
    """`publish(SlipState(probability=1.5))` returned normally and every subscriber dropped it as
    malformed; `SlipState(slip=np.bool_(True))` failed in msgpack naming no field."""
    import numpy as np

    from nodes.client import advertise

    with TopicReader(["/my/slip"]) as reader, advertise("/my/slip") as pub:
        with pytest.raises(ValueError, match=r"^SlipState\.probability: 1\.5 is not in \[0, 1\]$"):
            pub.publish(SlipState(probability=1.5))
        with pytest.raises(ValueError, match=r"^SlipState\.slip: 1 is not a bool"):
            pub.publish(SlipState(slip=np.int64(1)))
        # what msgpack cannot carry ended in its own OverflowError, UnicodeEncodeError or TypeError
        with pytest.raises(ValueError, match=r"^MarkerArray\.width: 1180591620717411303424 cannot be sent"):
            pub.publish(MarkerArray(width=2**70, height=1))
        with pytest.raises(ValueError, match=r"^SlipState\.frame_id: '\\udcff' cannot be sent"):
            pub.publish(SlipState(frame_id="\udcff"))
        for _ in range(40):  # until the reader's subscription has reached the forwarder
            pub.publish(SlipState(slip=np.bool_(True), probability=np.float32(0.75), stamp_ns=np.int64(5)))
            if (got := reader.recv(0.05)) is not None:
                break
        assert got is not None and (got.msg.slip, got.msg.probability, got.msg.stamp_ns) == (True, 0.75, 5)
        assert reader.malformed == 0


@pytest.mark.parametrize("bad", ["topic", "empty topic", "tcp bus without keys"])
def test_client_listen_raises_what_subscribe_raises(bus_env: Bus, monkeypatch: pytest.MonkeyPatch, bad: str) -> None:
    """`listen("slip", print)` and a TCP bus without FV_CURVE_DIR returned after 2 s with the listener's
    thread dead (a traceback on stderr the only sign): the robot went on with nothing watching for slip.
    `subscribe("")` (an unset variable) received every topic."""
    from nodes.client import listen, subscribe

    topic, error, match = "slip", ValueError, "topic 'slip': must start with '/'"
    if bad == "empty topic":
        topic, match = "", "topic '': must start with '/'"
    if bad == "tcp bus without keys":
        topic, error, match = "/slip", RuntimeError, CURVE_ENV
        monkeypatch.setenv("FV_BUS", "tcp://127.0.0.1:17600")
        monkeypatch.delenv(CURVE_ENV, raising=False)
    with pytest.raises(error, match=match):
        subscribe(topic)
    threads = set(threading.enumerate())
    start = time.monotonic()
    with pytest.raises(error, match=match):
        listen(topic, print)
    assert time.monotonic() - start < 1.0
    assert set(threading.enumerate()) <= threads, "a listener thread was started"


def test_malformed_frames_are_counted_by_a_reader(bus: Bus) -> None:
    raw = zmq.Context.instance().socket(zmq.PUB)
    raw.linger = 0
    raw.connect(bus.address.pub)
    with TopicReader(["/x"]) as reader:
        time.sleep(0.2)
        for frames in ([envelope("/x", "n", False), b"\xc1garbage"], [envelope("/x", "n", False)]):
            raw.send_multipart(frames)
        raw.send_multipart([envelope("/x", "n", False), *msgs.encode(SlipState(seq=7))])
        item = reader.recv(timeout_s=2.0)
        assert item is not None and item.msg.seq == 7 and reader.malformed == 2
    raw.close()


def test_client_drops_and_counts_messages_of_another_type(bus: Bus, caplog: pytest.LogCaptureFixture) -> None:
    """One NodeStatus on a listened SlipState topic killed the listener thread (nothing reported, later
    states never delivered); `subscribe("/slip")` handed it to the robot's loop."""
    from nodes.client import listen, subscribe
    got: list[float] = []
    pub = PublisherSocket("mixed", bus.address)
    assert pub.wait_connected(2.0)
    with listen("/mixed/slip", lambda m: got.append(m.probability), SlipState) as listener, \
            subscribe("/mixed/slip", timeout_s=2.0) as states, TopicReader(["/mixed/slip"]) as probe:
        poll_until(lambda: probe.recv(0.05) is not None, 3.0, period_s=0.0,  # until every subscription is up
                   between=lambda: pub.publish("/mixed/slip", SlipState(probability=0.0)))
        while states.recv(0.2) is not None:
            pass
        got.clear()
        for msg in (SlipState(probability=0.1), NodeStatus(), NodeStatus(), SlipState(probability=0.2)):
            pub.publish("/mixed/slip", msg)
        assert [s.probability for s in (next(iter(states)), next(iter(states)))] == [0.1, 0.2]
        assert states.wrong_type == 2
        poll_until(lambda: len(got) >= 2, 3.0, period_s=0.02)
        assert got == [0.1, 0.2] and listener.wrong_type == 2 and listener._thread.is_alive()
    pub.close()
    drops = [r.getMessage() for r in caplog.records if "dropped a NodeStatus" in r.getMessage()]
    assert len(drops) == 2, drops  # once per subscriber, not per message


def test_seq_tracker_gaps_stay_bounded_by_absurd_jumps() -> None:
    """seq 0, 2**63 - 1, 0, ...: the gap count grew past what msgpack encodes, and the status thread
    of the node died re-encoding it."""
    seq = SeqTracker()
    for n in (0, 2**63 - 1, 0, 2**63 - 1, 0, 2**63 - 1):
        assert seq.accept("/t", "n", n, False, 1)
    assert seq.gaps == 0  # a jump beyond MAX_GAP starts the sequence over; a jump up to it is gaps
    for n in (0, 5, 5 + SeqTracker.MAX_GAP + 1, 5 + 2 * SeqTracker.MAX_GAP + 3):
        assert seq.accept("/u", "n", n, False, n)
    assert seq.gaps == 4 + SeqTracker.MAX_GAP


def test_the_forwarder_survives_latched_messages_without_a_header(bus: Bus) -> None:
    """`[b"L/slip\\0n"]` twice from a raw socket ended the forwarder (IndexError in its latched cache);
    now subscribers count them as malformed and later messages pass."""
    raw = zmq.Context.instance().socket(zmq.PUB)
    raw.linger = 0
    raw.connect(bus.address.pub)
    try:
        with TopicReader(["/x"]) as reader:
            for _ in range(40):  # until the reader's subscription has reached the forwarder
                raw.send_multipart([envelope("/x", "n", False), *msgs.encode(SlipState(seq=1))])
                if reader.recv(0.05) is not None:
                    break
            for _ in range(2):
                raw.send_multipart([envelope("/x", "n", True)])
            raw.send_multipart([envelope("/x", "n", False), *msgs.encode(SlipState(seq=7))])
            while (item := reader.recv(timeout_s=2.0)) is not None and item.msg.seq != 7:
                pass  # a probe that came late
            assert item is not None and reader.malformed == 2
        assert bus._thread is not None and bus._thread.is_alive(), "the forwarder died"
    finally:
        raw.close()


def test_silence_says_whether_the_bus_still_answers_and_reaches_a_listener(bus: Bus) -> None:
    """A robot's subscription that stopped hearing /slip raised "no message on /slip within 1.0 s" whether
    the launch was gone or not; a listener had no timeout at all and waited for good, the gripper never
    told that the pipeline had stopped."""
    from nodes.client import listen, subscribe, wait_for_message

    with subscribe("/slip", timeout_s=0.2) as states, pytest.raises(TimeoutError) as silent:
        next(iter(states))
    assert f"(the forwarder at {bus.address.url} still answers)" in str(silent.value)
    pub = PublisherSocket("slip_detector", bus.address)
    assert pub.wait_connected(2.0)
    silences: list[TimeoutError] = []
    got: list[SlipState] = []
    with listen("/slip", got.append, timeout_s=0.3, on_timeout=silences.append) as listener:
        for burst in (1, 2):
            # the listener reports each silence once...
            waited_s = wait_for(lambda: len(silences) >= burst, 5.0, f"silence {burst} reported", period_s=0.05)
            time.sleep(0.5)
            assert len(silences) == burst and listener.timeouts == burst  # ...not on every poll
            # messages end the silence: within 10 s of the silence's wait
            wait_for(lambda: len(got) >= burst, 10.0 - waited_s - 0.5, "a message reaching the listener",
                     period_s=0.05, between=lambda: pub.publish("/slip", SlipState()))
    pub.close()
    assert f"no message on /slip within 0.3 s (the forwarder at {bus.address.url} still answers)" in str(silences[0])
    bus.stop_forwarder()  # (stopped first: the bus is asked as the silence is raised)
    gone: list[TimeoutError] = []
    with listen("/slip", got.append, timeout_s=0.3, on_timeout=gone.append):
        wait_for(lambda: gone, 5.0, "the launch gone reported", period_s=0.05)
    assert f"no forwarder answers on {bus.address.url}: the launch is gone" in str(gone[0])
    with pytest.raises(TimeoutError, match="no forwarder answers on ipc://"):
        wait_for_message("/slip", timeout_s=0.2)


def test_silence_is_raised_before_the_bus_answers(bus_env: Bus, monkeypatch: pytest.MonkeyPatch) -> None:
    """The bus is asked from a thread as the silence is raised: a ping before the raise (2 s on TCP) would
    hold back the TimeoutError a gripper stops on. Its text waits for the answer."""
    import nodes.client
    from nodes.client import subscribe

    asked, answer = threading.Event(), threading.Event()

    def slow_ping(address: object) -> None:
        asked.set()
        assert answer.wait(10.0)

    monkeypatch.setattr(nodes.client, "ping", slow_ping)
    with subscribe("/slip", timeout_s=0.1) as states, pytest.raises(TimeoutError) as silent:
        next(iter(states))
    assert asked.wait(5.0) and not answer.is_set(), "raised while the bus was being asked"
    answer.set()
    assert f"no forwarder answers on {bus_env.address.url}" in str(silent.value)


def test_silence_says_what_the_bus_answered_when_it_was_raised(bus_env: Bus) -> None:
    """The text said what the bus answered when it was first read: a silence raised while the launch was
    gone, logged after a new launch had started, said "the forwarder ... still answers"."""
    from nodes.client import wait_for_message

    with pytest.raises(TimeoutError) as silent:
        wait_for_message("/slip", timeout_s=0.1)
    assert silent.value.bus_answers is False  # asked at the raise
    bus_env.start_forwarder()
    assert ping(bus_env.address, 2.0) is not None
    assert f"(no forwarder answers on {bus_env.address.url}: the launch is gone" in str(silent.value)


def test_a_silence_error_pickles_and_reprs_with_its_answer(bus: Bus) -> None:
    """A SilenceError could not be unpickled (`__init__() missing 2 required positional arguments`: a
    process pool's result, a multiprocessing queue) nor copied, and its repr left out the bus's answer."""
    from nodes.client import SilenceError, wait_for_message

    with pytest.raises(SilenceError) as silent:
        wait_for_message("/slip", timeout_s=0.1)
    text = str(silent.value)
    assert text == f"no message on /slip within 0.1 s (the forwarder at {bus.address.url} still answers)"
    bus.stop_forwarder()  # neither a copy nor an unpickled one asks the bus again
    for again in (pickle.loads(pickle.dumps(silent.value)), copy.copy(silent.value)):
        assert isinstance(again, SilenceError) and str(again) == text and again.topic == "/slip"
    assert repr(silent.value) == f"SilenceError({text!r})"


@pytest.mark.parametrize("topic", ["slip", "", "/slip ", "/slip/"])
def test_client_advertise_refuses_a_topic_no_subscriber_can_ask_for(bus: Bus, topic: str) -> None:
    """`advertise("slip")` published without a word on a topic `subscribe` and `fv topic echo` refuse."""
    from nodes.client import advertise

    with pytest.raises(ValueError, match=f"topic {topic!r}: must start with '/'"):
        advertise(topic)


@pytest.mark.parametrize("timeout_s, match", [
    (None, r"on_timeout is never called without timeout_s"),
    (0.0, r"timeout_s 0.0 must be > 0 s"),
    (-1.0, r"timeout_s -1.0 must be > 0 s"),
])
def test_a_listener_refuses_a_timeout_it_cannot_keep(bus: Bus, timeout_s: float | None, match: str) -> None:
    """`listen("/slip", cb, on_timeout=gripper.stop)` without `timeout_s` started and never called
    `on_timeout`: the gripper was told of no silence, and nothing said why. A timeout of 0 s called it
    on every gap between two messages."""
    from nodes.client import listen

    with pytest.raises(ValueError, match=match):
        listen("/slip", print, timeout_s=timeout_s, on_timeout=print).close()


def test_client_arguments_robot_code_gets_wrong_are_said_at_the_call(bus: Bus) -> None:
    """A msg_type that is no message class killed a listener's thread at its first message, without a word to
    the caller; `reset_grasp(confirm="/left")` waited on /, l, e, f, t; a param name that is no text was dropped
    by the node, the call waiting its whole timeout; a timeout of infinity (no timeout) ended in an
    OverflowError, and 0, -1 or NaN of the calls that did not check it were a TimeoutError at once."""
    from nodes.client import advertise, get_params, listen, reset_grasp, set_param, subscribe, wait_for_message

    for bad in ("SlipState", int):
        with pytest.raises(TypeError, match="is not a message class"):
            listen("/slip", print, bad)
    with pytest.raises(TypeError, match="callback None and on_timeout must be callable"):
        listen("/slip", None)
    with pytest.raises(TypeError, match="topic None is not text"):  # an AttributeError of NoneType before
        subscribe(None)
    with pytest.raises(TimeoutError, match=r"within 0.3 s in /left \(on /left/markers/grasp_start\)"):
        reset_grasp(confirm="/left", timeout_s=0.3)
    with pytest.raises(ParamError, match="param name 5 is not text"):
        set_param("slip_detector", 5, 1)
    for call in (lambda t: wait_for_message("/slip", timeout_s=t), lambda t: get_params("slip_detector", timeout_s=t),
                 lambda t: reset_grasp(timeout_s=t)):
        for timeout_s in (0.0, -1.0, float("nan")):
            with pytest.raises(ValueError, match="must be > 0 s"):
                call(timeout_s)
    pub = PublisherSocket("det", bus.address)
    assert pub.wait_connected(2.0)
    with subscribe("/slip", timeout_s=float("inf")) as forever:
        stop = threading.Event()
        thread = _publish_until(stop, pub, [("/slip", SlipState(slip=True))])
        assert next(iter(forever)).slip and forever.recv(float("inf")).slip
        stop.set()
        thread.join()
    pub.close()
    with pytest.raises(RuntimeError, match="the subscription to /slip is closed"):  # ZeroMQ's "Operation not supported"
        forever.recv(0.1)
    with advertise("/x") as closed:
        pass
    with pytest.raises(RuntimeError, match="the publisher of /x is closed"):
        closed.publish(SlipState())


def test_closing_a_listener_whose_callback_still_runs_says_so(bus: Bus, caplog: pytest.LogCaptureFixture) -> None:
    """close() waited 1 s for a callback that ran on (a gripper command at Ctrl-C) and returned without a
    word, the callback going on beside the code after the `with`."""
    from nodes.client import listen

    entered, release = threading.Event(), threading.Event()

    def slow(_msg: object) -> None:
        entered.set()
        release.wait(10.0)

    pub = PublisherSocket("slip_detector", bus.address)
    assert pub.wait_connected(2.0)
    listener = listen("/slip", slow)
    try:
        wait_for(entered.is_set, 5.0, "the callback called", period_s=0.05,
                 between=lambda: pub.publish("/slip", SlipState()))
        listener.close(timeout_s=0.1)
        assert "listener for /slip closed while its callback still runs after 0.1 s" in caplog.text
    finally:
        release.set()
        listener._thread.join(5.0)
        pub.close()
    assert listener.received == 1, "no call follows the close"


def test_a_listener_closed_from_its_own_callback_stops_after_it(bus: Bus) -> None:
    """A gripper that stops listening once it has seen a slip, calling close() in its callback: the
    callback raised RuntimeError ('cannot join current thread'), logged and counted, and the listener went
    on calling it."""
    from nodes.client import listen

    calls: list[SlipState] = []
    listener = None

    def once(msg: SlipState) -> None:
        calls.append(msg)
        listener.close()

    pub = PublisherSocket("slip_detector", bus.address)
    assert pub.wait_connected(2.0)
    listener = listen("/slip", once)
    try:
        wait_for(lambda: calls, 5.0, "the callback called", period_s=0.05,
                 between=lambda: pub.publish("/slip", SlipState()))
        for _ in range(5):  # more messages, which no call follows
            pub.publish("/slip", SlipState())
            time.sleep(0.05)
        listener._thread.join(5.0)
        assert not listener._thread.is_alive()
    finally:
        listener.close()
        pub.close()
    assert (len(calls), listener.errors) == (1, 0)


@pytest.mark.parametrize("timeout_s", [0.0, -1.0, float("nan")])
def test_a_subscription_refuses_a_timeout_it_cannot_keep(bus: Bus, timeout_s: float) -> None:
    """subscribe("/slip", timeout_s=0) raised at the first wait, and nan never: a silence went unnoticed."""
    from nodes.client import subscribe

    with pytest.raises(ValueError, match=f"timeout_s {timeout_s} must be > 0 s"):
        subscribe("/slip", timeout_s=timeout_s)


def test_the_forwarder_answers_a_request_of_several_frames(bus: Bus) -> None:
    """A two-frame request on the control socket ended the forwarder (ZMQError: Operation cannot be
    accomplished in current state: its REP had read one frame of two before answering)."""
    req = zmq.Context.instance().socket(zmq.REQ)
    req.linger = 0
    req.connect(bus.address.ctl)
    try:
        req.send_multipart([b"ping", b"more"])
        assert req.poll(5000), "no answer"
        assert msgpack.unpackb(req.recv())["url"] == bus.address.url
    finally:
        req.close()
    assert ping(bus.address, 2.0) is not None and bus._thread is not None and bus._thread.is_alive()


def test_a_forwarder_no_longer_waited_for_is_ended_and_reaped(bus_env: Bus, monkeypatch: pytest.MonkeyPatch) -> None:
    """`ensure_forwarder` stopped (a launch's Ctrl-C) while the forwarder it started was starting terminated it
    without waiting: a zombie process until the launch exited."""
    started, stop, popen = [], threading.Event(), subprocess.Popen

    def popen_then_stop(*args: object, **kwargs: object) -> subprocess.Popen:
        started.append(popen(*args, **kwargs))
        stop.set()
        return started[-1]

    monkeypatch.setattr(subprocess, "Popen", popen_then_stop)
    with pytest.raises(RuntimeError, match="stopped before the forwarder"):
        ensure_forwarder(bus_env.address, stop=stop)
    assert started[0].returncode is not None, "the forwarder was left running or unreaped"
