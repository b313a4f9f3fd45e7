"""`NodeStatus`: the periodic health report every node publishes on `/status`."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from msgs.message import Message


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
    publishes / subscribes: [topic, type] pairs of the node's endpoints.
    counters: node-specific counts (e.g. {"lost": 1, "reopened": 1}) plus the runtime's
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
