"""`NodeStatus`: the periodic health report every node publishes on `/status`."""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import ClassVar

from msgs.message import Message

STATES = ("ok", "warn", "error")
MAX_AHEAD_S = 60.0  # a status stamped further ahead of the reader's clock is refused (it would look alive for good)


@dataclass(kw_only=True)
class NodeStatus(Message):
    """Health of one node over the last status period.

    state: "ok", "warn" (degraded: e.g. camera lost and reopening, an input overdue, the
    forwarder unreachable) or "error" (e.g. a callback stuck, a recording failed).
    message: the current warnings and errors, worst first, joined by "; " ("" when none),
    e.g. "callback on_image (/camera/image) stuck for 6.2 s; no /markers for 2.1 s".
    rate_hz: callbacks processed per second; proc_ms_mean / proc_ms_p99: callback time.
    drops: messages dropped by keep-last queues; gaps: messages missing by sequence
    number; malformed: undecodable messages dropped; errors: callbacks that raised.
    publishes / subscribes: [topic, type] pairs of text, the node's endpoints.
    stamp_ns: when it was published; one more than `MAX_AHEAD_S` ahead of the reader's clock is refused.
    counters: {name: number}, node-specific counts (e.g. {"lost": 1, "reopened": 1}) plus the runtime's
    "bus_reconnects" (forwarder restarts survived) and "stuck_callbacks" (watchdog reports).
    """

    TYPE: ClassVar[str] = "NodeStatus"
    VERSION: ClassVar[int] = 1

    state: str = "ok"
    message: str = ""
    pid: int = 0
    uptime_s: float = 0.0
    rate_hz: float = 0.0
    proc_ms_mean: float = 0.0
    proc_ms_p99: float = 0.0
    drops: int = 0
    gaps: int = 0
    malformed: int = 0
    errors: int = 0
    cpu_percent: float = 0.0
    rss_bytes: int = 0
    publishes: list = field(default_factory=list)
    subscribes: list = field(default_factory=list)
    counters: dict = field(default_factory=dict)

    def validate(self) -> None:
        """Also check what `fv topic list / info` and `fv node list` read: a latched status with a
        [topic] of one item broke them for every user of the bus ("not enough values to unpack")."""
        super().validate()
        if self.state not in STATES:
            raise ValueError(f"state: {self.state!r} is not one of {STATES}")
        for name in ("publishes", "subscribes"):
            for end in getattr(self, name):
                if not (isinstance(end, list) and len(end) == 2 and all(isinstance(s, str) for s in end)):
                    raise ValueError(f"{name}: {end!r:.80} is not a [topic, type] pair of text")
        for key, value in self.counters.items():
            if not isinstance(key, str) or not isinstance(value, (int, float)) or isinstance(value, bool):
                raise ValueError(f"counters: {key!r:.40}: {value!r:.40} is not a name and a number")
        ahead_s = (self.stamp_ns - time.time_ns()) / 1e9
        if ahead_s > MAX_AHEAD_S:
            raise ValueError(f"stamp_ns: {ahead_s:.0f} s ahead of this host's clock (more than {MAX_AHEAD_S:g} s)")
