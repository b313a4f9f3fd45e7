"""`Backlog`: the messages the recorder's receive thread has stamped and its writer thread has yet to write.

Bounded, as the socket's receive queue it empties is (`queue_depth`): a writer that falls behind the bus (a
disk slower than the stream) cannot fill the memory. A message that arrives while `max_count` wait is dropped
(the newest goes, the backlog keeps its order) and counted under its topic in `dropped`.
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


class Backlog:
    """A bounded FIFO from one receiving thread to one writing thread.

    max_count: at most this many wait.
    """

    def __init__(self, max_count: int) -> None:
        if max_count <= 0:
            raise ValueError(f"max_count ({max_count}) must be > 0")
        self.max_count = max_count
        self.dropped: dict[str, int] = {}
        self._items: deque[Stamped] = deque()
        self._cond = threading.Condition()
        self._closed = False

    def put(self, item: Stamped) -> bool:
        """Queue `item`; False when it is dropped (counted) because the writer is too far behind."""
        with self._cond:
            if len(self._items) >= self.max_count:
                self.dropped[item.topic] = self.dropped.get(item.topic, 0) + 1
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

    @property
    def finished(self) -> bool:
        """Closed and emptied."""
        with self._cond:
            return self._closed and not self._items

    @property
    def total_dropped(self) -> int:
        with self._cond:
            return sum(self.dropped.values())
