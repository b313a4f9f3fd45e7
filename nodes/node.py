"""The node runtime: publishers, subscriptions with queue policies, timers, params,
logging and a periodic `NodeStatus` on `/status`.

Threading model: one receiver thread drains the node's SUB socket into per-subscription
queues (so ZeroMQ buffers never fill and a slow callback never slows a publisher), and
`spin()` runs callbacks and timers one at a time on the calling thread. A queue of depth
N keeps the last N messages (depth 1 = latest only, for camera frames) and counts what
it drops; depth None keeps all (up to `KEEP_ALL_CAP`). Queued messages are handled in the
order they arrived, whatever their topic (as one callback queue): a message that causes
another (a tracker's new reference, then the field of that frame through the interpolator)
is handled first, and no topic starves another.

A pipeline stage names, on its input's subscription, the publisher that answers it (`answered_by`): a
message whose callback publishes nothing there (a tracker's frame before its reference, a window model's
field while its window fills, a callback that raised) is said on `unanswered` (`msgs.Unanswered`), so that a
batch replay's player (`nodes.bag.player`, `sync_topic`) sends the next frame at once.

A third thread, the status thread, publishes `NodeStatus` every `STATUS_PERIOD_S` and at
once when the node's health changes, so a node whose callback hangs still reports. It is
also the watchdog: besides the node's own `warn()`, the status reports
- error "callback on_image (/camera/image) stuck for 6.2 s": a callback or timer has run
  longer than `STUCK_AFTER_S` (counted in counters["stuck_callbacks"]);
- warn "no /camera/image for 2.1 s": a subscription made with `stale_after_s` got no
  message for that long (cleared when messages flow again);
- error "callback on_field (/field) raised on its last 3 calls: ValueError: ...": a callback or timer that raised on
  `FAILING_AFTER` calls in a row, until it returns again (a node whose every callback failed
  reported "ok" with its error count growing);
- warn "forwarder ipc://... unreachable for 1.0 s": the bus forwarder went away (seen in
  the logs; the status itself cannot travel then). When it is back, latched messages are
  re-sent and counters["bus_reconnects"] counts it;
- warn "no forwarder answers on ipc://... (4.0 s): start one with `fv forwarder` or `fv launch`":
  none answered within `CONNECT_WAIT_S` of the start (logged once); cleared when one answers.
"""
from __future__ import annotations

import collections
import contextlib
import itertools
import logging
import os
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable, ClassVar

import numpy as np
import zmq

import msgs
from msgs import Message, MessageError, NodeStatus, Unanswered
from nodes.bus import (ALL_TOPICS, GONE, PublisherSocket, SeqTracker, absolute_namespace, new_context,
                       parse_envelope, resolve_topic, subscriber_socket, subscription_prefixes)
from nodes.endpoints import BusAddress, bus_address
from nodes.exit_codes import NodeFailed, Stopped, on_stop_signals
from nodes.param_service import ParamService, is_param_topic
from nodes.params import build_params

STATUS_TOPIC = "/status"
UNANSWERED_TOPIC = "unanswered"  # relative: in the node's namespace, beside the topics it answers on
STANDBY_READY = "fv-standby-ready"  # the line a standby process prints once it waits to take over
LAUNCH_ENV = "FV_LAUNCH_NS"  # set by `fv launch` for its nodes: when the launch started, ns since the epoch
KEEP_ALL_CAP = 10_000
_PAGE = os.sysconf("SC_PAGE_SIZE")
_SEVERITY = {"ok": 0, "warn": 1, "error": 2}


def is_plumbing_topic(topic: str) -> bool:
    """Whether `topic` is bus plumbing the runtime gives every node beside its data topics: a node's param
    request or state topic (`nodes.param_service.is_param_topic`: /N/param/set, /N/param/state) or the
    `unanswered` notices of a namespace (`msgs.Unanswered`: /unanswered, /left/unanswered)."""
    return is_param_topic(topic) or topic.rpartition("/")[2] == UNANSWERED_TOPIC


@dataclass
class NoParams:
    """A node without parameters."""


class Publisher:
    """Publishes one message type on one topic (resolved name)."""

    def __init__(self, sock: PublisherSocket, topic: str, msg_type: type[Message], latched: bool) -> None:
        self.topic = topic
        self.msg_type = msg_type
        self.latched = latched
        self._sock = sock
        self.count = 0

    def publish(self, msg: Message) -> int:
        if not isinstance(msg, self.msg_type):
            raise TypeError(f"{self.topic}: publishes {self.msg_type.TYPE}, got {type(msg).__name__}")
        self.count += 1
        return self._sock.publish(self.topic, msg, self.latched)

    def has_subscribers(self) -> bool:
        return self._sock.has_subscribers(self.topic)


# numbers the nodes' inproc control addresses in this process: the id() of a node never closed (its control
# socket still bound) was given to the next node, whose bind then failed
_CONTROL_IDS = itertools.count()

class Subscription:
    """A callback on one topic with its queue (depth None = keep all).

    stale_after_s: report "no <topic> for N s" in NodeStatus when no message came for
    this long (None = never: the topic may legitimately stay quiet). gone: also the last latched
    message of each publisher of the topic that is gone (`nodes.latched_cache`). answered_by: the
    publisher of the answers to this topic's messages (`Node.subscribe`). last_rx_s: monotonic
    time of the last message received (or of the subscription / node start).
    """

    def __init__(self, topic: str, msg_type: type[Message] | None, callback: Callable[[Message], None],
                 depth: int | None, stale_after_s: float | None = None, gone: bool = False,
                 answered_by: Publisher | None = None) -> None:
        if depth is not None and depth < 1:
            raise ValueError(f"subscription {topic}: depth {depth} must be >= 1 or None (keep all)")
        if stale_after_s is not None and stale_after_s <= 0:
            raise ValueError(f"subscription {topic}: stale_after_s {stale_after_s} must be > 0 or None")
        self.topic = topic
        self.msg_type = msg_type
        self.callback = callback
        self.depth = depth
        self.stale_after_s = stale_after_s
        self.gone = gone
        self.answered_by = answered_by
        self.queue: collections.deque = collections.deque()
        self.drops = 0
        self.received = 0
        self.last_rx_s = time.monotonic()

    def staleness(self, now_s: float) -> str | None:
        """The "no <topic> for N s" warning when the input is overdue at `now_s`, else None."""
        if self.stale_after_s is None:
            return None
        age_s = now_s - self.last_rx_s
        if age_s <= self.stale_after_s:
            return None
        return f"no {self.topic} for {age_s:.1f} s" if self.received else f"no {self.topic} yet ({age_s:.1f} s)"


@dataclass
class Timer:
    period_s: float
    callback: Callable[[], None]
    next_s: float


class _Stats:
    """Callback timings and counters over one status period."""

    def __init__(self) -> None:
        self.proc_ms: list[float] = []
        self.calls = 0
        self.errors = 0
        self.malformed = 0
        self.started = time.monotonic()
        self.cpu0 = time.process_time()
        self.wall0 = time.monotonic()


class Node:
    """Base class of every node. Subclasses set `Params` (a dataclass) and override
    `setup()` to create publishers, subscriptions and timers from `self.params`.

    STATUS_PERIOD_S: NodeStatus period (s). STUCK_AFTER_S: a callback running longer is
    reported stuck (s): pipeline callbacks take milliseconds, but a first call that
    initialises libraries lazily can take seconds on a loaded machine (the interpolator's
    first RBF solve: 0.4 s idle, 2.4 s at a load average of 8); raise it in a node whose
    callbacks legitimately take longer.
    WATCH_PERIOD_S: how often the status thread checks the node's health (s).
    CONNECT_WAIT_S: how long spin() waits for the forwarder before warning that none answers (s).
    FAILING_AFTER: calls in a row a callback has raised on when the status says it fails.
    LIVE_PARAMS: the params `fv param set` may change while the node runs (`nodes.param_service`): ones the
    node reads afresh at each use; the others need a restart.
    """

    Params: ClassVar[type] = NoParams
    STATUS_PERIOD_S: ClassVar[float] = 1.0
    STUCK_AFTER_S: ClassVar[float] = 5.0
    WATCH_PERIOD_S: ClassVar[float] = 0.2
    CONNECT_WAIT_S: ClassVar[float] = 2.0
    FAILING_AFTER: ClassVar[int] = 3
    LIVE_PARAMS: ClassVar[frozenset[str]] = frozenset()

    def __init__(self, name: str, params: dict[str, Any] | None = None, *, namespace: str = "",
                 remap: dict[str, str] | None = None, address: BusAddress | None = None) -> None:
        self.name = name
        self.namespace = absolute_namespace(namespace)
        self.remap = dict(remap or {})
        self.params = build_params(self.Params, params or {}, where=f"node {name!r}")
        self.log = logging.getLogger(name)
        self.address = address or bus_address()
        self.ctx = new_context()
        self._pub_sock = PublisherSocket(name, self.address, self.ctx)
        self._answering: list[PublisherSocket] = [self._pub_sock]  # updated by the status thread (`keep_answering`)
        self._announced: list[list[str]] = []  # [topic, type] published through sockets of its own (`announce`)
        self._publishers: list[Publisher] = []
        self._subs: dict[str, list[Subscription]] = {}
        self._arrivals = 0  # messages queued so far: each queued message carries its arrival number
        self._timers: list[Timer] = []
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self._seq = SeqTracker()
        self._stats = _Stats()
        self._totals = {"drops": 0, "malformed": 0, "errors": 0}
        self._logged_kinds: set[str] = set()
        self.state = "ok"
        self.message = ""
        self.counters: dict[str, int] = {}
        self._receiver: threading.Thread | None = None
        self._watcher: threading.Thread | None = None
        self._busy: tuple[str, float] | None = None  # (callback label, monotonic start) while one runs
        self._stuck_count = 0
        self._failing: dict[str, tuple[int, str]] = {}  # callback label -> (calls in a row that raised, the last error)
        self._no_forwarder_since_s: float | None = None  # monotonic start of a wait for a forwarder never seen
        self._failure: str | None = None  # the error fail() stopped the node with
        self._starting = True  # spin() has not yet run setup to its end: a stop signal raises (`_on_stop_signal`)
        self._ctl_addr = f"inproc://fv-node-{next(_CONTROL_IDS)}"
        self._ctl_out = self.ctx.socket(zmq.PAIR)  # used under _ctl_lock: a ZeroMQ socket is not thread-safe
        self._ctl_out.sndhwm = 0  # no limit: a command that found the queue full would be dropped (`_tell_receiver`)
        self._ctl_out.bind(self._ctl_addr)
        self._ctl_lock = threading.Lock()
        self._started = time.monotonic()
        self._status_pub = self.publisher(STATUS_TOPIC, NodeStatus, latched=True)
        self._unanswered_pub: Publisher | None = None  # made by the first subscription with answered_by
        self._param_service = ParamService(self, self._pub_sock)  # `fv param`: /<name>/param/set and .../state

    # -- names ---------------------------------------------------------------------
    def resolve(self, topic: str) -> str:
        """Absolute topic name: relative names get the namespace, then remaps apply."""
        if topic == ALL_TOPICS:
            return topic
        return resolve_topic(topic, self.namespace, self.remap)

    # -- endpoints -----------------------------------------------------------------
    def publisher(self, topic: str, msg_type: type[Message], latched: bool = False) -> Publisher:
        pub = Publisher(self._pub_sock, self.resolve(topic), msg_type, latched)
        self._publishers.append(pub)
        return pub

    def keep_answering(self, sock: PublisherSocket) -> None:
        """Have the status thread answer the forwarder's refreshes on `sock`, a publisher socket of this node's
        own besides its publishers' (a bag player's), also while it publishes nothing: a paused player's latched
        messages were taken for a gone publisher's, and a node started during the pause got no CameraInfo."""
        self._answering.append(sock)

    def announce(self, topic: str, type_name: str) -> None:
        """List `topic` (messages of `type_name`) among this node's publications in NodeStatus, for one it publishes
        through a socket of its own (a bag player's `publish_raw`): `fv topic list / info` did not see a player's
        topics, nor a node started beside it find their publisher."""
        self._announced.append([topic, type_name])

    def subscribe(self, topic: str, msg_type: type[Message] | None, callback: Callable[[Message], None],
                  depth: int | None = 10, stale_after_s: float | None = None, gone: bool = False,
                  answered_by: Publisher | None = None) -> Subscription:
        """Call `callback(msg)` for each message on `topic` (msg_type None = any type).
        With `stale_after_s` (s), NodeStatus warns when no message came for that long: give
        it for inputs that should stream (camera frames), not for occasional commands. With `gone`,
        the last latched message of a publisher of `topic` that is gone comes too (a latched topic
        reaches late joiners only from publishers that are there: `nodes.latched_cache`). With
        `answered_by` (a publisher of this node: a pipeline stage's output), a message whose callback
        publishes nothing on it (returns without, or raises) is said on `unanswered` in the node's
        namespace (`msgs.Unanswered`, with the message's stamp and topic)."""
        if answered_by is not None and self._unanswered_pub is None:
            self._unanswered_pub = self.publisher(UNANSWERED_TOPIC, Unanswered)
        sub = Subscription(self.resolve(topic), msg_type, callback, depth, stale_after_s, gone, answered_by)
        with self._cond:
            first = sub.topic not in self._subs
            self._subs.setdefault(sub.topic, []).append(sub)
        if first or gone:
            self._tell_receiver("sub " + sub.topic)
        return sub

    def _prefixes(self, topic: str) -> list[bytes]:
        """The subscription prefixes of `topic`: with those of gone publishers where a subscription asks."""
        with self._cond:
            gone = any(s.gone for s in self._subs.get(topic, ()))
        return subscription_prefixes(topic, gone)

    def timer(self, period_s: float, callback: Callable[[], None]) -> Timer:
        if period_s <= 0:
            raise ValueError(f"timer period {period_s} s must be > 0")
        t = Timer(period_s, callback, time.monotonic() + period_s)
        with self._cond:
            self._timers.append(t)
            self._cond.notify()
        return t

    # -- life cycle ----------------------------------------------------------------
    @classmethod
    def preload(cls, params: dict[str, Any]) -> None:
        """Import (and load) what `setup()` will need with these `params`, so a standby process
        (`fv node KIND --standby`) can take over at once; override when setup imports heavy modules
        (torch) or reads files (a model)."""

    def setup(self) -> None:
        """Create the node's publishers, subscriptions and timers (override)."""

    def teardown(self) -> None:
        """Release the node's resources (override when it holds devices or files)."""

    def warn(self, message: str, kind: str | None = None) -> None:
        """Report a degraded state in NodeStatus and log it, once per `kind`: what the warning is
        about, without the figures its message carries ("window rejected" for "window rejected: 12
        non-finite values"); default the message itself (a message with a count then logs each new count)."""
        self.state, self.message = "warn", message
        self._log_once("warn:" + (message if kind is None else kind), logging.WARNING, message)

    def clear_warning(self) -> None:
        """Back to "ok" in NodeStatus: the node's own warning is over (runtime faults are apart)."""
        self.state, self.message = "ok", ""

    def fail(self, message: str) -> None:
        """Stop the node for an error it cannot go on from: a configuration error found while it runs (a
        simulated scene whose next frame cannot be played), which a retry would meet again. NodeStatus says
        it at once (state "error", "stopped: <message>"), then spin() raises NodeFailed(message), so that
        `fv node` exits CONFIG_WHILE_RUNNING, saying it, and a launch stops rather than start it again."""
        self.state, self.message = "error", f"stopped: {message}"
        self._failure = message
        self._publish_status()
        self.stop()

    def stop(self) -> None:
        self._stop.set()
        with self._cond:
            self._cond.notify_all()

    @property
    def stopped(self) -> bool:
        return self._stop.is_set()

    def spin(self, install_signals: bool = True) -> None:
        """Run setup, then callbacks and timers until stop() or one of `stop_signals()`; NodeFailed after
        fail(). With `install_signals` (in the main thread), a stop signal that comes before setup has
        returned raises `Stopped(signum)` (`_on_stop_signal`)."""
        try:
            if install_signals and threading.current_thread() is threading.main_thread():
                on_stop_signals(self._on_stop_signal)
            self._receiver = threading.Thread(target=self._receive_loop, name=f"{self.name}-rx", daemon=True)
            self._receiver.start()
            started_s = time.monotonic()
            if not self._pub_sock.wait_connected(self.CONNECT_WAIT_S):
                from nodes.forwarder import silent_forwarder  # only then: a node's start does without the module

                self._no_forwarder_since_s = started_s
                self.log.warning("no forwarder answers on %s; %s (waiting for it)", self.address.url,
                                 silent_forwarder(self.address) or "start one with `fv forwarder` or `fv launch`")
            self.setup()
            self._starting = False
            self._watcher = threading.Thread(target=self._watch_loop, name=f"{self.name}-status", daemon=True)
            self._watcher.start()
            self._executor_loop()
        finally:
            self._starting = False  # (a setup that raised: its teardown is not cut short)
            self.close()
        if self._failure is not None:
            raise NodeFailed(self._failure)

    def _on_stop_signal(self, signum: int) -> None:
        """The node's stop on one of `stop_signals()`. Before its setup has returned (the forwarder's wait,
        torch's import, a model's load and first pass) it is cut short there by `Stopped(signum)`, raised
        where it runs: the slip detector's setup ran to its end first (1 to 4 s on 2 cores), past the
        launcher's grace time, which then killed it (2 of 5 launches stopped 3 s after their start). The node
        is stopped first, should that exception be lost (raised where Python ignores exceptions), so that it
        stops once its setup is done."""
        self.stop()
        if self._starting:
            raise Stopped(signum)

    def close(self) -> None:
        self._stop.set()
        try:
            self.teardown()
        finally:
            if self._watcher is not None:
                self._watcher.join(2.0)
            if self._receiver is not None:
                self._tell_receiver("stop")
                self._receiver.join(2.0)
            with self._ctl_lock:
                self._ctl_out.close(linger=0)
            self._pub_sock.close()

    # -- receiving -----------------------------------------------------------------
    def _tell_receiver(self, command: str) -> None:
        """Send the receiving thread ``command`` ("sub TOPIC" or "stop") without waiting. A PAIR send waits for
        its peer: for a thread that has not connected yet, with no limit, and for one that has returned, for good.
        Neither needs it: once connected, the thread returns if the node is stopped and subscribes every topic
        subscribed by then (`_receive_loop`). Under `_ctl_lock`: `subscribe` may be called from any thread (a
        callback, a thread of the node's own) while another subscribes or `close` runs; a command after `close` is
        dropped."""
        with self._ctl_lock:
            if self._receiver is not None and self._receiver.is_alive() and not self._ctl_out.closed:
                with contextlib.suppress(zmq.Again):
                    self._ctl_out.send_string(command, zmq.NOBLOCK)

    def _receive_loop(self) -> None:
        sub = subscriber_socket(self.ctx, self.address)
        ctl = self.ctx.socket(zmq.PAIR)
        ctl.connect(self._ctl_addr)
        try:
            if self._stop.is_set():  # stopped before this connection: its "stop" could not be sent (`close`)
                return
            with self._cond:
                topics = list(self._subs)
            for topic in topics:
                for prefix in self._prefixes(topic):
                    sub.setsockopt(zmq.SUBSCRIBE, prefix)
            poller = zmq.Poller()
            poller.register(sub, zmq.POLLIN)
            poller.register(ctl, zmq.POLLIN)
            while True:
                ready = dict(poller.poll())
                if ctl in ready:
                    cmd = ctl.recv_string()
                    if cmd == "stop":
                        return
                    for prefix in self._prefixes(cmd[4:]):
                        sub.setsockopt(zmq.SUBSCRIBE, prefix)
                if sub in ready:
                    while sub.poll(0):
                        self._enqueue(sub.recv_multipart(copy=False))
        finally:
            sub.close(linger=0)
            ctl.close(linger=0)

    def _enqueue(self, frames: list[zmq.Frame]) -> None:
        node = None  # the publisher, once the envelope is read
        try:
            topic, node, latched = parse_envelope(frames[0])
            if len(frames) < 2:
                raise ValueError(f"topic {topic!r}: no header frame")
            header = msgs.decode_header(frames[1], topic)
        except (ValueError, MessageError) as exc:
            self._malformed(exc, node)
            return
        gone = frames[0].bytes[:1] == GONE
        with self._cond:
            if not self._seq.accept(topic, node, header["seq"], latched, header["pub_ns"]):
                return
            targets = [s for s in list(self._subs.get(topic, ())) + list(self._subs.get(ALL_TOPICS, ()))
                       if s.gone or not gone]
            now = time.monotonic()
            self._arrivals += 1
            for s in targets:
                s.received += 1
                s.last_rx_s = now
                s.queue.append((self._arrivals, topic, node, frames[1:]))
                limit = s.depth or KEEP_ALL_CAP
                while len(s.queue) > limit:
                    s.queue.popleft()
                    s.drops += 1
                    self._totals["drops"] += 1
            self._cond.notify()

    # -- executing -----------------------------------------------------------------
    def _next_work(self) -> tuple[Subscription, str, str, list] | Timer | None:
        """Wait for the next due timer or queued message (its subscription, topic, publishing node and
        frames after the envelope); None when stopping."""
        with self._cond:
            while not self._stop.is_set():
                now = time.monotonic()
                due = min(self._timers, key=lambda t: t.next_s, default=None)
                if due is not None and due.next_s <= now:
                    due.next_s = max(due.next_s + due.period_s, now)
                    return due
                waiting = [s for subs in self._subs.values() for s in subs if s.queue]
                if waiting:  # the message that arrived first, of any topic
                    s = min(waiting, key=lambda s: s.queue[0][0])
                    _, topic, node, frames = s.queue.popleft()
                    return s, topic, node, frames
                # a timer due past threading.TIMEOUT_MAX (292 years: a camera at fps 1e-12) is waited for in steps:
                # a longer wait raised OverflowError and ended the node
                self._cond.wait(None if due is None else min(due.next_s - now, threading.TIMEOUT_MAX))
        return None

    def _executor_loop(self) -> None:
        while True:
            work = self._next_work()
            if work is None:
                return
            if isinstance(work, Timer):
                self._run(work.callback, label=f"timer {_name(work.callback)}")
                continue
            sub, topic, node, frames = work
            try:
                msg = msgs.decode(frames, topic)
                if sub.msg_type is not None and not isinstance(msg, sub.msg_type):
                    raise MessageError(topic, msg.TYPE, "type", f"subscription expects {sub.msg_type.TYPE}")
            except MessageError as exc:
                self._malformed(exc, node)
                continue
            answers = None if sub.answered_by is None else sub.answered_by.count
            self._run(sub.callback, msg, label=f"callback {_name(sub.callback)} ({topic})",
                      timed=topic != STATUS_TOPIC)
            if answers is not None and sub.answered_by.count == answers:
                self._unanswered_pub.publish(Unanswered(stamp_ns=msg.stamp_ns, frame_id=msg.frame_id, topic=topic))

    def _run(self, fn: Callable, *args: Any, label: str, timed: bool = True) -> None:
        """Call fn(*args), timing it for NodeStatus (when `timed`: not the other nodes' statuses a node
        may follow, which would add to its rate) and showing it to the watchdog as `label` while it
        runs; an exception is counted and logged once per kind, never raised, and calls in a row that
        raised are kept for the status (`FAILING_AFTER`)."""
        t0 = time.perf_counter()
        self._busy = (label, time.monotonic())
        name = _name(fn)
        try:
            fn(*args)
        except Exception as exc:  # a node never dies on one bad callback
            self._stats.errors += 1
            self._totals["errors"] += 1
            self._failing[label] = (self._failing.get(label, (0, ""))[0] + 1, f"{type(exc).__name__}: {exc}")
            self._log_once(f"err:{type(exc).__name__}:{name}", logging.ERROR,
                           f"{name} raised {type(exc).__name__}: {exc} (counted; repeats not logged)",
                           exc_info=True)
        else:
            self._failing.pop(label, None)
        finally:
            self._busy = None
        if timed:
            self._stats.calls += 1
            self._stats.proc_ms.append((time.perf_counter() - t0) * 1e3)

    def _malformed(self, exc: Exception, node: str | None = None) -> None:
        """Count and log (once per topic, type and field) a message dropped as malformed, naming its
        publishing `node` when its envelope could be read."""
        with self._cond:  # counted from the receiver and the executor thread
            self._totals["malformed"] += 1
        kind = f"{getattr(exc, 'topic', '?')}:{getattr(exc, 'type_name', '?')}:{getattr(exc, 'field', type(exc).__name__)}"
        sender = "" if node is None else f" from node {node!r}"
        self._log_once("bad:" + kind, logging.WARNING,
                       f"dropped malformed message{sender}: {exc} (counted; repeats not logged)")

    def _log_once(self, kind: str, level: int, text: str, exc_info: bool = False) -> None:
        if kind not in self._logged_kinds:
            self._logged_kinds.add(kind)
            self.log.log(level, text, exc_info=exc_info)

    # -- status --------------------------------------------------------------------
    def _faults(self, now_s: float) -> list[tuple[str, str, str]]:
        """(state, kind, message) of each runtime fault at `now_s`: a stuck callback,
        overdue inputs, an unreachable forwarder (the node's own warn() comes on top).
        `kind` names the fault without its duration."""
        faults = []
        busy = self._busy
        if busy is not None and now_s - busy[1] > self.STUCK_AFTER_S:
            faults.append(("error", f"stuck {busy[0]}", f"{busy[0]} stuck for {now_s - busy[1]:.1f} s"))
        with self._cond:
            subs = [s for ss in self._subs.values() for s in ss]
        faults += [("warn", f"stale {s.topic}", text) for s in subs if (text := s.staleness(now_s)) is not None]
        faults += [("error", f"failing {label}", f"{label} raised on its last {calls} calls: {error}")
                   for label, (calls, error) in list(self._failing.items()) if calls >= self.FAILING_AFTER]
        never_since = self._no_forwarder_since_s
        if never_since is not None:
            faults.append(("warn", "bus", f"no forwarder answers on {self.address.url} ({now_s - never_since:.1f} s): "
                                          "start one with `fv forwarder` or `fv launch`"))
        down_since = self._pub_sock.down_since_s
        if down_since is not None:
            faults.append(("warn", "bus", f"forwarder {self.address.url} unreachable for {now_s - down_since:.1f} s"))
        return faults

    def health(self, now_s: float | None = None) -> tuple[str, str]:
        """The (state, message) NodeStatus reports at `now_s` (monotonic, default now):
        the worst of the node's own state and the runtime faults; the messages joined by
        "; ", worst first."""
        now_s = time.monotonic() if now_s is None else now_s
        reports = [(self.state, self.message)] + [(state, text) for state, _, text in self._faults(now_s)]
        reports.sort(key=lambda r: -_SEVERITY.get(r[0], 2))
        state = reports[0][0] if _SEVERITY.get(reports[0][0], 2) > 0 else "ok"
        return state, "; ".join(text for _, text in reports if text)

    def status(self) -> NodeStatus:
        """The NodeStatus for the period since the last call (resets period stats)."""
        st, self._stats = self._stats, _Stats()
        now = time.monotonic()
        wall = max(now - st.wall0, 1e-9)
        proc = np.asarray(st.proc_ms) if st.proc_ms else np.zeros(1)
        try:
            with open("/proc/self/statm") as f:
                rss = int(f.read().split()[1]) * _PAGE
        except OSError:
            rss = 0
        with self._cond:
            subs = [[t, (s.msg_type.TYPE if s.msg_type else "*")] for t, ss in self._subs.items() for s in ss
                    if t != self._param_service.set_topic]
        state, message = self.health(now)
        return NodeStatus(
            stamp_ns=time.time_ns(), state=state, message=message, pid=os.getpid(),
            uptime_s=now - self._started, rate_hz=st.calls / wall,
            proc_ms_mean=float(proc.mean()), proc_ms_p99=float(np.percentile(proc, 99)),
            drops=self._totals["drops"], gaps=self._seq.gaps, malformed=self._totals["malformed"],
            errors=self._totals["errors"], cpu_percent=100.0 * (time.process_time() - st.cpu0) / wall,
            rss_bytes=rss, publishes=[[p.topic, p.msg_type.TYPE] for p in self._publishers] + self._announced,
            subscribes=subs, counters={**self.counters, "bus_reconnects": self._pub_sock.reconnects,
                                       "stuck_callbacks": self._stuck_count})

    def _publish_status(self) -> None:
        self._status_pub.publish(self.status())

    def _watch_loop(self) -> None:
        """The status thread: NodeStatus every STATUS_PERIOD_S and at once when the health
        changes (which fault, not how long it has lasted); logs stuck callbacks and the
        forwarder going and coming back (or answering at last). An exception in one round is logged
        once per kind and the thread goes on: a node whose status stopped dropped out of `fv node list`."""
        now = time.monotonic()
        with self._cond:
            for s in (s for ss in self._subs.values() for s in ss if not s.received):
                s.last_rx_s = now  # overdue counts from the start of spinning, not from setup
        watch = _Watch(next_status_s=now)
        while True:
            try:
                self._watch_once(watch)
            except Exception as exc:  # the watchdog outlives whatever one round met
                self._log_once(f"status:{type(exc).__name__}", logging.ERROR,
                               f"status thread: {type(exc).__name__}: {exc} (going on; repeats not logged)",
                               exc_info=True)
            if self._stop.wait(self.WATCH_PERIOD_S):
                return

    def _watch_once(self, watch: _Watch) -> None:
        """One round of the status thread; `watch` holds what the rounds share."""
        for sock in self._answering:
            sock.update()
        now = time.monotonic()
        never_since = self._no_forwarder_since_s
        if never_since is not None and self._pub_sock.connected:
            self._no_forwarder_since_s = None
            self.log.info("forwarder %s answers after %.1f s", self.address.url, now - never_since)
        busy = self._busy
        stuck = busy if busy is not None and now - busy[1] > self.STUCK_AFTER_S else None
        if stuck is not None and stuck != watch.stuck_since:
            self._stuck_count += 1
            self.log.error("%s stuck for %.1f s (watchdog; reported in NodeStatus)", stuck[0], now - stuck[1])
        elif stuck is None and watch.stuck_since is not None:
            self.log.warning("%s returned after %.1f s", watch.stuck_since[0], now - watch.stuck_since[1])
        watch.stuck_since = stuck
        down = self._pub_sock.down_since_s
        if down is not None and watch.down_since is None:
            self.log.warning("forwarder %s gone; reconnecting", self.address.url)
        elif down is None and watch.down_since is not None:
            self.log.info("forwarder %s back after %.1f s (reconnect %d); latched messages re-sent",
                          self.address.url, now - watch.down_since, self._pub_sock.reconnects)
        watch.down_since = down
        kinds = (self.state, self.message, [kind for _, kind, _ in self._faults(now)])
        if now >= watch.next_status_s or kinds != watch.last_kinds:
            watch.next_status_s, watch.last_kinds = now + self.STATUS_PERIOD_S, kinds
            self._publish_status()


@dataclass
class _Watch:
    """What the status thread's rounds share: when the next NodeStatus is due (monotonic s), the
    health last published, and the stuck callback and forwarder outage last seen."""

    next_status_s: float
    last_kinds: tuple | None = None
    stuck_since: tuple[str, float] | None = None
    down_since: float | None = None


def launch_started_ns() -> int:
    """When the `fv launch` that started this process started (ns since the epoch); 0 for a node started
    by hand."""
    return int(os.environ.get(LAUNCH_ENV, "0"))


def _name(fn: Callable) -> str:
    """A callable's name for messages (on_image, tick)."""
    return getattr(fn, "__name__", repr(fn))
