"""The robot-code client: read a topic in a few lines, without writing a node.

Iterator form (blocking, in the caller's thread)::

    from nodes.client import subscribe

    with subscribe("/slip", timeout_s=1.0) as states:
        for state in states:          # SlipState messages, in order
            if state.slip:
                gripper.squeeze()

Callback form (a background thread calls the function)::

    from nodes.client import listen

    with listen("/slip", lambda state: state.slip and gripper.squeeze()):
        robot.run_task()

`timeout_s` makes silence an error (`SilenceError`, a `TimeoutError` saying whether the bus answered then): a gripper
that stops hearing the slip detector should know. A listener given `timeout_s` calls `on_timeout` with
that error, from its thread, once per silence. A message of another type than expected (a NodeStatus published on
`/slip` by mistake) or one that cannot be decoded is dropped, counted and logged (at most every
`LOG_EVERY_S` per kind): it never reaches the loop nor stops a listener. The bus is the one
`FV_BUS` names (default: this host's).

Publishing (the gripper closed: every tracker takes a new reference, a new grasp starts)::

    from nodes.client import reset_grasp

    gripper.close()
    reset_grasp()                  # or reset_grasp(confirm=["/"]): TimeoutError unless the tracker took it

or, for any topic, ``with advertise("/my/topic") as pub: pub.publish(msg)``. A latched message
(``advertise(..., latched=True)``) reaches later subscribers while its publisher is open, as in ROS.

Tuning a running node (`fv param set` from Python; only the params a node takes live, e.g. a slip detector's
`threshold`; ValueError when the node refuses, TimeoutError when it does not answer)::

    from nodes.client import set_param

    set_param("slip_detector", "threshold", 0.7)
"""
from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from abc import ABC, abstractmethod
from typing import Any, Callable, Iterator, Sequence, TypeVar

from msgs import (CameraInfo, ContactSummary, DisplacementField, GraspStart, Image, MarkerArray, Message, NodeStatus,
                  SlipState)
from msgs.wire import check_message
from nodes.bus import PublisherSocket, TopicReader, absolute_namespace, check_timeout, resolve_topic, validate_topic
from nodes.endpoints import BusAddress
from nodes.forwarder import ping, silent_forwarder
from nodes.param_service import ANSWER_TIMEOUT_S, read_params, set_params

log = logging.getLogger("fv.client")
POLL_S = 0.1
LOG_EVERY_S = 10.0  # a kind of dropped message is logged when first seen, then at most this often
# what the pipeline publishes on a topic of each name, in any namespace (/slip, /left/slip): the type
# `subscribe` expects when given none
TOPIC_TYPES: dict[str, type[Message]] = {
    "slip": SlipState, "field": DisplacementField, "contact": ContactSummary, "markers": MarkerArray,
    "markers/reference": MarkerArray, "camera/image": Image, "camera/info": CameraInfo, "status": NodeStatus,
}


def expected_type(topic: str) -> type[Message]:
    """The type the pipeline publishes on `topic` (`TOPIC_TYPES`, by the end of its name), or
    `Message` (any type) for a topic of another name."""
    for name, cls in TOPIC_TYPES.items():
        if topic == "/" + name or topic.endswith("/" + name):
            return cls
    return Message


class SilenceError(TimeoutError):
    """No message on `topic` for `timeout_s` s. Its text says whether the forwarder at `address` answered
    when the silence was raised (when it did not, the launch that served the bus is gone, or its forwarder is
    stopped or hung, which it names: `nodes.forwarder.silent_forwarder`): a thread asks it then (`ping`: up to
    `nodes.forwarder.ANSWER_WAIT_S`, 2 s), so the raise a gripper acts on is never held back; reading the text, or
    `bus_answers`, waits for that answer. `answers` and `silent` give it instead (a copy, an unpickled one)."""

    def __init__(self, topic: str, timeout_s: float, address: BusAddress, answers: bool | None = None,
                 silent: str = "") -> None:
        super().__init__(f"no message on {topic} within {timeout_s} s")
        self.topic = topic
        self.timeout_s = timeout_s
        self.address = address
        self._answers = answers
        self._silent = silent  # the forwarder that holds the bus but did not answer ("" when none)
        self._asking: threading.Thread | None = None
        if answers is None:
            self._asking = threading.Thread(target=self._ask, name=f"fv-silence{topic}", daemon=True)
            self._asking.start()

    def _ask(self) -> None:
        """Ping the forwarder (the thread started at the raise); name it when it runs but does not answer."""
        self._answers = ping(self.address) is not None
        if not self._answers:
            self._silent = silent_forwarder(self.address)

    @property
    def bus_answers(self) -> bool:
        """Whether the forwarder answered a ping sent as the silence was raised (waits for it)."""
        if self._asking is not None:
            self._asking.join()
        return bool(self._answers)

    def __str__(self) -> str:
        url = self.address.url
        why = (f"the forwarder at {url} still answers" if self.bus_answers
               else f"no forwarder answers on {url}: {self._silent or 'the launch is gone or not started'}")
        return f"{self.args[0]} ({why})"

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self)!r})"

    def __reduce__(self) -> tuple[type[SilenceError], tuple[str, float, BusAddress, bool, str]]:
        """Copied and pickled with its answer (the exception's args are its text alone)."""
        return type(self), (self.topic, self.timeout_s, self.address, self.bus_answers, self._silent)


_C = TypeVar("_C", bound="_Closing")


class _Closing(ABC):
    """A context manager that calls `self.close()` on exit."""

    @abstractmethod
    def close(self) -> None:
        """Release the sockets (and threads) the object holds."""

    def __enter__(self: _C) -> _C:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Subscription(_Closing):
    """Messages of one topic, read on demand; iterate it, or call `recv()`.

    msg_type: the expected class; None for the type the pipeline publishes on a topic of that
    name (`expected_type`: SlipState on /slip and /left/slip), any type on other topics; `Message`
    for any type. A message of another type is dropped and counted in `wrong_type`, one that cannot
    be decoded in `malformed`; both are logged when first seen, then at most every `LOG_EVERY_S`.
    timeout_s: longest silence allowed while iterating, None = wait forever.
    latest: skip to the newest message when several are waiting (for control loops
    slower than the topic); default keeps every message in order.
    """

    def __init__(self, topic: str, msg_type: type[Message] | None = None, *, timeout_s: float | None = None,
                 latest: bool = False, address: BusAddress | None = None) -> None:
        check_timeout(timeout_s)
        if msg_type is not None and not (isinstance(msg_type, type) and issubclass(msg_type, Message)):
            raise TypeError(f"msg_type {msg_type!r} is not a message class (msgs.SlipState, ...; None: the topic's "
                            "own): a listener's thread died on it at the first message")
        self.topic = validate_topic(topic)  # '' (an unset variable) would be every topic
        self.msg_type = expected_type(topic) if msg_type is None else msg_type
        self.timeout_s = timeout_s
        self.latest = latest
        self.wrong_type = 0
        self._closed = False
        self._logged_s: dict[str, float] = {}  # kind of dropped message -> when it was last logged (monotonic s)
        self._reader = TopicReader([topic], address)

    def recv(self, timeout_s: float | None = None) -> Message | None:
        """The next message of the expected type (the newest one waiting when `latest`), or None
        after `timeout_s`; others are dropped and counted on the way."""
        msg = self._next(timeout_s)
        if msg is not None and self.latest:
            while (newer := self._next(0)) is not None:
                msg = newer
        return msg

    def _next(self, timeout_s: float | None) -> Message | None:
        """The next message of the expected type within `timeout_s`, or None."""
        if self._closed:  # (ZeroMQ's "Operation not supported" before)
            raise RuntimeError(f"the subscription to {self.topic} is closed")
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        while True:
            malformed = self._reader.malformed
            item = self._reader.recv(None if deadline is None else max(0.0, deadline - time.monotonic()))
            if self._reader.malformed != malformed:
                self._log_drop("malformed", "malformed", self._reader.malformed, self._reader.last_malformed)
            if item is None:
                return None
            if isinstance(item.msg, self.msg_type):
                return item.msg
            self.wrong_type += 1
            self._log_drop(f"type {item.msg.TYPE}", "wrong_type", self.wrong_type,
                           f"a {item.msg.TYPE} from node {item.msg.node!r}, not a {self.msg_type.TYPE}")

    def _log_drop(self, kind: str, counter: str, count: int, why: str) -> None:
        """Log a dropped message of `kind` (counted in `counter`, now `count`) when first seen, then at
        most every LOG_EVERY_S."""
        now = time.monotonic()
        if now - self._logged_s.get(kind, -LOG_EVERY_S) >= LOG_EVERY_S:
            self._logged_s[kind] = now
            log.warning("%s: dropped %s (%s: %d; logged at most every %g s)", self.topic, why, counter, count,
                        LOG_EVERY_S)

    def __iter__(self) -> Iterator[Message]:
        while True:
            msg = self.recv(self.timeout_s)
            if msg is None:
                raise SilenceError(self.topic, self.timeout_s, self.address)
            yield msg

    @property
    def address(self) -> BusAddress:
        """The bus read."""
        return self._reader.address

    @property
    def malformed(self) -> int:
        """Messages dropped because they could not be decoded."""
        return self._reader.malformed

    @property
    def gaps(self) -> int:
        """Messages missed, by sequence number."""
        return self._reader.seq.gaps

    def close(self) -> None:
        self._closed = True
        self._reader.close()


def subscribe(topic: str, msg_type: type[Message] | None = None, *, timeout_s: float | None = None,
              latest: bool = False, address: BusAddress | None = None) -> Subscription:
    """Subscribe to `topic`: ``for msg in subscribe("/slip"): ...`` (see `Subscription`)."""
    return Subscription(topic, msg_type, timeout_s=timeout_s, latest=latest, address=address)


def wait_for_message(topic: str, msg_type: type[Message] | None = None, timeout_s: float = 5.0,
                     address: BusAddress | None = None) -> Message:
    """The next message on `topic` (a latched one arrives at once); TimeoutError after `timeout_s`."""
    check_timeout(timeout_s)
    with Subscription(topic, msg_type, address=address) as sub:
        msg = sub.recv(timeout_s)
        if msg is None:
            raise SilenceError(sub.topic, timeout_s, sub.address)
    return msg


class Listener(_Closing):
    """Calls `callback(msg)` for each message of `topic` from a background thread until
    `close()`. A callback that raises is logged and counted in `errors`; a message of another type
    or that cannot be decoded is dropped and counted in `wrong_type` or `malformed` (see
    `Subscription`); the thread goes on. What `subscribe` refuses (a topic without its leading '/', a TCP
    bus without `FV_CURVE_DIR`) raises here, in the caller's thread, before any thread starts.

    timeout_s: with it, silence that long calls `on_timeout(error)` (the `SilenceError` `subscribe` raises,
    saying whether the bus answered then) from the thread, once per silence (up to `POLL_S` after
    `timeout_s`: the thread looks every `POLL_S`), counted in `timeouts`;
    without `on_timeout` the error is logged. An `on_timeout` that raises is logged and counted in `errors`.
    ValueError for a `timeout_s` <= 0, and for an `on_timeout` without `timeout_s` (it would never be called).
    """

    def __init__(self, topic: str, callback: Callable[[Message], object], msg_type: type[Message] | None = None,
                 *, latest: bool = False, timeout_s: float | None = None,
                 on_timeout: Callable[[TimeoutError], object] | None = None, address: BusAddress | None = None) -> None:
        check_timeout(timeout_s)
        if on_timeout is not None and timeout_s is None:
            raise ValueError("on_timeout is never called without timeout_s (the silence, s, that calls it)")
        if not callable(callback) or (on_timeout is not None and not callable(on_timeout)):  # (each message logged
            raise TypeError(f"callback {callback!r} and on_timeout must be callable")  # a TypeError before)
        self.topic = topic
        self.callback = callback
        self.timeout_s = timeout_s
        self.on_timeout = on_timeout
        self.timeouts = 0
        self.errors = 0
        self.received = 0
        self.wrong_type = 0
        self.malformed = 0
        self._stop = threading.Event()
        # built here so that its errors reach the caller; from start() on, only the thread uses its socket
        # (ZeroMQ allows moving a socket to another thread across a memory barrier, which start() is)
        sub = Subscription(topic, msg_type, latest=latest, address=address)
        self._thread = threading.Thread(target=self._loop, args=(sub,), name=f"listen-{topic}", daemon=True)
        self._thread.start()

    def _loop(self, sub: Subscription) -> None:
        heard_s = time.monotonic()  # when the last message came, or the listener started
        told = False  # this silence was reported
        with sub:
            while not self._stop.is_set():
                msg = sub.recv(POLL_S)
                self.wrong_type, self.malformed = sub.wrong_type, sub.malformed
                if msg is None:
                    if self.timeout_s is not None and not told and time.monotonic() - heard_s > self.timeout_s:
                        told = True
                        self.timeouts += 1
                        self._call("on_timeout", self.on_timeout or _log_silence,
                                   SilenceError(self.topic, self.timeout_s, sub.address))
                    continue
                heard_s, told = time.monotonic(), False
                self.received += 1
                self._call("callback", self.callback, msg)

    def _call(self, what: str, func: Callable[[Any], object], arg: object) -> None:
        """`func(arg)` (the `what`); robot code keeps listening when it raises: the error is logged and counted."""
        try:
            func(arg)
        except Exception:
            self.errors += 1
            log.exception("%s for %s raised", what, self.topic)

    def close(self, timeout_s: float = 1.0) -> None:
        """Stop the thread, waiting up to `timeout_s` for a callback that runs; one still running then is
        logged (it returned without a word, the callback going on beside the code after the `with`), and
        no other follows it. Called from the listener's own callback (a gripper that stops listening once
        it has seen a slip), it stops the thread after that callback and returns at once (it raised
        RuntimeError: a thread cannot join itself)."""
        self._stop.set()
        if threading.current_thread() is self._thread:
            return
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            log.warning("listener for %s closed while its callback still runs after %g s: no other call follows",
                        self.topic, timeout_s)


def _log_silence(error: TimeoutError) -> None:
    """A listener's silence, without an `on_timeout`: logged."""
    log.warning("%s", error)


def listen(topic: str, callback: Callable[[Message], object], msg_type: type[Message] | None = None, *,
           latest: bool = False, timeout_s: float | None = None,
           on_timeout: Callable[[TimeoutError], object] | None = None, address: BusAddress | None = None) -> Listener:
    """Call `callback(msg)` for each message on `topic` in a background thread (see `Listener`)."""
    return Listener(topic, callback, msg_type, latest=latest, timeout_s=timeout_s, on_timeout=on_timeout,
                    address=address)


RESET_TOPIC = "/tracker/reset"  # any message on it starts a new grasp on every tracker
GRASP_START_TOPIC = "markers/grasp_start"  # in a tracker's namespace: each grasp it starts (`msgs.GraspStart`)
PASS_START_TOPIC = "camera/pass_start"  # in a camera's namespace: each pass of its video or folder (`msgs.GraspStart`)


class Publisher(_Closing):
    """Publishes robot-code messages on `topic` (close() it, or use it as a context manager).

    `topic` is refused as `subscribe` refuses it (ValueError for "slip", without its '/'). It waits up to
    `connect_timeout_s` for the bus to take its messages (TimeoutError naming the
    bus when none answers): a message sent before that would be lost without a word. `publish` checks
    each message as subscribers will (`check_message`): one they would drop as malformed raises here.
    A latched publisher's last message reaches later subscribers until it is closed: a thread answers
    the forwarder's refreshes (`nodes.latched_cache`) while the caller publishes nothing.
    """

    def __init__(self, topic: str, *, name: str | None = None, latched: bool = False, connect_timeout_s: float = 2.0,
                 address: BusAddress | None = None) -> None:
        self.topic = validate_topic(topic)  # "slip" was published where no subscriber can ask for it
        check_timeout(connect_timeout_s)
        self.latched = latched
        self._sock = PublisherSocket(default_name() if name is None else name, address)
        if not self._sock.wait_connected(connect_timeout_s):
            url = self._sock.address.url
            self._sock.close()
            raise TimeoutError(f"no forwarder took {topic} on {url} within {connect_timeout_s} s "
                               "(is a launch running on this FV_BUS?)")
        self._closed = threading.Event()
        self._keeper: threading.Thread | None = None
        if latched:
            self._keeper = threading.Thread(target=self._sock.answer_until, args=(self._closed,),
                                            name=f"fv-latched{topic}", daemon=True)
            self._keeper.start()

    def publish(self, msg: Message) -> None:
        """Send `msg` (stamped with seq, pub_ns and node); ValueError "Type.field: reason" for a message
        subscribers would drop (`SlipState.probability: 1.5 is not in [0, 1]`). A numpy scalar of a
        scalar field is sent, and left on `msg`, as its plain Python value."""
        if self._closed.is_set():  # (ZeroMQ's "Operation not supported" before)
            raise RuntimeError(f"the publisher of {self.topic} is closed")
        check_message(msg)
        self._sock.publish(self.topic, msg, self.latched)

    def close(self) -> None:
        self._closed.set()
        if self._keeper is not None:
            self._keeper.join()
        self._sock.close()


def default_name() -> str:
    """The name robot code publishes under when it gives none: `robot_<pid>`, one per process, as ROS names
    anonymous nodes. Under one shared name ("robot", before) two scripts' latched messages on one topic were
    one to the bus: a late subscriber got only the last one's, and each script's sequence read as the
    other's gaps."""
    return f"robot_{os.getpid()}"


def advertise(topic: str, *, name: str | None = None, latched: bool = False, connect_timeout_s: float = 2.0,
              address: BusAddress | None = None) -> Publisher:
    """A `Publisher` on `topic` under `name` (default `default_name()`):
    ``with advertise("/my/topic") as pub: pub.publish(msg)``."""
    return Publisher(topic, name=name, latched=latched, connect_timeout_s=connect_timeout_s, address=address)


def reset_grasp(*, confirm: Sequence[str] = (), timeout_s: float = 1.0, connect_timeout_s: float = 2.0,
                address: BusAddress | None = None) -> None:
    """Start a new grasp: one message on /tracker/reset (call it when the gripper closes). Every
    tracker takes its next frame as the reference; the slip detectors judge the grasp from there.

    confirm: the namespace, or namespaces, of the trackers that must say they took it ("/" for the one-camera
    launch files, "/left" and "/right", or "left" and "right" as launch files write them, for a pair's), each on
    `GRASP_START_TOPIC` in its namespace (a `GraspStart` stamped as this reset). TimeoutError naming those that did not within
    `timeout_s` s: a tracker that is not running (respawning as the reset came) never takes it, and the bus
    keeps no reset for it; call again."""
    check_timeout(timeout_s)
    check_timeout(connect_timeout_s)
    confirm = [confirm] if isinstance(confirm, str) else confirm  # one namespace ("/left" was read as /, l, e, f, t)
    topics = {resolve_topic(GRASP_START_TOPIC, absolute_namespace(ns)): ns for ns in confirm}
    stamp_ns = time.time_ns()
    with (TopicReader(sorted(topics), address) if topics else contextlib.nullcontext()) as reader, advertise(
            RESET_TOPIC, name="robot_reset", connect_timeout_s=connect_timeout_s, address=address) as pub:
        pub.publish(SlipState(stamp_ns=stamp_ns))
        deadline = time.monotonic() + timeout_s
        while topics and (left_s := deadline - time.monotonic()) > 0:
            item = reader.recv(left_s)
            if (item is not None and isinstance(item.msg, GraspStart) and item.msg.cause == "reset"
                    and item.msg.stamp_ns == stamp_ns):
                topics.pop(item.topic, None)
    if topics:
        raise TimeoutError(f"no tracker took the reset within {timeout_s:g} s in {', '.join(topics.values())} "
                           f"(on {', '.join(topics)}): none runs there, or it was respawning; call reset_grasp again")


def set_param(node: str, name: str, value: Any, *, timeout_s: float = ANSWER_TIMEOUT_S,
              address: BusAddress | None = None) -> Any:
    """Set param `name` of the running node `node` (its name as `fv node list` shows it, "left_slip_detector",
    or its ROS-style path, "/left/slip_detector": `nodes.param_service.param_topics`) to `value` and return
    it as the node now holds it, as `fv param set` does (`nodes.param_service`): from the node's next callback
    on. `ParamError` (a ValueError) with the node's reason when it refuses it (an unknown param, a wrong type,
    an invalid value, one it takes only at start); TimeoutError when it does not answer within `timeout_s` s."""
    return set_params(node, {name: value}, timeout_s, address).params[name]


def get_params(node: str, *, timeout_s: float = ANSWER_TIMEOUT_S, address: BusAddress | None = None) -> dict[str, Any]:
    """{name: value} of the running node `node`'s params now (`fv param get`; its name or path, as for
    `set_param`); TimeoutError when it does not answer within `timeout_s` s."""
    return read_params(node, timeout_s, address).params
