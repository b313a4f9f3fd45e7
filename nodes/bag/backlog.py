"""`Backlog`: the messages the recorder's receive thread has stamped and its writer thread has yet to write.

Bounded, as the socket's receive queue it empties is (`queue_depth`): a writer that falls behind the bus (a
disk slower than the stream) cannot fill the memory. A message that arrives while `max_count` wait is dropped
(the newest goes, the backlog keeps its order) and counted under its topic in `dropped`. A writer that fails
`abandon`s it: the messages waiting then, the one it failed on and every one put after are counted under their
topic in `lost`, so that each message put is either taken by the writer, dropped or lost.
"""
from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Stamped:
    """One received message as the writer stores it: its bus frames (header first), the decoded header and
    `log_time_ns`, the wall time (ns) the receive thread took it from the socket."""

    topic: str
    node: str
    latched: bool
    frames: list[Any]
    header: dict[str, Any]
    log_time_ns: int


def _count(counts: dict[str, int], topic: str, n: int = 1) -> None:
    counts[topic] = counts.get(topic, 0) + n


class Backlog:
    """A bounded FIFO from one receiving thread to one writing thread.

    max_count: at most this many wait.
    """

    def __init__(self, max_count: int) -> None:
        if max_count <= 0:
            raise ValueError(f"max_count ({max_count}) must be > 0")
        self.max_count = max_count
        self.dropped: dict[str, int] = {}
        self.lost: dict[str, int] = {}
        self._items: deque[Stamped] = deque()
        self._cond = threading.Condition()
        self._closed = False
        self._abandoned = False

    def put(self, item: Stamped) -> bool:
        """Queue `item`; False when it is dropped (counted) because the writer is too far behind, or lost
        (counted) because the writer failed."""
        with self._cond:
            if self._abandoned:
                _count(self.lost, item.topic)
                return False
            if len(self._items) >= self.max_count:
                _count(self.dropped, item.topic)
                return False
            self._items.append(item)
            self._cond.notify()
            return True

    def get(self, timeout_s: float) -> Stamped | None:
        """The oldest waiting message, or None when none comes within `timeout_s` or the backlog is finished."""
        with self._cond:
            self._cond.wait_for(lambda: self._items or self._closed, timeout_s)
            return self._items.popleft() if self._items else None

    def close(self) -> None:
        """No more messages will come: `finished` once the waiting ones are taken."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def abandon(self, unwritten: Stamped | None = None, unstored: dict[str, int] | None = None) -> None:
        """The writer failed and takes no more: the waiting messages, `unwritten` (the one it failed on, if
        any), `unstored` ({topic: count} it took that the file did not) and every message put from now on are
        counted under their topic in `lost`."""
        with self._cond:
            self._abandoned = True
            for item in ([unwritten] if unwritten is not None else []) + list(self._items):
                _count(self.lost, item.topic)
            for topic, count in (unstored or {}).items():
                _count(self.lost, topic, count)
            self._items.clear()

    @property
    def finished(self) -> bool:
        """Closed and emptied."""
        with self._cond:
            return self._closed and not self._items

    @property
    def total_dropped(self) -> int:
        with self._cond:
            return sum(self.dropped.values())

    @property
    def total_lost(self) -> int:
        with self._cond:
            return sum(self.lost.values())
