"""The robot-code client: read a topic in a few lines, without writing a node.

Iterator form (blocking, in the caller's thread)::

    from nodes.client import subscribe

    with subscribe("/slip", timeout_s=0.5) as states:
        for state in states:          # SlipState messages, in order
            if state.slip:
                gripper.squeeze()

Callback form (a background thread calls the function)::

    from nodes.client import listen

    with listen("/slip", lambda state: state.slip and gripper.squeeze()):
        robot.run_task()

`timeout_s` makes silence an error (`TimeoutError`): a gripper that stops hearing the
slip detector should know. The bus is the one `FV_BUS` names (default: this host's).
"""
from __future__ import annotations

import logging
import threading
from typing import Callable, Iterator

from msgs import Message
from nodes.bus import TopicReader
from nodes.endpoints import BusAddress

log = logging.getLogger("fv.client")
POLL_S = 0.1


class Subscription:
    """Messages of one topic, read on demand; iterate it, or call `recv()`.

    msg_type: the expected class (TypeError for another), None for any.
    timeout_s: longest silence allowed while iterating, None = wait forever.
    latest: skip to the newest message when several are waiting (for control loops
    slower than the topic); default keeps every message in order.
    """

    def __init__(self, topic: str, msg_type: type[Message] | None = None, *, timeout_s: float | None = None,
                 latest: bool = False, address: BusAddress | None = None) -> None:
        self.topic = topic
        self.msg_type = msg_type
        self.timeout_s = timeout_s
        self.latest = latest
        self._reader = TopicReader([topic], address)

    def recv(self, timeout_s: float | None = None) -> Message | None:
        """The next message (the newest one waiting when `latest`), or None after `timeout_s`."""
        item = self._reader.recv(timeout_s)
        if item is None:
            return None
        if self.latest:
            while (newer := self._reader.recv(0)) is not None:
                item = newer
        if self.msg_type is not None and not isinstance(item.msg, self.msg_type):
            raise TypeError(f"{self.topic}: expected {self.msg_type.TYPE}, got {item.msg.TYPE} from {item.msg.node!r}")
        return item.msg

    def __iter__(self) -> Iterator[Message]:
        while True:
            msg = self.recv(self.timeout_s)
            if msg is None:
                raise TimeoutError(f"no message on {self.topic} within {self.timeout_s} s")
            yield msg

    @property
    def malformed(self) -> int:
        """Messages dropped because they could not be decoded."""
        return self._reader.malformed

    @property
    def gaps(self) -> int:
        """Messages missed, by sequence number."""
        return self._reader.seq.gaps

    def close(self) -> None:
        self._reader.close()

    def __enter__(self) -> "Subscription":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def subscribe(topic: str, msg_type: type[Message] | None = None, *, timeout_s: float | None = None,
              latest: bool = False, address: BusAddress | None = None) -> Subscription:
    """Subscribe to `topic`: ``for msg in subscribe("/slip"): ...`` (see `Subscription`)."""
    return Subscription(topic, msg_type, timeout_s=timeout_s, latest=latest, address=address)


def wait_for_message(topic: str, msg_type: type[Message] | None = None, timeout_s: float = 5.0,
                     address: BusAddress | None = None) -> Message:
    """The next message on `topic` (a latched one arrives at once); TimeoutError after `timeout_s`."""
    with Subscription(topic, msg_type, address=address) as sub:
        msg = sub.recv(timeout_s)
    if msg is None:
        raise TimeoutError(f"no message on {topic} within {timeout_s} s")
    return msg


class Listener:
    """Calls `callback(msg)` for each message of `topic` from a background thread until
    `close()`. A callback that raises is logged and counted in `errors`; the thread goes on."""

    def __init__(self, topic: str, callback: Callable[[Message], object], msg_type: type[Message] | None = None,
                 *, latest: bool = False, address: BusAddress | None = None) -> None:
        self.topic = topic
        self.callback = callback
        self.errors = 0
        self.received = 0
        self._stop = threading.Event()
        self._ready = threading.Event()
        self._args = (topic, msg_type, latest, address)
        self._thread = threading.Thread(target=self._loop, name=f"listen-{topic}", daemon=True)
        self._thread.start()
        self._ready.wait(2.0)

    def _loop(self) -> None:
        topic, msg_type, latest, address = self._args
        with Subscription(topic, msg_type, latest=latest, address=address) as sub:  # sockets stay in one thread
            self._ready.set()
            while not self._stop.is_set():
                msg = sub.recv(POLL_S)
                if msg is None:
                    continue
                self.received += 1
                try:
                    self.callback(msg)
                except Exception:  # robot code keeps listening; the error is logged and counted
                    self.errors += 1
                    log.exception("callback for %s raised", topic)

    def close(self, timeout_s: float = 1.0) -> None:
        self._stop.set()
        self._thread.join(timeout_s)

    def __enter__(self) -> "Listener":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def listen(topic: str, callback: Callable[[Message], object], msg_type: type[Message] | None = None, *,
           latest: bool = False, address: BusAddress | None = None) -> Listener:
    """Call `callback(msg)` for each message on `topic` in a background thread (see `Listener`)."""
    return Listener(topic, callback, msg_type, latest=latest, address=address)
