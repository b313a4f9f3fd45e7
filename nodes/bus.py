"""Bus sockets: the topic envelope, a publisher socket and a topic reader.

Every bus message is ``[envelope, header, array frames...]``. The envelope is
``FLAG + topic + b"\\0" + node`` with FLAG ``b"L"`` (latched) or ``b"-"``. Subscribers
subscribe to ``b"-" + topic + b"\\0"`` and ``b"L" + topic + b"\\0"``: ZeroMQ matches by
prefix, and the NUL makes the match exact (``/slip`` never receives ``/slip_debug``).
The forwarder keeps the last latched message per (topic, node) and replays it to each
new subscriber, so latched topics reach late joiners, while its publisher is connected: the
last latched message of a publisher that is gone reaches only a subscriber that asks for those
too (FLAG ``b"G"``, `subscription_prefixes(topic, gone=True)`; `nodes.latched_cache`). A restarted
forwarder has lost that cache: each publisher notices the new forwarder (its subscription to
latched topics arrives again) and re-sends its last latched message per topic; it re-sends them
too when the forwarder asks (a subscription to ``REFRESH`` + a number).
"""
from __future__ import annotations

import itertools
import logging
import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any, ClassVar

import zmq

import msgs
from msgs import Message, MessageError
from nodes.endpoints import BusAddress, bus_address, curve_dir, secure_client

LATCHED = b"L"
VOLATILE = b"-"
GONE = b"G"  # the flag of a latched message whose publisher is gone, as the forwarder replays it
REFRESH = b"?"  # the forwarder's subscription that asks every publisher to re-send its latched messages
ANSWER_PERIOD_S = 0.2  # how often an idle publisher of latched messages reads the forwarder's requests
LINGER_MS = 100
PUB_HWM = 200
SUB_HWM = 200
ALL_TOPICS = ""
HEARTBEAT_IVL_MS = 1000  # TCP only: ping the forwarder this often...
HEARTBEAT_TIMEOUT_MS = 3000  # ...and drop the connection (then reconnect) after this long without an answer

log = logging.getLogger("fv.bus")


def envelope(topic: str, node: str, latched: bool) -> bytes:
    return (LATCHED if latched else VOLATILE) + topic.encode() + b"\0" + node.encode()


def parse_envelope(frame: Any) -> tuple[str, str, bool]:
    """(topic, node, latched) of an envelope frame; ValueError when it is not one."""
    raw = frame.bytes if hasattr(frame, "bytes") else bytes(frame)
    if len(raw) < 3 or raw[:1] not in (LATCHED, VOLATILE, GONE) or b"\0" not in raw:
        raise ValueError(f"not a bus envelope: {raw[:40]!r}")
    topic, _, node = raw[1:].partition(b"\0")
    return topic.decode(errors="replace"), node.decode(errors="replace"), raw[:1] != VOLATILE


def subscription_prefixes(topic: str, gone: bool = False) -> list[bytes]:
    """The ZeroMQ prefixes that receive exactly `topic` ("" = every topic); with `gone`, also the last
    latched message of each of its publishers that are gone (a respawned node's predecessor's)."""
    flags = (LATCHED, VOLATILE, GONE) if gone else (LATCHED, VOLATILE)
    if topic == ALL_TOPICS:
        return list(flags)
    return [flag + topic.encode() + b"\0" for flag in flags]


def validate_topic(topic: str) -> str:
    if not isinstance(topic, str):  # (an AttributeError of NoneType's startswith before)
        raise TypeError(f"topic {topic!r} is not text")
    if not topic.startswith("/") or "\0" in topic or " " in topic or topic.endswith("/") and topic != "/":
        raise ValueError(f"topic {topic!r}: must start with '/', hold no spaces or NUL, and not end with '/'")
    return topic


def absolute_namespace(namespace: str) -> str:
    """"left", "/left" and "/left/" are "/left"; "" (or "/") is no namespace, ""."""
    name = namespace.strip("/")
    return "/" + name if name else ""


def namespaced_name(namespace: str, name: str) -> str:
    """The name of the node `name` that a launch file puts in `namespace` (its own or its includes'): the
    namespace's parts, each followed by _, before it ("/left", "slip_detector" -> "left_slip_detector";
    "/hand/left" -> "hand_left_slip_detector"; no namespace, "": `name`)."""
    return "_".join([*absolute_namespace(namespace).split("/")[1:], name])


def node_name(path: str) -> str:
    """The name (as `fv node list` shows it) of the node at the ROS-style `path`: its namespace in the launch
    (its includes' and its own), then its name in its own launch file ("/left/slip_detector" and
    "left/slip_detector" -> "left_slip_detector", `namespaced_name`); "/slip_detector" and a name
    ("left_slip_detector") are that name. ValueError when `path` holds no name ("", "/")."""
    namespace, _, name = path.strip("/").rpartition("/")
    if not name:
        raise ValueError(f"{path!r} is not a node name or path (slip_detector, /left/slip_detector)")
    return namespaced_name(namespace, name)


def check_timeout(timeout_s: float | None) -> None:
    """ValueError for a wait (s) that is not > 0: 0 or -1 raised at the first wait, nan never (infinity and None:
    no timeout)."""
    if timeout_s is not None and not timeout_s > 0:
        raise ValueError(f"timeout_s {timeout_s} must be > 0 s (None: no timeout)")


def poll_ms(wait_s: float | None) -> int | None:
    """A wait of `wait_s` seconds as ZeroMQ's poll takes it: whole ms, None (for ever) for None or infinity
    (`int(inf)` ended a wait for ever, `timeout_s=float('inf')`, in an OverflowError)."""
    return None if wait_s is None or wait_s == math.inf else int(wait_s * 1000)


def resolve_topic(topic: str, namespace: str = "", remap: dict[str, str] | None = None) -> str:
    """The absolute topic a node in `namespace` ("/left", "" for none) with `remap` means by
    `topic`: a relative name ("camera/image") gets the namespace (/left/camera/image), an absolute
    one is kept; then a remap of the full name, else of the name as written, replaces it."""
    full = topic if topic.startswith("/") else f"{namespace}/{topic}"
    remap = remap or {}
    return validate_topic(remap.get(full, remap.get(topic, full)))


def new_context() -> zmq.Context:
    return zmq.Context.instance()


def subscriber_socket(ctx: zmq.Context, address: BusAddress, rcvhwm: int = SUB_HWM) -> zmq.Socket:
    """A SUB socket connected to the bus's subscribers' side, queueing up to `rcvhwm` messages. Its send queue
    holds only its subscriptions and has no limit: ZeroMQ drops a subscription that finds a send queue full, and
    the topic's messages then never come (the forwarder's queue to a publisher lost some of 1,600 topics
    subscribed at once: `nodes.forwarder`)."""
    sock = ctx.socket(zmq.SUB)
    sock.linger = LINGER_MS
    sock.rcvhwm = rcvhwm
    sock.sndhwm = 0
    connect_client(sock, address, address.sub)
    return sock


def connect_client(sock: zmq.Socket, address: BusAddress, endpoint: str) -> None:
    """Configure `sock` for the bus (CURVE and heartbeats on TCP) and connect it to
    `endpoint`. ZeroMQ reconnects by itself after the forwarder restarts; the heartbeat
    lets a TCP client notice a forwarder host that vanished without closing the connection.
    On TCP a failed CURVE handshake is logged as an error (`_watch_handshake`)."""
    secure_client(sock, address)
    if address.is_tcp:
        sock.heartbeat_ivl = HEARTBEAT_IVL_MS
        sock.heartbeat_timeout = HEARTBEAT_TIMEOUT_MS
        _watch_handshake(sock, address)
    sock.connect(endpoint)


_REFUSED: set[str] = set()  # the bus URLs whose refused handshake this process has logged
_MONITORS = itertools.count()  # numbers the handshake monitors' endpoints
_WATCHERS: list[threading.Thread] = []  # this process's handshake watchers (the finished ones pruned)
_STOP_WATCHING = threading.Event()
WATCH_POLL_MS = 100  # how often a watcher looks at _STOP_WATCHING
_HANDSHAKE_EVENTS = zmq.EVENT_HANDSHAKE_SUCCEEDED | zmq.EVENT_HANDSHAKE_FAILED_AUTH | \
    zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL | zmq.EVENT_MONITOR_STOPPED


def _watch_handshake(sock: zmq.Socket, address: BusAddress) -> None:
    """Log, once, why the forwarder at `address` refuses `sock`'s CURVE handshake, from a thread that
    watches it until the socket closes: ZeroMQ retries it for good without a word, so a host whose key
    the forwarder does not know received nothing and said nothing. The thread closes the monitor only
    when ZeroMQ says it has stopped (the socket closed): closed before, at the handshake, it left the
    monitor's sockets behind, 4 file descriptors per socket, and a process that had pinged a TCP
    forwarder 300 times could open no more sockets ("Too many open files")."""
    from zmq.utils.monitor import recv_monitor_message

    # pyzmq names the endpoint after the socket's file descriptor by default, which the next socket may reuse
    monitor = sock.get_monitor_socket(_HANDSHAKE_EVENTS, addr=f"inproc://fv-handshake-{next(_MONITORS)}")
    keys = curve_dir()  # as the socket was given them

    def watch() -> None:
        try:
            while not _STOP_WATCHING.is_set():
                if not monitor.poll(WATCH_POLL_MS):
                    continue
                event = recv_monitor_message(monitor)["event"]
                if event == zmq.EVENT_MONITOR_STOPPED:
                    return
                if event == zmq.EVENT_HANDSHAKE_SUCCEEDED or address.url in _REFUSED:  # said once per bus
                    continue
                _REFUSED.add(address.url)
                why = ("it does not know this host's client key: copy that client.key into its authorized/ folder"
                       if event == zmq.EVENT_HANDSHAKE_FAILED_AUTH else
                       "this host's server.key is not that forwarder's: copy its server.key here")
                log.error("the forwarder at %s refuses the CURVE handshake (FV_CURVE_DIR %s): %s; nothing "
                          "passes until it is fixed", address.url, keys, why)
        except zmq.ZMQError:  # the context went away
            return
        finally:
            monitor.close(linger=0)

    watcher = threading.Thread(target=watch, name="fv-curve-handshake", daemon=True)
    _WATCHERS[:] = [t for t in _WATCHERS if t.is_alive()] + [watcher]
    watcher.start()


def stop_handshake_watchers(timeout_s: float = 1.0) -> None:
    """Stop this process's handshake watchers, each closing its own monitor socket, before its ZeroMQ
    context is destroyed: destroying it closes every socket, and a monitor socket closed under the
    watcher reading it aborted the process (libzmq's "Assertion failed: pfd.revents & POLLIN"; a node on
    a TCP bus stopped with Ctrl-C, 7 runs in 8)."""
    _STOP_WATCHING.set()
    for watcher in list(_WATCHERS):
        watcher.join(timeout_s)
    _STOP_WATCHING.clear()  # sockets made afterwards are watched again


class PublisherSocket:
    """One node's publishing socket (an XPUB connected to the forwarder).

    XPUB rather than PUB so the node sees which topics have subscribers (the forwarder
    passes subscriptions upstream) and whether the forwarder is there: the forwarder
    always subscribes to latched topics, so its subscription arriving means connected and
    its removal (ZMQ_IMMEDIATE: the connection's pipe goes with the connection) means
    gone. When a forwarder connects (the first, or a restarted one), or asks (`REFRESH`: a
    publisher has left it, and it learns which of its cached latched messages still have theirs), the
    last latched message of each topic is sent again, unchanged; subscribers that saw it already drop
    it by its seq. The forwarder's requests are read with its other subscription events, on each
    publish or `update()`. Thread-safe.

    connected: the forwarder is connected now. reconnects: forwarder connections after
    the first. down_since_s: monotonic time the forwarder went away (None while connected).
    """

    def __init__(self, node: str, address: BusAddress | None = None, ctx: zmq.Context | None = None) -> None:
        self.node = node
        self.address = address or bus_address()
        self._lock = threading.Lock()
        self._sock = (ctx or new_context()).socket(zmq.XPUB)
        self._sock.linger = LINGER_MS
        self._sock.sndhwm = PUB_HWM
        self._sock.immediate = 1  # no queueing for a forwarder that is not there; unsubscribe when it goes
        connect_client(self._sock, self.address, self.address.pub)
        self._prefixes: set[bytes] = set()
        self._seq: dict[str, int] = {}
        self._latched: dict[bytes, list[bytes]] = {}  # envelope -> message frames, re-sent after a reconnect
        self.connected = False
        self.reconnects = 0
        self.down_since_s: float | None = None
        self._connections = 0

    def _drain_subscriptions(self) -> None:
        while self._sock.poll(0):
            event = self._sock.recv()
            if event[1:2] == REFRESH:
                if event[:1] == b"\x01":
                    self._send_latched()
                continue
            if event[:1] == b"\x01":
                self._prefixes.add(event[1:])
                if event[1:] == LATCHED and not self.connected:
                    self._forwarder_connected()
            elif event[:1] == b"\x00":
                self._prefixes.discard(event[1:])
                if event[1:] == LATCHED and self.connected:
                    self.connected = False
                    self.down_since_s = time.monotonic()
                    log.debug("%s: forwarder %s gone", self.node, self.address.url)

    def _forwarder_connected(self) -> None:
        """Connected: the last latched message of each topic is sent (again), on the first connection
        too: one published before any forwarder answered was dropped (ZMQ_IMMEDIATE), and a camera
        started before its forwarder never delivered its `CameraInfo`."""
        self.connected = True
        self.down_since_s = None
        self._connections += 1
        self.reconnects += self._connections > 1
        self._send_latched()
        if self._latched:
            log.debug("%s: forwarder %s connected (reconnects %d); %d latched messages sent", self.node,
                      self.address.url, self.reconnects, len(self._latched))

    def _send_latched(self) -> None:
        """Send the last latched message of each topic again, unchanged."""
        for env, frames in self._latched.items():
            self._send([env, *frames])

    def update(self) -> None:
        """Process the forwarder's subscription events: track the connection and re-send
        latched messages after a reconnect or when the forwarder asks. Every publish does this; a
        publisher of latched messages that may stay idle calls it periodically (the node runtime does,
        from its status thread; `nodes.client.Publisher` from a thread of its own): unanswered, the
        forwarder takes its latched messages for a gone publisher's. Nothing once closed."""
        with self._lock:
            if not self._sock.closed:
                self._drain_subscriptions()

    def answer_until(self, done: threading.Event) -> None:
        """`update()` every ANSWER_PERIOD_S until `done` is set: an idle latched publisher's own loop (a
        thread of `nodes.client.Publisher`, `fv topic pub --latched` after its last message)."""
        while not done.wait(ANSWER_PERIOD_S):
            self.update()

    def wait_connected(self, timeout_s: float = 2.0) -> bool:
        """Block until the forwarder has subscribed (it always asks for latched topics)."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            self._drain_subscriptions()
            while not self.connected:
                remaining = deadline - time.monotonic()
                if remaining <= 0 or not self._sock.poll(poll_ms(remaining)):
                    return False
                self._drain_subscriptions()
            return True

    def has_subscribers(self, topic: str) -> bool:
        """True when some subscriber asked for `topic` (exactly or through a wildcard)."""
        key = VOLATILE + topic.encode() + b"\0"
        with self._lock:
            self._drain_subscriptions()
            return any(key.startswith(p) for p in self._prefixes if p[:1] == VOLATILE)

    def publish(self, topic: str, msg: Message, latched: bool = False) -> int:
        """Stamp `msg` (seq, pub_ns, node) and send it; returns its seq. Never blocks."""
        with self._lock:
            self._drain_subscriptions()
            seq = self._seq.get(topic, -1) + 1
            self._seq[topic] = seq
            msg.seq = seq
            msg.node = self.node
            msg.pub_ns = time.time_ns()
            self._send_new([envelope(topic, self.node, latched), *msgs.encode(msg)], latched)
            return seq

    def publish_raw(self, topic: str, node: str, latched: bool, frames: list[Any]) -> None:
        """Send already encoded message frames unchanged (bag play): the header keeps its
        recorded seq / pub_ns / node and the envelope names `node`, the recorded
        publisher, so subscribers' SeqTrackers and the forwarder's latched cache see it
        as that publisher. Never blocks (dropped when the forwarder is gone)."""
        with self._lock:
            self._drain_subscriptions()
            self._send_new([envelope(topic, node, latched), *frames], latched)

    def _send_new(self, frames: list[Any], latched: bool) -> None:
        """Send a new message; a latched one is also kept (copied) for re-sending."""
        if latched:
            self._latched[frames[0]] = [bytes(f) for f in frames[1:]]
        self._send(frames)

    def _send(self, frames: list[Any]) -> None:
        try:
            self._sock.send_multipart(frames, copy=False, flags=zmq.NOBLOCK)
        except zmq.Again:
            pass  # HWM reached: dropping beats blocking the publisher

    def close(self) -> None:
        with self._lock:
            self._sock.close(linger=LINGER_MS)


@dataclass
class SeqTracker:
    """Counts sequence gaps per (topic, publisher node) and drops latched replays.

    A latched message is replayed by the forwarder to every new subscriber (and re-sent
    by its publisher after a forwarder restart); a subscriber that already saw it sees
    the same message again and drops it. A seq that goes back otherwise means the
    publisher restarted: the count starts over. With `pub_ns` given, a replay is told
    from a restarted publisher's new latched message by its publish time (a replay is
    byte-identical); without it, any latched seq that goes back counts as a replay. A seq more
    than `MAX_GAP` ahead is no gap either (no publisher lost that many messages in between) but a
    sequence that starts over there: one bad seq (2**63 - 1) had made `gaps` too large for msgpack.
    """

    MAX_GAP: ClassVar[int] = 1_000_000

    last: dict[tuple[str, str], int] = field(default_factory=dict)
    last_pub_ns: dict[tuple[str, str], int] = field(default_factory=dict)
    gaps: int = 0

    def accept(self, topic: str, node: str, seq: int, latched: bool, pub_ns: int | None = None) -> bool:
        key = (topic, node)
        prev = self.last.get(key)
        if prev is not None and seq <= prev:
            if latched and (pub_ns is None or pub_ns == self.last_pub_ns.get(key)):
                return False
            prev = None
        if prev is not None and prev + 1 < seq <= prev + 1 + self.MAX_GAP:
            self.gaps += seq - prev - 1
        self.last[key] = seq
        if pub_ns is not None:
            self.last_pub_ns[key] = pub_ns
        return True


@dataclass
class Received:
    """A decoded message with its routing: topic, publisher node and latched flag."""

    topic: str
    msg: Message
    latched: bool


class TopicReader:
    """A blocking subscriber for tools and robot code (no threads, no callbacks).

    >>> with TopicReader(["/slip"]) as reader:
    ...     item = reader.recv(timeout_s=1.0)   # Received or None
    """

    def __init__(self, topics: list[str], address: BusAddress | None = None, ctx: zmq.Context | None = None,
                 hwm: int = SUB_HWM) -> None:
        self.address = address or bus_address()
        self._sock = subscriber_socket(ctx or new_context(), self.address, hwm)
        for topic in topics:
            for prefix in subscription_prefixes(topic if topic == ALL_TOPICS else validate_topic(topic)):
                self._sock.setsockopt(zmq.SUBSCRIBE, prefix)
        self.seq = SeqTracker()
        self.malformed = 0
        self.last_malformed = ""  # why the last malformed message was dropped, naming its publisher

    def recv_raw(self, timeout_s: float | None = None) -> tuple[str, str, bool, list[Any]] | None:
        """(topic, node, latched, message frames) of the next fresh message, or None on
        timeout. Latched replays already seen are skipped; gaps are counted."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            wait = None if deadline is None else max(0.0, deadline - time.monotonic())
            if not self._sock.poll(poll_ms(wait)):
                return None
            frames = self._sock.recv_multipart(copy=False)
            node = "?"
            try:
                topic, node, latched = parse_envelope(frames[0])
                header = msgs.decode_header(frames[1], topic) if len(frames) > 1 else None
                if header is None:
                    raise ValueError("no header frame")
            except (ValueError, MessageError) as exc:
                self._dropped(exc, node)
                continue
            if self.seq.accept(topic, node, header["seq"], latched, header["pub_ns"]):
                return topic, node, latched, frames[1:]

    def recv(self, timeout_s: float | None = None) -> Received | None:
        """Next decoded message, or None on timeout; malformed ones are counted and skipped."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            wait = None if deadline is None else max(0.0, deadline - time.monotonic())
            raw = self.recv_raw(wait)
            if raw is None:
                return None
            topic, node, latched, frames = raw
            try:
                return Received(topic, msgs.decode(frames, topic), latched)
            except MessageError as exc:
                self._dropped(exc, node)

    def _dropped(self, exc: Exception, node: str) -> None:
        """Count a malformed message from publisher `node` and keep why in `last_malformed`."""
        self.malformed += 1
        self.last_malformed = f"{exc} (from node {node!r})"
        log.debug("dropped malformed message: %s", self.last_malformed)

    def close(self) -> None:
        self._sock.close(linger=LINGER_MS)

    def __enter__(self) -> "TopicReader":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
